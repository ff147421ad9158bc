"""analysis.html: the findings of one analysis, self-contained (pictures inlined).

The effect maps on the mean surface from three views (significance and the effect along the
normal, the significant region outlined), the global test, the discriminant shape change of two
groups at -2 and +2 SD, the discriminant scores by group, the classification, the unusual cases,
and a few lines on how to read them.
"""

from __future__ import annotations

import html
import logging
import textwrap
from pathlib import Path

import numpy as np

from ..analysis.effects import PREDICTED_AT
from ..analysis.study import Analysis
from ..errors import MDLShapeModelError
from ..model.shape_model import ShapeModel
from ..prepare import io
from .figures import encoded_png, pyplot
from .html import html_page, image_tag, table
from .rendering import render_maps, render_modes
from .viewer import EffectMap, effects_section

log = logging.getLogger("mdlshapemodel")

HOW_TO_READ = """
<h2>How to read this page</h2>
<ul>
<li><b>What is tested at each point.</b> {what}{design}. The statistic is
{statistic}{assumes}; its p-value{tail} counts how often {permutations} random resamples (the
residuals of the model without the effect {resampling}, Freedman-Lane) gave a statistic at least
as extreme at that point (so it is at least 1/{permutations_plus_one}).</li>
<li><b>Family-wise correction</b> (p<sub>FWER</sub>): {family_wise} over all points is
compared, so the chance that <i>any</i> point is called significant when there is no effect is
at most &alpha; = {alpha}. <b>FDR</b> (q): among the points called significant, the expected share
of false ones is at most &alpha; (Benjamini-Hochberg of the per-point p-values); it finds more,
with weaker guarantees.</li>
{tfce}<li><b>Effect along the normal</b>: the mean difference {effect_unit} projected on the mean
surface's outward normal; negative values (blue) point inwards (a loss of volume there).</li>
<li><b>Global test</b>: the same test on the first k principal scores together: is there any
difference in shape at all?</li>
<li>The shapes were aligned by rotation and translation{size}; differences in position and
orientation are not findings, differences in {sized} are.</li>
</ul>
"""


# characters per line of a map's title beside its picture
LABEL_WIDTH = 26

# what is not significant is greyed: its pictures without colour, its text grey
STYLE = ("section.not-significant{color:#777}section.not-significant img{filter:grayscale(1);"
         "opacity:0.5}section.not-significant p.note{color:#333;background:#f3f3f3;"
         "border-left:4px solid #999;padding:4px 8px}")


