"""report.html: one self-contained page per build (images embedded as base64 PNG).

Sections: what was run (version, date, command, settings, links to the output files), the quality
measures with error bars against the baselines of the same cases and how to read them, the
convergence of the objective, the first modes rendered at -2, 0, +2 standard deviations from
three sides (as the paper's Fig. 12-15), the correspondence as a colour map on a few cases (Fig.
22-23), the interactive viewer, and a per-case table (surface fidelity, sphere-map distortion,
score outliers) with readable headers and units.
"""

from __future__ import annotations

import base64
import html
import logging
from pathlib import Path

import numpy as np

from .. import folders
from ..correspondence.trace import stop_summary
from ..errors import MDLShapeModelError
from ..model.evaluation import verdict
from ..prepare import io
from .figures import encoded_png, pyplot

log = logging.getLogger("mdlshapemodel")

BASELINE_NAMES = {"none": "initial correspondence (--strategy none)",
                  "cpd": "CPD template registration"}
STYLE = ("body{font-family:sans-serif;margin:2em;max-width:1150px}table{border-collapse:collapse;"
         "margin:1em 0}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}"
         "th{background:#eee}td.flag{color:#b00;font-weight:bold}img{max-width:100%}"
         # a long command line (hundreds of input paths) wraps in a box of a few lines that
         # scrolls, instead of widening the page
         "pre.command{white-space:pre-wrap;overflow-wrap:anywhere;max-height:7.5em;"
         "overflow:auto;background:#f6f6f6;border:1px solid #ccc;padding:4px 8px;margin:0}"
         # the cases table scrolls sideways in its box, the case name and its flags pinned
         "div.cases{overflow-x:auto;max-width:100%}div.cases table{margin:0}"
         "div.cases td:nth-child(-n+2),div.cases th:nth-child(-n+2){position:sticky;"
         "box-sizing:border-box;text-align:left;overflow-wrap:anywhere;z-index:1}"
         "div.cases td:nth-child(-n+2){background:#fff}"
         "div.cases td:first-child,div.cases th:first-child{left:0;width:11em;min-width:11em;"
         "max-width:11em}div.cases td:nth-child(2),div.cases th:nth-child(2){left:11em;"
         "min-width:9em;max-width:16em}"
         "div.flagged{border:2px solid #b00;padding:0 1em;margin:1em 0}")


def measure_plot(series: list, keys=("compactness", "generalization", "specificity")) -> str:
    """Base64 PNG: one panel per measure, one error-bar line per (values, label) in ``series``."""
    plt = pyplot()
    titles = {"compactness": "Compactness C(M) [mm²]", "generalization": "Generalization G(M) [mm²]",
              "specificity": "Specificity S(M) [mm²]",
              "generalization_surface_mm": "Generalization, surface distance [mm]",
              "specificity_surface_mm": "Specificity, surface distance [mm]"}
    figure, axes = plt.subplots(1, len(keys), figsize=(4.4 * len(keys), 3.6), squeeze=False)
    for axis, key in zip(axes[0], keys):
        for index, (values, label) in enumerate(series):
            if key not in values:
                continue
            modes = np.asarray(values["modes"]) + 0.12 * index
            axis.errorbar(modes, values[key], yerr=values[key + "_se"], marker="o", ms=3,
                          capsize=3, label=label)
        axis.set_xlabel("number of modes M")
        axis.set_title(titles.get(key, key))
        axis.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    return encoded_png(figure)


def convergence_plot(path: Path) -> str | None:
    """Base64 PNG of convergence.csv, one panel per objective phase (their scales differ)."""
    rows = io.read_csv(path) if path.exists() else []
    if len(rows) < 2:
        return None
    plt = pyplot()
    titles = {"coarse fixed": "fixed-Delta objective (eq. 13), coarse grid",
              "coarse integrated": "objective (eq. 14), coarse grid",
              "fixed": "fixed-Delta objective (eq. 13)", "integrated": "objective (eq. 14)"}
    phases = [p for p in titles if any(r["phase"] == p for r in rows)]
    figure, axes = plt.subplots(1, len(phases), figsize=(5.5 * len(phases), 3.4), squeeze=False)
    for axis, phase in zip(axes[0], phases):
        selected = [r for r in rows if r["phase"] == phase]
        axis.plot([float(r["wall_seconds"]) for r in selected],
                  [float(r["objective"]) for r in selected])
        axis.set_title(titles[phase])
        axis.set_xlabel("wall seconds")
        axis.set_ylabel("F [nats]")
        axis.grid(alpha=0.3)
    return encoded_png(figure)


