"""Figures of 2-D models (curves): the modes as curves at -3, 0, +3 SD, the correspondence as
coloured points (matplotlib; the 3-D renderings are :mod:`.rendering`).

A 2-D model keeps its points as (n_p, 3) with z = 0 and its connectivity as segments (m, 2),
one closed polyline per part.
"""

from __future__ import annotations

import numpy as np

from .figures import encoded_png, pyplot


def _draw(axes, points: np.ndarray, segments: np.ndarray, **style):
    from matplotlib.collections import LineCollection

    axes.add_collection(LineCollection(points[segments][:, :, :2], **style))


def _frame(axes, shapes):
    low, high = shapes[..., :2].reshape(-1, 2).min(0), shapes[..., :2].reshape(-1, 2).max(0)
    margin = 0.05 * float(np.max(high - low))
    axes.set_xlim(low[0] - margin, high[0] + margin)
    axes.set_ylim(low[1] - margin, high[1] + margin)
    axes.set_aspect("equal")
    axes.set_xticks([])
    axes.set_yticks([])


def mode_curves(model, n_modes: int = 3, standard_deviations=(-3.0, 0.0, 3.0)) -> str:
    """Base64 PNG: one panel per mode (at most ``n_modes``), the mean and the shapes at
    ``standard_deviations`` of that mode drawn as curves (the classic figure of 2-D models)."""
    plt = pyplot()
    n_modes = max(1, min(n_modes, model.n_modes))
    figure, panels = plt.subplots(1, n_modes, figsize=(3.2 * n_modes, 3.4), squeeze=False)
    colours = {s: plt.get_cmap("coolwarm")(0.5 + s / (2.0 * max(map(abs, standard_deviations))
                                                       or 1.0)) for s in standard_deviations}
    for k, axes in enumerate(panels[0]):
        shapes = []
        for s in standard_deviations:
            scores = np.zeros(k + 1)
            if k < model.n_modes:
                scores[k] = s * np.sqrt(max(float(model.variances[k]), 0.0))
            shape = model.instance(scores)
            shapes.append(shape)
            _draw(axes, shape, model.triangles, colors=[colours[s]],
                  linewidths=2.0 if s == 0 else 1.2, label=f"{s:+g} SD" if s else "mean")
        _frame(axes, np.stack(shapes))
        variance = float(model.variances[k]) if k < model.n_modes else 0.0
        axes.set_title(f"mode {k + 1}: √λ = {np.sqrt(max(variance, 0.0)):.3g} mm", fontsize=9)
    panels[0][0].legend(fontsize=7, loc="best")
    return encoded_png(figure)


def correspondence_points(shapes: np.ndarray, segments: np.ndarray, names=None,
                          max_cases: int = 4) -> str:
    """Base64 PNG: a few cases' curves with their sample points coloured by index: the same colour is
    the same point of the model on every case."""
    plt = pyplot()
    shapes = np.asarray(shapes)
    chosen = np.unique(np.linspace(0, len(shapes) - 1, min(max_cases, len(shapes))).astype(int))
    figure, panels = plt.subplots(1, len(chosen), figsize=(3.2 * len(chosen), 3.4),
                                  squeeze=False)
    colour = np.arange(shapes.shape[1])
    for axes, i in zip(panels[0], chosen):
        _draw(axes, shapes[i], segments, colors="0.6", linewidths=0.8)
        axes.scatter(shapes[i, :, 0], shapes[i, :, 1], c=colour, cmap="hsv", s=9)
        _frame(axes, shapes[i][None])
        if names is not None:
            axes.set_title(str(names[i]), fontsize=9)
    return encoded_png(figure)