def _maps(analysis: Analysis, model: ShapeModel) -> list:
    points, alpha = analysis.points, analysis.config.alpha
    significant = analysis.significant("fwer")
    cells = model.triangles
    log_p = -np.log10(points.p_fwer)
    level = float(-np.log10(alpha))
    # one fixed scale from 0 past the significance level: a null result stays dark; the scale's
    # ends come from the values as the page stores them (4-byte floats), so that they cover
    # every value shown
    top = max(float(log_p.astype(np.float32).max()), level * 1.5)
    rows = [("-log10 p (FWER)", log_p, "viridis", 0.0, top, "-log10 p, family-wise")]
    outlines = [significant]
    if points.tfce is not None:
        rows.append(_tfce_row("-log10 p (FWER, TFCE)", points.tfce_p_fwer, level))
        outlines.append(points.tfce_p_fwer <= alpha)
    labels = effect_labels(analysis.subjects)
    for label, values in zip(labels, analysis.normal_difference):
        limit = float(np.max(np.abs(values.astype(np.float32)))) or 1.0
        rows.append((label, values, "coolwarm", -limit, limit, "along the normal [mm]"))
    # the region outlined on each map: the per-point test's, or a signed map's own
    outlines += [significant] * (len(rows) - len(outlines))
    # one signed map per effect column, and its own family-wise p when it is a test of its own
    for k, found in enumerate(analysis.signed):
        label = labels[k] if k < len(labels) else f"contrast {found.name}"
        values = found.test.t
        limit = float(np.max(np.abs(values.astype(np.float32)))) or 1.0
        rows.append((f"signed t, {label}", values, "coolwarm", -limit, limit,
                     "t along the normal"))
        own_region = significant if found.joint else found.test.p_fwer <= alpha
        outlines.append(own_region)
        if not found.joint:
            own = -np.log10(found.test.p_fwer)
            rows.append((f"-log10 p (FWER), {label}", own, "viridis", 0.0,
                         max(float(own.astype(np.float32).max()), level * 1.5),
                         "-log10 p, family-wise"))
            outlines.append(own_region)
            if found.test.tfce is not None:
                rows.append(_tfce_row(f"-log10 p (FWER, TFCE), {label}",
                                      found.test.tfce_p_fwer, level))
                outlines.append(found.test.tfce_p_fwer <= alpha)
    parts = []
    if model.of_curves:
        return [image_tag(_curve_maps(analysis, rows, significant), "effect maps")]
    for row, outlined in zip(rows, outlines):
        # the row's title beside the picture, broken into lines that fit its height
        wrapped = (textwrap.fill(row[0], LABEL_WIDTH), *row[1:])
        png = render_maps(analysis.mean, cells, [wrapped], outlined=outlined)
        parts.append(image_tag(_b64(png), row[0]))
    parts += effects_section(analysis.mean, cells, [
        EffectMap(label, values, diverging=cmap == "coolwarm", limit=high,
                  marks=() if cmap == "coolwarm" else ((level, f"α = {alpha:g}"),))
        for label, values, cmap, _, high, _ in rows] + uncertainty_maps(analysis))
    return parts


def uncertainty_maps(analysis: Analysis) -> list:
    """The viewer's maps of how large and how certain each effect is: per signed map the
    half-width of its confidence interval (mm) and Cohen's d; then each effect shape drawn as
    itself, coloured by the displacement it belongs to along the normal (choosing between a
    pair switches the shapes)."""
    labels = effect_labels(analysis.subjects)
    maps = []
    for k, effect in enumerate(analysis.effect_sizes):
        label = labels[k] if k < len(labels) else f"contrast {effect.name}"
        level = f"{100 * effect.interval.level:g} %"
        maps.append(EffectMap(f"{level} confidence interval half-width [mm], {label}",
                              (effect.interval.upper - effect.interval.lower) / 2))
        if effect.d is not None:
            maps.append(EffectMap(f"Cohen's d, {label}", effect.d, diverging=True))
    levels = analysis.subjects.levels
    for shape in analysis.shapes:
        limit = float(np.max(np.abs(shape.normal_displacement))) or 1.0
        change = (f"{PREDICTED_AT[-1]:g}th minus {PREDICTED_AT[0]:g}th percentile"
                  if shape.level is None else
                  f"{levels[1] if shape.level == levels[0] else shape.level} minus {levels[0]}")
        maps.append(EffectMap(f"{shape.label}, coloured by {change} along the normal [mm]",
                              shape.normal_displacement, diverging=True, limit=limit,
                              points=shape.points))
    return maps