def table(header, rows, flags=None) -> str:
    """An HTML table; ``flags[i][j]`` true marks cell (i, j); no header row when ``header`` is
    None."""
    head = ("" if header is None else
            "<thead><tr>" + "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
            + "</tr></thead>")
    body = []
    for i, row in enumerate(rows):
        cells = []
        for j, value in enumerate(row):
            flagged = flags is not None and flags[i][j]
            cells.append(f"<td{' class=flag' if flagged else ''}>{html.escape(_fmt(value))}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table>{head}<tbody>{''.join(body)}</tbody></table>"


def _fmt(value) -> str:
    if isinstance(value, (float, np.floating)):
        return f"{value:.4g}"
    return str(value)


def html_page(title: str, body: list) -> str:
    return "\n".join([f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>"
                      f"{html.escape(title)}</title><style>{STYLE}</style></head><body>",
                      *body, "</body></html>"])


def image_tag(encoded: str, alt: str) -> str:
    """An <img> of a base64-encoded PNG, with its alternative text."""
    return f"<img src='data:image/png;base64,{encoded}' alt='{html.escape(alt)}'>"


def _series(metrics: dict) -> list:
    series = [(metrics, f"MDL ({metrics['strategy']})")]
    for name, values in metrics.get("baselines", {}).items():
        series.append((values, BASELINE_NAMES.get(name, name)))
    return series


def _baseline_cell(values: dict, key: str, k: int) -> tuple[str, bool]:
    """A baseline's value ± SE at the k-th M, with the verdict of the model against it where
    metrics.json records their difference (``differences``, the model's minus the
    baseline's: the rule of ``mdlshapemodel compare``), and whether the model is worse."""
    cell = f"{values[key][k]:.4g} ± {values[key + '_se'][k]:.2g}"
    found = values.get("differences", {}).get(key)
    if found is None:
        return cell, False
    difference, se = found["difference"][k], found["se"][k]
    said = verdict(difference, se)
    if said != "same":
        cell += f" (MDL {said} by {abs(difference):.2g} ± {se:.2g})"
    return cell, said == "worse"


def _measure_table(metrics: dict) -> str:
    """Values ± SE per M; the baselines' G and S with the verdict of the MDL model against
    each (:func:`~mdlshapemodel.model.evaluation.verdict`), a flag where it is worse."""
    baselines = metrics.get("baselines", {})
    header = ["M", "C(M)", "G(M)", "S(M)"]
    for name in baselines:
        header += [f"G {name}", f"S {name}"]
    rows, flags = [], []
    for k, m in enumerate(metrics["modes"]):
        row = [m] + [f"{metrics[key][k]:.4g} ± {metrics[key + '_se'][k]:.2g}"
                     for key in ("compactness", "generalization", "specificity")]
        flag = [False] * 4
        for values in baselines.values():
            for key in ("generalization", "specificity"):
                cell, worse = _baseline_cell(values, key, k)
                row.append(cell)
                flag.append(worse)
        rows.append(row)
        flags.append(flag)
    return table(header, rows, flags)


def _subsample_note(metrics: dict) -> list:
    """Where the generalization left out a random subset of the cases
    (:func:`~mdlshapemodel.model.evaluation.leave_out_cases`), a sentence that says so."""
    if "generalization_cases" not in metrics:
        return []
    part = metrics["generalization_subsample_se"][0]
    return [f"<p id=generalization-cases>G(M) is estimated from a random sample of "
            f"{metrics['generalization_cases']} of the {metrics['n_shapes']} cases, each left "
            f"out in turn and reconstructed by the model of all the others (the build's "
            f"<code>generalization_cases</code>); its ± is over those cases and includes the "
            f"sample's own error as an estimate of the mean over all the cases (for G(1): "
            f"{part:.2g}; <code>generalization_subsample_se</code> in {folders.METRICS}).</p>"]


def _flagged_part(metrics: dict) -> list:
    """The cases the build's checks flag (metrics.json ``flagged_cases``), named with why: at
    the top of the report, so that they are seen before the model is used."""
    flagged = metrics.get("flagged_cases")
    if flagged is None:
        return []
    if not flagged:
        return ["<p id=flagged>No case is flagged by the build's checks (score outliers, "
                "normals off).</p>"]
    items = "".join(f"<li><b>{html.escape(name)}</b>: {html.escape('; '.join(reasons))}</li>"
                    for name, reasons in flagged.items())
    return [f"<div id=flagged class=flagged><p><b>{len(flagged)} case(s) flagged</b> by the "
            "build's checks: look at them before using the model (the case table at the end "
            f"has them in its column 'flagged: why').</p><ul>{items}</ul></div>"]


def _renderings(model, shapes, names) -> list:
    """The mode and correspondence images, or a note when offscreen rendering is unavailable."""
    if model is None or model.triangles is None:
        return []
    from . import curves, rendering

    if model.of_curves:
        parts = ["<h2>Modes of variation</h2>",
                 "<p>The mean curve and the curves at ± 3 standard deviations along the first "
                 "modes.</p>", image_tag(curves.mode_curves(model), "modes of variation")]
        if shapes is not None:
            parts += ["<h2>Correspondence</h2>",
                      "<p>The sample points coloured by their index: the same colour is the "
                      "same model point on every case.</p>",
                      image_tag(curves.correspondence_points(shapes, model.triangles, names),
                             "correspondence")]
        return parts

    parts = []
    try:
        parts += ["<h2>Modes of variation</h2>",
                  "<p>Mean shape ± 2 standard deviations along the first modes; colour: "
                  "displacement from the mean along its normal (mm; blue inward, red outward), "
                  "from three sides (looking along the mean's shortest, middle and longest "
                  "axis).</p>"]
        for view in rendering.MODE_VIEWS:
            modes = base64.b64encode(rendering.render_modes(model, view=view)).decode("ascii")
            parts += [f"<h3>{view}</h3>", image_tag(modes, f"modes of variation, {view}")]
        if shapes is not None:
            colours = base64.b64encode(rendering.render_correspondence(
                shapes, model.triangles, names=names)).decode("ascii")
            parts += ["<h2>Correspondence</h2>",
                      "<p>The same colour marks corresponding points on every case.</p>",
                      image_tag(colours, "correspondence colour map")]
    except (MDLShapeModelError, RuntimeError) as error:
        log.warning("report: no renderings (%s)", error)
        parts.append(f"<p>Renderings left out: {html.escape(str(error))}</p>")
    return parts


def _normals_section(model, normals, names) -> list:
    """How well the cases' normals agree at each model point (model/normals.py): the count of
    flagged points, a map of the spread on the mean (surfaces), the cases most often off."""
    from ..model.normals import OFF_DEGREES, SPREAD_DEGREES

    spread = normals.spread_degrees
    flagged = int(np.count_nonzero(normals.flagged))
    parts = ["<h2>Correspondence check: normals</h2>",
             f"<p>At each model point, the mean angle between the aligned cases' surface normals "
             f"and their mean direction. Where the points of the cases are the same anatomical "
             f"place their normals agree, up to the shapes' own variation; where they spread "
             f"widely, the correspondence there is likely wrong (a region turned or twisted in "
             f"some cases). The spread does not rank two correspondences: the shapes' own "
             f"variation spreads normals too. <b>{flagged} of {len(spread)} points "
             f"({100.0 * flagged / len(spread):.1f}%)</b> spread more than "
             f"{SPREAD_DEGREES:.0f}°; median spread {np.median(spread):.1f}°. Every point's "
             f"value is in {folders.MEAN} (point arrays normal_spread_degrees and "
             f"normal_agreement, "
             f"the mean resultant length).</p>"]
    if not model.of_curves:
        from . import rendering

        try:
            image = rendering.render_maps(model.mean, model.triangles, [
                ("normal spread", spread, "viridis", 0.0, max(2 * SPREAD_DEGREES, 1e-9),
                 "mean angle to the mean normal [°]")], outlined=normals.flagged)
            parts += [image_tag(base64.b64encode(image).decode("ascii"), "normal spread"),
                      f"<p>Outlined: points spreading more than {SPREAD_DEGREES:.0f}°.</p>"]
        except (MDLShapeModelError, RuntimeError) as error:
            log.warning("report: no normal map (%s)", error)
    off = normals.cases_off()
    worst = [i for i in np.argsort(-off, kind="stable")[:5] if off[i] > 0]
    if worst:
        parts += [f"<p>Cases with the most points whose normal is more than {OFF_DEGREES:.0f}° "
                  "from the mean direction (column 'normals off' of the case table):</p>",
                  table(("case", "points"), [(names[i] if names is not None else str(i),
                                              int(off[i])) for i in worst])]
    return parts


# The per-case table's columns (cases.csv) as the report heads them, with their units.
CASE_COLUMNS = {
    "case": "case", "flags": "flagged: why", "file": "input file",
    "surface_vertices": "surface vertices",
    "mean_distance_mm": "mean distance to the input [mm]",
    "max_distance_mm": "largest distance to the input [mm]",
    "mean_distance_voxels": "mean distance to the input [voxels]",
    "sphere_flips": "sphere map: flipped triangles",
    "sphere_mean_abs_log_area": "sphere map: mean |ln area ratio|",
    "sphere_p95_abs_log_area": "sphere map: 95th percentile |ln area ratio|",
    "sphere_seconds": "sphere map [s]", "warps": "warps", "warp_kinds": "warp kinds",
    "normals_off": "normals off (points)",
    "mahalanobis": "Mahalanobis distance", "unusual_p": "p (empirical null)",
    "unusual_p_normal": "p (assuming normality)", "score_outlier": "outlier (p < 0.01)",
    "smoothing_sigma": "blur [voxels]", "repair": "repaired", "mirrored": "mirrored"}

# The files of a build's output folder that the report links to, and what each holds.
OUTPUT_FILES = (
    (folders.MODEL, "the model (Statismo/Scalismo format, with this package's exact copy)"),
    (folders.MEAN, "the mean shape"),
    (folders.CORRESPONDENCE + "/", "each case's corresponded mesh, in its input's space"),
    (folders.ALIGNED + "/", "each case's corresponded mesh in the model's frame"),
    (folders.SCORES, "each case's scores per mode"), (folders.CASES, "the table below"),
    (folders.LANDMARKS, "each case's corresponded landmarks beside the ones given"),
    (folders.METRICS, "every number of this page"),
    (folders.CONVERGENCE, "the objective by time"),
    (folders.CONFIG, "every setting of the build"),
    (folders.REJECTED, "inputs left out and why"), (folders.LOG, "the build's log"))


def _landmarks_section(summary: dict) -> list:
    """The landmarks that guided the correspondence (metrics.json ``landmarks``): per label, how
    far the cases' corresponded landmarks lie from the given ones."""
    rows = [(label, item["cases"], item["mean_mm"], item["max_mm"], item["max_case"])
            for label, item in summary["per_label"].items()]
    return ["<h2>Landmarks that guided the correspondence</h2>",
            f"<p>{len(summary['labels'])} labels, {summary['given']} landmarks given. Each "
            "case's corresponded landmark is the model point of its label; its distance from "
            f"the landmark given shows how closely the correspondence follows it "
            f"({folders.LANDMARKS} has every case's).</p>",
            table(("label", "cases", "mean distance [mm]", "largest [mm]", "case of the largest"),
                  rows)]


def _landmark_check_section(check: dict) -> list:
    """How far the correspondence carries each landmark where it does not guide it
    (metrics.json ``landmark_check``): per label the error left out of the guides, and guiding."""
    def mm(value):
        return "" if value is None else f"{value:.2f}"

    labels = check["per_label"]
    if check["guided"]:
        folds = check["folds"]
        how = ("each label was left out of the guides in turn and the correspondence optimised "
               "again with the others" if all(len(fold) == 1 for fold in folds) else
               f"the labels were left out of the guides in {len(folds)} groups ("
               + "; ".join(", ".join(fold) for fold in folds)
               + "), and the correspondence optimised again with the others each time")
        rows = [(label, item["cases"], mm(item["held_out_mm"]), mm(item["guided_mm"]))
                for label, item in labels.items()]
        rows.append(("mean", "", mm(check["mean"]["held_out_mm"]), mm(check["mean"]["guided_mm"])))
        return ["<h2>Landmarks left out of the guides</h2>",
                f"<p>How well the correspondence lands where no landmark holds it: "
                f"{html.escape(how)}. "
                "<i>Left out</i>: how far the correspondence carries the label from the "
                "experts' position when the label does not guide it; <i>guiding</i>: the same "
                "in this build, which it guided (small by construction). Each distance: "
                f"{html.escape(check['measure'])}.</p>",
                table(("label", "cases", "left out of the guides [mm]", "guiding [mm]"), rows)]
    rows = [(label, item["cases"], mm(item["held_out_mm"])) for label, item in labels.items()]
    rows.append(("mean", "", mm(check["mean"]["held_out_mm"])))
    return ["<h2>Landmarks: how far the correspondence carries them</h2>",
            "<p>The landmarks did not guide this correspondence: it carries each label from "
            "the experts' position by the distance shown. Each distance: "
            f"{html.escape(check['measure'])}.</p>",
            table(("label", "cases", "distance [mm]"), rows)]


def run_table() -> str:
    """What is running: this package's version and the date (a table), and the command line
    (wrapped, scrolling when long)."""
    import shlex
    import sys
    import time

    from ..version import __version__

    return (table(None, [("version", f"mdlshapemodel {__version__}"),
                             ("date", time.strftime("%Y-%m-%d %H:%M"))])
            + f"<p>Command:</p><pre class=command>{html.escape(shlex.join(sys.argv))}</pre>")


def _objective_parts(objective: dict) -> str:
    """The final objective's parts, as the report names them ('' where metrics.json has none)."""
    parts = objective.get("parts", {}).get("final")
    if not parts:
        return ""
    return (f" (description length {parts['description_length']:.3f}, smoothness prior "
            f"{parts['prior']:.3f}, landmark guides {parts['guides']:.3f})")


def _measured_on(objective: dict, n_points: int) -> str:
    """", on the N sample points the optimisation ran on" where they are not the model's."""
    measured = objective.get("n_points", n_points)
    return "" if measured == n_points else f", on the {measured} sample points it was optimised on"


def _run_parts(output: Path, metrics: dict) -> list:
    """What was run: version, date, command, settings, and links to the output files."""
    folder = folders.BuildFolder(output)
    settings = folder.settings()
    there = folder.existing()
    links = "".join(f"<li><a href='{html.escape(name)}'>{html.escape(name)}</a>: "
                    f"{html.escape(what)}</li>" for name, what in OUTPUT_FILES if name in there)
    return ["<h2>What was run</h2>", run_table(),
            f"<details><summary>Settings ({folders.CONFIG})</summary>",
            table(("setting", "value"), [(k, v if v != "" else "''") for k, v in settings.items()]),
            "</details>", "<h3>Output files</h3>", f"<ul>{links}</ul>"]


HOW_TO_READ = """
<h3>How to read C(M), G(M) and S(M)</h3>
<ul>
<li><b>Compactness C(M)</b>: the variance the first M modes hold (mm²). Lower: the model
describes the population with less variance in its first modes.</li>
<li><b>Generalization G(M)</b>: leave one case out, build the model of the others with M modes,
and measure how far the left-out case is from its best reconstruction (mean squared point
distance, mm²). Lower: the model reproduces shapes it has not seen.</li>
<li><b>Specificity S(M)</b>: draw random shapes from the model with M modes and measure how far
each is from the nearest training shape. Lower: the model makes shapes like the real ones.</li>
<li>The error bars are ± 1 standard error over the cases (G, C) or the samples (S). Two
correspondences of the same cases differ where their values differ by more than two standard
errors of the difference. These point measures depend on where the points lie; G and S measured
surface to surface (when shown) do not.</li>
</ul>
"""


def write_report(output: Path, metrics: dict, cases: list, rejected: list, model=None,
                 shapes=None, names=None, distances=None, normals=None) -> Path:
    """Write ``output/report.html`` and return its path.

    ``model`` (ShapeModel) and ``shapes`` (aligned corresponded shapes, with ``names``) add the
    mode and correspondence renderings and the interactive viewer (report/viewer.py);
    ``distances`` (n_s, n_p), each corresponded point's distance to its input surface, colour a
    case there; ``normals`` (:class:`~mdlshapemodel.model.normals.NormalAgreement`) adds the
    check of the corresponded normals.
    """
    objective = metrics["objective"]
    ending = metrics.get("optimisation", {})    # how it ended; an unconverged one has a warning
    parts = [
        "<h1>MDLShapeModel report</h1>",
        f"<p>{metrics['n_shapes']} shapes, {metrics['n_points']} points each, correspondence "
        f"<b>{html.escape(metrics['strategy'])}</b>; {metrics['n_rejected']} input(s) rejected"
        f"{' (listed at the end)' if metrics['n_rejected'] else ''}. "
        f"Objective (eq. 14 with the prior and the guides' term"
        f"{_measured_on(objective, metrics['n_points'])}): "
        f"{objective['initial']:.3f} before, {objective['final']:.3f} after"
        f"{_objective_parts(objective)}. "
        f"Optimisation: <b>{html.escape(stop_summary(ending.get('stopped_by')))}</b>.</p>",
    ]
    parts += [f"<p class=flag>Warning: {html.escape(warning)}.</p>"
              for warning in metrics.get("warnings", [])]
    parts += _flagged_part(metrics)
    baselines = metrics.get("baselines", {})
    if baselines:
        parts.append("<p>Objective of the baselines on the same cases: " + "; ".join(
            f"{html.escape(BASELINE_NAMES.get(k, k))}: {v['objective']:.3f}"
            for k, v in baselines.items()) + ".</p>")
    parts += _run_parts(output, metrics)
    parts += ["<h2>Model quality (area-weighted squared distances, ± 1 standard error)</h2>",
              "<p>Lower is better for all three measures. A baseline value marked "
              "'MDL better' exceeds the MDL model's by more than two standard errors of the "
              "difference ('MDL worse': falls short of it), by the rule of "
              "<code>mdlshapemodel compare</code>: for G, whose cases are the same, the paired "
              "difference with its jackknife standard error over the cases; for S, the two "
              f"Monte Carlo errors together. {folders.METRICS} has each difference and its "
              "standard "
              "error (<code>baselines</code>, <code>differences</code>).</p>",
              image_tag(measure_plot(_series(metrics)), "quality measures"),
              _measure_table(metrics), *_subsample_note(metrics), HOW_TO_READ]
    if "generalization_surface_mm" in metrics:
        parts += ["<h3>Measured surface to surface, against the true training surfaces</h3>",
                  image_tag(measure_plot(_series(metrics), keys=("generalization_surface_mm",
                                                              "specificity_surface_mm")),
                         "surface-to-surface measures")]
    convergence = convergence_plot(folders.BuildFolder(output).convergence_file)
    if convergence:
        parts += ["<h2>Convergence</h2>", image_tag(convergence, "convergence")]
    parts += _renderings(model, shapes, names)
    if metrics.get("landmarks"):
        parts += _landmarks_section(metrics["landmarks"])
    if metrics.get("landmark_check"):
        parts += _landmark_check_section(metrics["landmark_check"])
    if normals is not None:
        parts += _normals_section(model, normals, names)
    from .viewer import viewer_section     # the interactive 3-D viewer (plotly.js, offline)

    parts += viewer_section(model, shapes, names, distances=distances)
    if cases:
        keys = list(cases[0].keys())
        flags = [[k in ("score_outlier", "flags") and bool(c.get(k)) for k in keys]
                 for c in cases]
        shown = [[Path(str(c.get(k, ""))).name if k == "file" else c.get(k, "") for k in keys]
                 for c in cases]
        parts += ["<h2>Cases</h2>",
                  "<p>Fidelity: distance from the input surface to the corresponded mesh. Sphere "
                  "map: flipped triangles and |ln area ratio|. Score outlier: the Mahalanobis "
                  "distance of the case's scores (over the modes explaining 95% of the "
                  "variance) has p < 0.01 against the empirical null of the cases' own "
                  "distances (their scaled-Beta p-values as z-values, centred on their median "
                  "and widened to their 90% quantile; the p assuming normality is beside it). "
                  "The table scrolls sideways; the case and why it "
                  "is flagged stay in view.</p>",
                  "<div class=cases>",
                  table([CASE_COLUMNS.get(k, k) for k in keys], shown, flags), "</div>"]
    if rejected:
        parts += ["<h2>Rejected inputs</h2>",
                  table(("case", "file", "reason"), [(r.name, r.path, r.reason) for r in rejected])]
    path = folders.BuildFolder(output).report_file
    io.write_text(path, html_page("MDLShapeModel report", parts))
    return path
