"""report.html: a self-contained page with the model's quality measures and convergence."""

from __future__ import annotations

import base64
import html
import io as _io
from pathlib import Path

import numpy as np

from . import io


def _figure_to_base64(figure) -> str:
    buffer = _io.BytesIO()
    figure.savefig(buffer, format="png", dpi=90, bbox_inches="tight")
    return base64.b64encode(buffer.getvalue()).decode("ascii")


def _measure_plots(metrics: dict) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    modes = np.asarray(metrics["modes"])
    series = [(metrics, f"optimised ({metrics['strategy']})", 0.0)]
    if "baseline" in metrics:
        series.append((metrics["baseline"], "initial correspondence", 0.15))
    for axis, key, label in zip(axes, ("compactness", "generalization", "specificity"),
                                ("Compactness C(M) [mm²]", "Generalization G(M) [mm²]",
                                 "Specificity S(M) [mm²]")):
        for values, name, shift in series:
            axis.errorbar(modes + shift, values[key], yerr=values[key + "_se"], marker="o",
                          capsize=3, label=name)
        axis.set_xlabel("number of modes M")
        axis.set_title(label)
        axis.grid(alpha=0.3)
    axes[0].legend()
    encoded = _figure_to_base64(figure)
    plt.close(figure)
    return encoded


def _convergence_plot(path: Path) -> str | None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = io.read_csv(path) if path.exists() else []
    if len(rows) < 2:
        return None
    titles = {"fixed": "fixed-Delta objective (eq. 13)", "integrated": "objective (eq. 14)"}
    phases = [p for p in titles if any(r["phase"] == p for r in rows)]
    figure, axes = plt.subplots(1, len(phases), figsize=(5.5 * len(phases), 3.4), squeeze=False)
    for axis, phase in zip(axes[0], phases):  # one panel per phase: their scales differ
        selected = [r for r in rows if r["phase"] == phase]
        axis.plot([float(r["wall_seconds"]) for r in selected],
                  [float(r["objective"]) for r in selected])
        axis.set_title(titles[phase])
        axis.set_xlabel("wall seconds")
        axis.set_ylabel("F [nats]")
        axis.grid(alpha=0.3)
    encoded = _figure_to_base64(figure)
    plt.close(figure)
    return encoded


def _table(header, rows) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(_fmt(v))}</td>" for v in row) + "</tr>"
                   for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _fmt(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def write_report(output: Path, metrics: dict, cases: list, rejected: list) -> Path:
    """Write ``output/report.html`` and return its path."""
    measures = _measure_plots(metrics)
    convergence = _convergence_plot(output / "convergence.csv")
    objective = metrics["objective"]
    rows = [(m, metrics["compactness"][k], metrics["compactness_se"][k],
             metrics["generalization"][k], metrics["generalization_se"][k],
             metrics["specificity"][k], metrics["specificity_se"][k])
            for k, m in enumerate(metrics["modes"])]
    if "baseline" in metrics:
        base = metrics["baseline"]
        rows = [row + (base["generalization"][k], base["specificity"][k])
                for k, row in enumerate(rows)]
        header = ("M", "C(M)", "SE", "G(M)", "SE", "S(M)", "SE", "G(M) initial", "S(M) initial")
    else:
        header = ("M", "C(M)", "SE", "G(M)", "SE", "S(M)", "SE")
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>MDLShapeModel report</title>",
        "<style>body{font-family:sans-serif;margin:2em;max-width:1100px}table{border-collapse:"
        "collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}"
        "th{background:#eee}</style></head><body>",
        "<h1>MDLShapeModel report</h1>",
        f"<p>{metrics['n_shapes']} shapes, {metrics['n_points']} points each, strategy "
        f"<b>{html.escape(metrics['strategy'])}</b>; {metrics['n_rejected']} input(s) rejected. "
        f"Objective (eq. 14): {objective['initial']:.3f} before, {objective['final']:.3f} after "
        f"optimisation{' (interrupted)' if metrics['interrupted'] else ''}.</p>",
        "<h2>Model quality (area-weighted squared distances, ± 1 standard error)</h2>",
        f"<img src='data:image/png;base64,{measures}' alt='quality measures'>",
        _table(header, rows),
    ]
    if convergence:
        parts += ["<h2>Convergence</h2>",
                  f"<img src='data:image/png;base64,{convergence}' alt='convergence'>"]
    if cases:
        keys = list(cases[0].keys())
        parts += ["<h2>Cases</h2>", _table(keys, [[c.get(k, "") for k in keys] for c in cases])]
    if rejected:
        parts += ["<h2>Rejected inputs</h2>",
                  _table(("case", "file", "reason"), [(r.name, r.path, r.reason) for r in rejected])]
    parts.append("</body></html>")
    path = output / "report.html"
    path.write_text("\n".join(parts))
    return path