def _effect_size_parts(analysis: Analysis, summary: dict) -> list:
    """The table of effect sizes and the list of the effect's shapes."""
    sizes = summary["effect_sizes"]
    if not sizes["maps"]:
        return []
    labels = effect_labels(analysis.subjects)
    rows = []
    for k, entry in enumerate(sizes["maps"]):
        d, half, eta = entry["cohens_d"], entry["half_width_mm"], entry["partial_eta2"]
        rows.append((labels[k] if k < len(labels) else f"contrast {entry['name']}",
                     f"{half['median']:.3g} ({half['largest']:.3g})",
                     "" if d is None else
                     f"{d['median_abs']:.3g} ({d['value']:+.3g} at point {d['at_point']})",
                     f"{eta['median']:.3g} ({eta['largest']:.3g})"))
    level = f"{100 * sizes['intervals']['level']:g} %"
    parts = ["<h2>Effect sizes</h2>",
             f"<p>At each point, the {level} confidence interval of the effect along the normal "
             f"({html.escape(sizes['intervals']['kind'])}), Cohen's d (the effect over the "
             "residual standard deviation of the groups compared) and partial &eta;<sup>2</sup> "
             "(the share of the variation left by the columns adjusted for that the effect "
             "explains); in <code>points.csv</code>, <code>effects.vtp</code> and the viewer "
             "above.</p>",
             table(("effect", f"{level} CI half-width, mm: median (largest)",
                    "|d|: median (largest)", "partial eta^2: median (largest)"), rows)]
    if summary["shapes"]:
        parts.append("<p>The effect as shapes, in <code>shapes/</code> (on the mean's "
                     "triangles, with the displacement between them as point data; in the "
                     "viewer, choose one to see it): "
                     + "; ".join(f"<code>{html.escape(s['file'])}</code> {html.escape(s['label'])}"
                                 + ("" if s["value"] is None else f" ({s['value']:.4g})")
                                 for s in summary["shapes"]) + ".</p>")
    return parts


def _tfce_row(label: str, p_fwer: np.ndarray, level: float) -> tuple:
    """A map's row of the family-wise p of its threshold-free cluster enhancement, on the
    same fixed scale as the other -log10 p maps."""
    values = -np.log10(p_fwer)
    return (label, values, "viridis", 0.0, max(float(values.astype(np.float32).max()),
                                                level * 1.5), "-log10 p, family-wise (TFCE)")


def effect_labels(subjects) -> list:
    """A title per tested effect column: the tested column and, for a group, which level is
    compared with which (the reference)."""
    labels, seen = [], {}
    for column in subjects.interest_columns:
        levels = subjects.levels_of.get(column)
        if ":" in column:
            labels.append(f"interaction {column}, per unit")
        elif subjects.mean_change_tested:
            times = subjects.repeated.times
            labels.append(f"mean change: {column} {times[1]} minus {times[0]}")
        elif levels:
            seen[column] = seen.get(column, 0) + 1
            labels.append(f"effect of {column}: {levels[seen[column]]} minus {levels[0]}")
        else:
            labels.append(f"effect of {column}, per unit")
    repeated = subjects.repeated
    if repeated is not None and repeated.design == "change" and not subjects.mean_change_tested:
        labels = [f"{label}, on the change" for label in labels]
    return labels


def _b64(png: bytes) -> str:
    import base64

    return base64.b64encode(png).decode("ascii")


def _curve_maps(analysis: Analysis, rows, significant) -> str:
    plt = pyplot()
    figure, axes = plt.subplots(1, len(rows), figsize=(4.2 * len(rows), 4.0), squeeze=False)
    for axis, (label, values, cmap, low, high, unit) in zip(axes[0], rows):
        drawn = axis.scatter(analysis.mean[:, 0], analysis.mean[:, 1], c=values, cmap=cmap,
                             vmin=low, vmax=high, s=14)
        axis.scatter(analysis.mean[significant, 0], analysis.mean[significant, 1], s=60,
                     facecolors="none", edgecolors="black", linewidths=0.6)
        axis.set_aspect("equal")
        axis.set_title(label)
        axis.set_xticks([])
        axis.set_yticks([])
        figure.colorbar(drawn, ax=axis, shrink=0.8, label=unit)
    return encoded_png(figure)


#: The AUC of a classification that does not separate the groups (the balanced accuracy's is
#: one over the number of groups, whatever their sizes).
CHANCE = 0.5

BELOW_CHANCE = ("<p class=chance>Below chance ({what}) does not mean that the "
                "shapes predict the other group: the groups do not separate. Cross-validated "
                "estimates of an effect that is not there scatter around chance, below it about "
                "as often as above (each case is classified by a discriminant fitted without it, "
                "whose group means lean away from it).</p>")


