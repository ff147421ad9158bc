"""Side-by-side evaluation of several models of the same cases: the computing and the page of
``mdlshapemodel compare`` (whose loading and writing are :mod:`mdlshapemodel.compare`'s).

Every model is evaluated again on the cases all of them share, with the same number of modes, the
same specificity samples and the same random seed, so that the measures are comparable. A
difference between two models at M modes is called significant when it exceeds two standard errors
of the difference (the paper's criterion for its error bars, IV-B).

Generalization is measured case by case on the same cases, so its difference is paired: the mean
of the per-case differences of the leave-one-out errors. Its standard error is a jackknife over
the cases (:func:`mdlshapemodel.model.evaluation.generalization_difference`): the spread of the
per-case differences alone would understate it, since each case's leave-one-out error depends on
the model of all the others, and the unpaired sqrt(SE_a^2 + SE_b^2) would count the spread between
cases, which both models share, as noise. Compactness (no per-case values) and specificity
(per-sample values of two different models) keep sqrt(SE_a^2 + SE_b^2); the specificity's SE is
the Monte Carlo error of its samples, so two builds that differ only in their seed, being
different models, can be told apart. False positives and power: benchmarks/compare_calibration.py.
"""

from __future__ import annotations

import html
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..folders import BuildFolder
from ..model.evaluation import (COMPARED_MEASURES, SIGNIFICANT_SE, evaluate, measure_differences,
                                verdict)

MEASURES = COMPARED_MEASURES
# the jackknife of the generalization difference leaves each case out and then each other case:
# with fewer than 4, a leave-one-out model of the jackknife's populations has no mode
MIN_SHARED_CASES = 4


@dataclass
class Population:
    """The aligned training shapes of one model, by case name."""

    label: str
    names: list
    shapes: np.ndarray
    weights: np.ndarray
    folder: str = ""          # the build's output folder it was read from ("" when none)


def compare_populations(populations: list, max_modes: int = 10, n_samples: int = 10_000,
                        seed: int = 0) -> dict:
    """Evaluate every population on the cases they share; differences against the first.

    Returns a JSON-ready dict: ``cases`` (shared), ``models`` (label -> measures as from
    :func:`mdlshapemodel.model.evaluation.evaluate`) and ``differences`` (label -> measure -> per M:
    difference to the first model, its standard error, and whether it exceeds two of them;
    ``paired`` says whether the difference is over the same cases, with the jackknife's standard
    error (:func:`mdlshapemodel.model.evaluation.generalization_difference`), as for
    generalization, or of two independent estimates, with sqrt(SE_a^2 + SE_b^2)).
    """
    if not populations:
        raise InputError("nothing to compare")
    # each population's row of a case name (its first, as with list.index): one look-up per
    # shared case, not a scan of the names
    positions = [{} for _ in populations]
    for population, position in zip(populations, positions):
        for i, name in enumerate(population.names):
            position.setdefault(name, i)
    shared = [n for n in populations[0].names if all(n in p for p in positions[1:])]
    if len(shared) < MIN_SHARED_CASES:
        raise InputError(f"the models share only {len(shared)} case(s); at least "
                         f"{MIN_SHARED_CASES} are needed")
    shared_set = set(shared)
    models = {}
    jackknifes = {}         # each population's leave-one-out errors, for paired differences
    for population, position in zip(populations, positions):
        index = [position[n] for n in shared]
        shapes = population.shapes[index]
        # one decomposition of the shapes serves the model's variances (variances=None: the
        # rule of ShapeModel.from_shapes), every measure and the generalization's jackknife
        measures = evaluate(shapes, population.weights, None, max_modes, n_samples,
                            np.random.default_rng(seed), jackknife=True)
        jackknifes[population.label] = measures.pop("jackknife")     # not JSON
        models[population.label] = measures
    reference = populations[0].label
    differences = {label: measure_differences(models[reference], values, jackknifes[reference],
                                              jackknifes[label])
                   for label, values in models.items() if label != reference}
    return {"reference": reference, "cases": shared, "n_cases": len(shared),
            "excluded_cases": {p.label: [n for n in p.names if n not in shared_set]
                               for p in populations},
            "models": models, "differences": differences,
            "folders": {p.label: p.folder for p in populations}}


def _shown(found: str) -> str:
    """A verdict (:func:`~mdlshapemodel.model.evaluation.verdict`) as the tables say it."""
    return f"same (within {SIGNIFICANT_SE:g} SE)" if found == "same" else found