def _not_significant(analysis: Analysis) -> str | None:
    """The note on the discriminant and the classification when the global test finds no
    difference at alpha (None when it does)."""
    overall, alpha = analysis.global_test, analysis.config.alpha
    if overall.p <= alpha:
        return None
    return (f"<p class=note><b>Not significant</b>: the global test gives p = {overall.p:.2g} "
            f"&gt; &alpha; = {alpha:g}, so the groups' shapes are not found to differ. A "
            "discriminant is fitted to any two groups, also to noise: its shape change and the "
            "classification are no finding.</p>")


def _section(name: str, parts: list, note: str | None) -> list:
    """``parts`` in a section ``name``; greyed with ``note`` first when not significant."""
    if not parts:
        return []
    if note is None:
        return [f"<section id={name}>", *parts, "</section>"]
    return [f"<section id={name} class=not-significant>", parts[0], note, *parts[1:],
            "</section>"]


def _classification_parts(analysis: Analysis, summary: dict) -> list:
    if analysis.classification is None:
        return []
    c = summary["classification"]
    adjusted = (f", with {', '.join(html.escape(a) for a in c['adjusted_for'])} regressed out "
                "in each training fold (fitted on its cases only)" if c["adjusted_for"] else "")
    auc_kind = "AUC" if c["auc_kind"] == "binary" else "AUC (macro one-vs-rest)"
    if c["subject"] is not None:
        adjusted += (f"; each subject (<code>{html.escape(c['subject'])}</code>) held out and "
                     "permuted whole")
    tested = ("all " if c["exact"] else "") + f"{c['permutations'] - 1:,} permuted labelings"
    parts = ["<h2>Classification</h2>",
             f"<p>{c['repeats']} &times; {c['folds']}-fold stratified cross-validation of a "
             "shrinkage linear discriminant on the principal scores (principal components and "
             f"discriminant fitted on the training folds only){adjusted}. Intervals: 95% "
             "corrected resampled t (Nadeau and Bengio 2003; the spread of the folds "
             "inflated for their shared training cases). p: the AUC against "
             f"{tested}, the cross-validation redone for each.</p>",
             table(("measure", "value", "95% interval", "permutation p"),
                   [(auc_kind, c["auc"], "{:.3f} - {:.3f}".format(*c["auc_interval"]),
                     "-" if c["p"] is None else c["p"]),
                    ("balanced accuracy", c["balanced_accuracy"],
                     "{:.3f} - {:.3f}".format(*c["balanced_accuracy_interval"]), "")])]
    chance = {"balanced accuracy": 1 / len(c["levels"]), "AUC": CHANCE}
    below = [f"{name} under {chance[name]:.3g}" for name, key
             in (("balanced accuracy", "balanced_accuracy"), ("AUC", "auc"))
             if c[key] < chance[name]]
    if below:
        parts.append(BELOW_CHANCE.format(what=" and ".join(below)))
    return parts


def _discriminant_parts(analysis: Analysis, model: ShapeModel) -> list:
    found = analysis.discriminant
    if found is None:
        return []
    levels = analysis.subjects.levels
    parts = [f"<h2>Discriminant shape change: {html.escape(levels[0])} &rarr; "
             f"{html.escape(levels[1])}</h2>",
             f"<p>Linear discriminant in the space of the first {found.modes} principal scores "
             f"(Ledoit-Wolf shrinkage {found.shrinkage:.2f}), shown as the shape change that "
             f"goes with its score: the mean at -2 and +2 SD of the score (positive towards "
             f"{html.escape(levels[1])}).</p>"]
    if not model.of_curves:
        pattern_model = ShapeModel(mean=found.mean, modes=found.pattern[None],
                                   variances=np.ones(1), weights=model.weights,
                                   scores=np.zeros((0, 1)), triangles=model.triangles)
        try:
            picture = render_modes(pattern_model, 1, row_labels=["discriminant\nscore"])
            parts.append(image_tag(_b64(picture), "discriminant change"))
        except (MDLShapeModelError, RuntimeError) as error:
            parts.append(f"<p>Rendering left out: {html.escape(str(error))}</p>")
    held_out = analysis.classification.predicted
    plt = pyplot()
    figure, axis = plt.subplots(figsize=(5.0, 2.6))
    groups = np.array(analysis.subjects.groups)
    for k, level in enumerate(levels):
        values = held_out[groups == level]
        axis.scatter(values, np.full(len(values), k) + np.linspace(-0.15, 0.15, len(values)),
                     s=14, label=level)
    axis.axvline(0.0, color="0.5", linewidth=0.8)
    axis.set_yticks(range(len(levels)), levels)
    axis.set_xlabel("held-out discriminant value (cross-validated; > 0: "
                    f"{levels[1]})")
    axis.grid(alpha=0.3)
    parts += ["<p>Each case's discriminant value from the fold that held it out (fitted "
              "without it): how well the groups separate on new cases. The values of the "
              "discriminant fitted on all cases separate them better than new cases would.</p>",
              image_tag(encoded_png(figure), "held-out discriminant values by group")]
    return parts


def write_analysis_page(path: Path, summary: dict, analysis: Analysis, model: ShapeModel
                        ) -> Path:
    """Write ``path`` (analysis.html) from an analysis and its ``summary`` (the content of
    analysis.json) and return the path."""
    config = analysis.config
    subjects = analysis.subjects
    body = ["<h1>MDLShapeModel analysis</h1>",
            f"<p>Build <code>{html.escape(str(summary['build']))}</code>, table "
            f"<code>{html.escape(str(summary['table']))}</code>. {summary['n_cases']} cases "
            f"used"]
    if subjects.groups is not None:
        body[-1] += " (" + ", ".join(f"{html.escape(level)}: {count}" for level, count
                                     in summary["n_per_group"].items()) + ")"
    body[-1] += f"; {len(subjects.left_out)} left out.</p>"
    repeated = subjects.repeated
    if repeated is not None and repeated.design == "blocks":
        body.append(f"<p>Repeated measures: {len(repeated.subjects)} subjects "
                    f"(<code>{html.escape(repeated.subject)}</code>), each subject's cases "
                    "permuted together (whole blocks).</p>")
    elif repeated is not None:
        body.append(f"<p>Repeated measures: {len(repeated.subjects)} subjects "
                    f"(<code>{html.escape(repeated.subject)}</code>) at "
                    f"<code>{html.escape(repeated.time)}</code> "
                    + ", ".join(html.escape(t) for t in repeated.times) + ": "
                    + ("each subject's change, " + html.escape(repeated.times[1]) + " minus "
                       + html.escape(repeated.times[0]) + ", is analysed."
                       if repeated.design == "change" else
                       "the effect of time within subjects, each subject adjusted for.")
                    + "</p>")

    def named(columns: list) -> str:
        return ", ".join(("group " if c == subjects.group else "") + f"<b>{html.escape(c)}</b>"
                         for c in columns) or "nothing"

    body.append(f"<p>Tested: {named(subjects.tested)}; adjusted for: "
                f"{named(subjects.adjusted_for)}.</p>")
    body += [f"<p class=note>{html.escape(note)}</p>" for note in subjects.notes]
    counts = summary["significant_points"]
    body += [f"<h2>Where the shapes differ by {named(subjects.tested)}</h2>",
             f"<p>{counts['fwer']} of {len(analysis.mean)} points significant at &alpha; = "
             f"{config.alpha} after family-wise correction, {counts['fdr']} after FDR "
             "correction (outlined in black: family-wise; on the signed map of an effect "
             "column tested on its own, that map's family-wise region).</p>"]
    try:
        body += _maps(analysis, model)
    except (MDLShapeModelError, RuntimeError) as error:
        log.warning("analysis page: no renderings (%s)", error)
        body.append(f"<p>Renderings left out: {html.escape(str(error))}</p>")
    body += _effect_size_parts(analysis, summary)
    overall = summary["global_test"]
    body += ["<h2>Global test</h2>",
             f"<p>On the first {overall['modes']} principal scores: statistic "
             f"{overall['statistic']:.4g}, permutation p = {overall['p']:.4g}.</p>"]
    size = summary["centroid_size"]
    effects = ", ".join(f"{html.escape(name)} {value:+.3g} mm"
                        for name, value in size["effects_mm"].items())
    body += ["<h2>Size</h2>",
             f"<p>The shapes are superimposed by {html.escape(config.superimposition)} "
             "generalized Procrustes. "
             f"Centroid size (area-weighted, before alignment) {size['mean_mm']:.4g} mm on "
             f"average; effect: {effects} ({html.escape(size['test'])}, permutation p = "
             f"{size['p']:.4g}). With <code>--size kept</code> a difference of size shows in the "
             "maps as a difference of shape.</p>"]
    note = _not_significant(analysis)
    body += _section("discriminant", _discriminant_parts(analysis, model), note)
    body += _section("classification", _classification_parts(analysis, summary), note)
    unusual = analysis.unusual
    flagged = [(name, d, p) for name, d, p, o in zip(unusual.names, unusual.distances.distance,
                                                      unusual.distances.p,
                                                      unusual.distances.outlier) if o]
    body += ["<h2>Unusual cases</h2>",
             f"<p>Mahalanobis distance over the first {unusual.distances.modes} modes, against "
             "the empirical null of the cases' own distances (their scaled-Beta p-values as "
             "z-values, centred on their median and widened to their 90% quantile, so that a "
             "heavy tail of the cases themselves is not flagged); flagged below "
             f"p = 0.01: {len(flagged)} case(s). Where each case departs from its reconstruction "
             "is in <code>unusual/</code>.</p>"]
    if flagged:
        body.append(table(("case", "distance", "p"), flagged))
    what = ("the displacement of the point along the mean surface's outward normal (one number;"
            " sliding of the correspondence along the surface does not change it)"
            if config.displacement == "normal" else
            "the displacement vector of the point from the mean shape")
    points = analysis.points
    assumes = (", which allows the groups to differ in spread" if points.variance == "groups"
               else ", which assumes that each subject's change is as likely as its negative "
               "when there is no change" if subjects.mean_change_tested
               else ", which assumes that every group varies alike")
    family_wise = ("the largest statistic" if points.family_wise == "maximum" else
                   "the smallest per-point p-value (min-p)")
    body.append(HOW_TO_READ.format(
        what=what, statistic=html.escape(points.name), assumes=assumes,
        design=("" if repeated is None else
                ", of each subject's change between the two times" if repeated.design == "change"
                else ", within each subject" if repeated.design == "within"
                else ", every case of a subject resampled with it"),
        tail=("" if points.tail == "both" else
              f" (one-sided: an effect {'above' if points.tail == 'greater' else 'below'} 0)"),
        resampling=html.escape(points.resampling), permutations=config.permutations, permutations_plus_one=config.permutations + 1,
        family_wise=family_wise, alpha=config.alpha,
        tfce=("" if points.tfce is None else
              "<li><b>TFCE</b> (threshold-free cluster enhancement; maps marked TFCE): each "
              "point's statistic is enhanced by the area of the region around it where the "
              "statistic is as high, summed over the heights up to the point's own (Smith and "
              "Nichols 2009), and compared with the largest enhanced value of every resample: "
              "an effect that spreads over a region is found with more power, but a significant "
              "point says that the region it lies in differs, not that the point itself "
              "does.</li>\n"),
        effect_unit=("(mm)" if subjects.tested == [subjects.group] else
                     "per unit of the covariate (mm)" if subjects.group not in subjects.tested
                     else "(mm; per unit for a covariate)"),
        size="" if config.size == "kept" else ", after scaling each case to the mean size",
        sized="size and shape" if config.size == "kept" else "shape"))
    if subjects.left_out:
        body += ["<h2>Cases left out</h2>",
                 table(("case", "reason"), [(c.case, c.reason) for c in subjects.left_out])]
    body.insert(0, f"<style>{STYLE}</style>")
    io.write_text(path, html_page("MDLShapeModel analysis", body))
    return path