def comparison_rows(result: dict) -> list:
    """Flat rows: measure, M, model, value, SE, difference to reference, its SE, verdict."""
    rows = []
    reference = result["reference"]
    for measure in MEASURES:
        for label, values in result["models"].items():
            for k, m in enumerate(values["modes"]):
                if label == reference:
                    extra = ("", "", "reference")
                else:
                    d = result["differences"][label][measure]
                    extra = (d["difference"][k], d["se"][k],
                             _shown(verdict(d["difference"][k], d["se"][k])))
                rows.append((measure, m, label, values[measure][k], values[measure + "_se"][k])
                            + extra)
    return rows


ROW_HEADER = ("measure", "M", "model", "value_mm2", "se", "difference", "difference_se",
              "verdict")


def comparison_page(result: dict, destination) -> str:
    """compare.html of a comparison (self-contained, with the measures' plot and a viewer of
    each model); its links to the builds' reports are relative to ``destination``, the folder
    it goes to."""
    import os

    from .html import HOW_TO_READ, html_page, measure_plot, run_table, table

    rows = comparison_rows(result)
    series = [(values, label) for label, values in result["models"].items()]
    plot = measure_plot(series)
    body = [f"<h1>Comparison of {len(series)} models</h1>",
            f"<p>{result['n_cases']} shared cases; differences are against "
            f"<b>{html.escape(result['reference'])}</b> and called significant beyond two "
            "standard errors of the difference (for generalization, the cases being the same, a "
            "jackknife over them). Lower is better for all three measures.</p>",
            f"<img src='data:image/png;base64,{plot}' alt='measures'>", HOW_TO_READ,
            "<h2>What was run</h2>", run_table()]
    models = []
    for label, folder in result.get("folders", {}).items():
        report = BuildFolder(folder).report_file if folder else None
        link = (f" (<a href='{html.escape(os.path.relpath(report, destination))}'>its report"
                f"</a>)" if report is not None and report.exists() else "")
        models.append(f"<li>{html.escape(label)}: <code>{html.escape(folder)}</code>{link}</li>")
    if models:
        body += ["<h3>The models</h3>", f"<ul>{''.join(models)}</ul>"]
    body += _viewers(result)
    for measure in MEASURES:
        body += [f"<h2>{measure}</h2>", table(ROW_HEADER[1:], [r[1:] for r in rows
                                                               if r[0] == measure])]
    excluded = {k: v for k, v in result["excluded_cases"].items() if v}
    if excluded:
        body.append("<h2>Cases left out (not in every model)</h2>")
        body.append(table(("model", "cases"), [(k, ", ".join(v)) for k, v in excluded.items()]))
    return html_page("MDLShapeModel comparison", body)


def _viewers(result: dict) -> list:
    """An interactive viewer of each model's mean and modes (plotly.js once for all)."""
    from .viewer import viewer_section

    parts = []
    for label, folder in result.get("folders", {}).items():
        build = BuildFolder(folder) if folder else None
        if build is None or not build.model_file.exists():
            continue
        section = viewer_section(build.model(), prefix=f"viewer{len(parts)}",
                                 heading=f"<h3>{html.escape(label)}</h3>",
                                 with_plotly=not parts)
        if any("id='viewer" in fragment for fragment in section):
            parts.append(section)
    if not parts:
        return []
    return ["<h2>The models in 3-D</h2>", "<p>Each model's mean, with its first modes on the "
            "sliders (drag to turn, scroll to zoom).</p>"] + [f for p in parts for f in p]


def summary_lines(result: dict, max_rows: int = 10) -> list:
    """A short text table per measure for the terminal."""
    lines = []
    labels = list(result["models"])
    for measure in MEASURES[1:]:
        lines.append(f"{measure} [mm^2 +- SE]; verdict against {result['reference']}")
        for label in labels:
            values = result["models"][label]
            cells = []
            for k in range(min(max_rows, len(values["modes"]))):
                cell = f"{values[measure][k]:.3f}+-{values[measure + '_se'][k]:.3f}"
                significant = (label != result["reference"] and
                               result["differences"][label][measure]["significant"][k])
                cell += "*" if significant else " "
                cells.append(cell)
            lines.append(f"  {label[:30]:<30} " + " ".join(cells))
    lines.append("  (* : differs from the reference by more than 2 SE)")
    return lines
