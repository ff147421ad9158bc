"""``analyze_build``: a build folder and a subjects table -> the analysis's output folder.

Everything is checked before anything is written: the build, the table, the columns. The files
are written into a temporary folder beside the output and moved into place at the end, so the
output folder holds a whole analysis or none (an interrupted run leaves nothing behind).

The output folder::

    analysis.json   settings, the columns tested and adjusted for, cases per group, cases left
                    out and why (with the columns and values missing), the per-point test
                    (statistic, variance groups, family-wise correction, smallest p), the global
                    test, the effect on centroid size, the number of significant points (FWER,
                    FDR), the classification (AUC and balanced accuracy with intervals, the
                    AUC's permutation p and null values, the per-fold values)
    points.csv      one row per model point: point,part,x,y,z,statistic,p,p_fwer,q_fdr,
                    difference_x,difference_y,difference_z,normal_difference_mm,t
                    (p: the point's own permutation p-value; p_fwer: family-wise corrected;
                    q_fdr: Benjamini-Hochberg of p; t: the signed t or Welch's v; several
                    effect columns or the vector displacement: difference_<name>_x ... and
                    t_<name>,p_<name>,p_fwer_<name>,q_fdr_<name> per column, each column's
                    own signed test along the normal adjusted for the others; with ``tfce``,
                    tfce,tfce_p_fwer after q_fdr, the map's threshold-free cluster enhancement
                    (signed as the effect) and its family-wise p, and tfce_<name>,
                    tfce_p_fwer_<name> per column's own test); the effect
                    sizes: partial_eta2 (the per-point test's), ci_lower_mm,ci_upper_mm
                    (the confidence interval at 1 - alpha of the effect along the normal),
                    cohens_d (two levels compared), or per column ci_lower_<name>_mm,
                    ci_upper_<name>_mm,cohens_d_<name>,partial_eta2_<name>
    effects.vtp     the mean surface with the same values as point arrays (effects/<part>.vtp
                    for a multi-part model)
    shapes/         the shapes of the tested effect on the mean's triangles: each group's
                    mean shape (<group>=<level>.vtp), a covariate's predicted shapes at its
                    10th and 90th percentile (<covariate>_p10.vtp, _p90.vtp), with the
                    displacement between them (vector and along the normal) as point data
    unusual.csv     per case: Mahalanobis distance, p (empirical null), p_normal (assuming
                    normality), flagged, largest departure from its reconstruction
    unusual/        per case, the mean surface with the case's departure (mm) as point data
    analysis.html   the page of findings
    long.csv        with ``long_table`` (``--long-table``): one row per used case and point,
                    case,point,part,normal_displacement_mm,score_1 ... score_k and every column
                    of the subjects table, for mixed models in R or pandas
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .analysis.shapes import read_build
from .analysis.study import Analysis, analyze_shapes, contrasts_of
from .analysis.table import CASE, read_table, subjects
from .config import TFCE_EXTENT, TFCE_HEIGHT, TFCE_STEP, AnalysisConfig
from .errors import InputError
from .prepare import io
from .report.analysis_page import write_analysis_page
from .version import __version__

SUMMARY = "analysis.json"
POINTS = "points.csv"
EFFECTS = "effects.vtp"          # one part; several: effects/<part>.vtp
EFFECTS_PARTS = "effects"
PAGE = "analysis.html"
# the folder of the effect's shapes (group means, predicted shapes), one .vtp per shape
SHAPES = "shapes"
ANALYSIS_FILES = (SUMMARY, POINTS, EFFECTS, EFFECTS_PARTS, "unusual.csv", "unusual", PAGE,
                  "long.csv", SHAPES)


class AnalysisFolder:
    """An analysis's output folder (:func:`analyze_build`) read by its files' names: the faces
    (the Slicer module) read it through this, never by the names themselves."""

    def __init__(self, path):
        self.path = Path(path)
        self.page_file = self.path / PAGE

    def summary(self) -> dict:
        """analysis.json: the settings, the columns tested, the cases, the findings."""
        return json.loads((self.path / SUMMARY).read_text())

    def points(self) -> dict:
        """points.csv as columns by name: ``point`` and ``part`` integers, the others numbers."""
        rows = io.read_csv(self.path / POINTS)
        return {key: [int(r[key]) if key in ("point", "part") else float(r[key]) for r in rows]
                for key in (rows[0] if rows else {})}

    def effect_meshes(self) -> list:
        """The effect map's mesh files: effects.vtp, or effects/<part>.vtp per part."""
        single = self.path / EFFECTS
        return [single] if single.exists() else sorted((self.path / EFFECTS_PARTS).glob("*.vtp"))

    def shape_meshes(self) -> list:
        """The effect's shapes (group means, a covariate's predicted shapes): shapes/*.vtp, by
        name (none where the analysis wrote none)."""
        return sorted((self.path / SHAPES).glob("*.vtp"))


@dataclass
class AnalysisResult:
    """What :func:`analyze_build` wrote and found."""

    output: Path
    analysis: Analysis
    summary: dict


def _columns(analysis: Analysis) -> tuple[list, list]:
    """The header of points.csv and its rows."""
    names = analysis.subjects.interest_names
    mean, points = analysis.mean, analysis.points
    header = ["point", "part", "x", "y", "z", "statistic", "p", "p_fwer", "q_fdr"]
    enhanced = tfce_columns(points)
    header += list(enhanced)
    single = len(names) == 1
    for name in names:
        prefix = "difference" if single else f"difference_{name}"
        header += [f"{prefix}_x", f"{prefix}_y", f"{prefix}_z"]
        header.append("normal_difference_mm" if single else f"normal_difference_{name}_mm")
    signed = signed_columns(analysis)
    signed.update(effect_columns(analysis))
    header += list(signed)
    rows = []
    for k in range(len(mean)):
        row = [k, int(analysis.parts[k]), *(f"{v:.6g}" for v in mean[k]),
               f"{points.statistic[k]:.6g}", f"{points.p[k]:.6g}", f"{points.p_fwer[k]:.6g}",
               f"{points.q_fdr[k]:.6g}", *(f"{values[k]:.6g}" for values in enhanced.values())]
        for r in range(len(names)):
            row += [f"{v:.6g}" for v in analysis.difference[r, k]]
            row.append(f"{analysis.normal_difference[r, k]:.6g}")
        row += [f"{values[k]:.6g}" for values in signed.values()]
        rows.append(row)
    return header, rows


def tfce_columns(test, suffix: str = "") -> dict:
    """A test's TFCE columns (``tfce``, ``tfce_p_fwer`` + ``suffix``), empty without TFCE."""
    if test.tfce is None:
        return {}
    return {f"tfce{suffix}": test.tfce, f"tfce_p_fwer{suffix}": test.tfce_p_fwer}


def signed_columns(analysis: Analysis) -> dict:
    """The signed maps' columns of points.csv and arrays of effects.vtp: ``t`` when the
    per-point test is itself the signed test of its one effect column; else per effect column
    ``t_<name>``, ``p_<name>``, ``p_fwer_<name>``, ``q_fdr_<name>`` (its own test along the
    normal, adjusted for the other effect columns)."""
    columns = {}
    for found in analysis.signed:
        if found.joint:
            columns["t"] = found.test.t
            continue
        for key in ("t", "p", "p_fwer", "q_fdr"):
            columns[f"{key}_{found.name}"] = getattr(found.test, key)
        columns.update(tfce_columns(found.test, f"_{found.name}"))
    return columns


def effect_columns(analysis: Analysis) -> dict:
    """The effect sizes' columns of points.csv and arrays of effects.vtp: ``partial_eta2`` of
    the per-point test, and per signed map the ends of its confidence interval along the normal
    (mm) and Cohen's d where it has one: ``ci_lower_mm``, ``ci_upper_mm``, ``cohens_d`` when the
    per-point test is the signed test of its one effect column, else ``ci_lower_<name>_mm``,
    ``ci_upper_<name>_mm``, ``cohens_d_<name>``, ``partial_eta2_<name>``."""
    columns = {}
    if analysis.effect_sizes:
        columns["partial_eta2"] = analysis.point_eta2
    for found, effect in zip(analysis.signed, analysis.effect_sizes):
        suffix = "" if found.joint else f"_{found.name}"
        columns[f"ci_lower{suffix}_mm"] = effect.interval.lower
        columns[f"ci_upper{suffix}_mm"] = effect.interval.upper
        if effect.d is not None:
            columns[f"cohens_d{suffix}"] = effect.d
        if not found.joint:
            columns[f"partial_eta2{suffix}"] = effect.partial_eta2
    return columns


def effects_summary(analysis: Analysis) -> dict:
    """analysis.json's ``effect_sizes``: the interval's kind and level, and per signed map the
    median and largest half-width of the interval (mm), the largest |d| (with its point) and
    the median |d|, and the same of partial eta^2."""
    if not analysis.effect_sizes:
        return {"intervals": None, "maps": []}
    first = analysis.effect_sizes[0].interval
    maps = []
    for effect in analysis.effect_sizes:
        half = (effect.interval.upper - effect.interval.lower) / 2
        entry = {"name": effect.name,
                 "half_width_mm": {"median": float(np.median(half)), "largest": float(half.max())},
                 "partial_eta2": {"median": float(np.median(effect.partial_eta2)),
                                  "largest": float(effect.partial_eta2.max()),
                                  "at_point": int(effect.partial_eta2.argmax())},
                 "cohens_d": None}
        if effect.d is not None:
            size = np.abs(effect.d)
            entry["cohens_d"] = {"median_abs": float(np.median(size)),
                                 "largest_abs": float(size.max()),
                                 "at_point": int(size.argmax()),
                                 "value": float(effect.d[size.argmax()])}
        maps.append(entry)
    return {"intervals": {"kind": first.name, "level": first.level},
            "partial_eta2": {"median": float(np.median(analysis.point_eta2)),
                             "largest": float(analysis.point_eta2.max())},
            "maps": maps}


def shapes_summary(analysis: Analysis, table) -> list:
    """analysis.json's ``shapes``: each effect shape's file (in the analysis folder), what it
    is, and for a covariate the value it is predicted at (in the table's units)."""
    found = []
    means = {}
    if any(shape.offset is not None for shape in analysis.shapes):
        _, rows = read_table(table)
        by_case = {row[CASE]: row for row in rows}
        for shape in analysis.shapes:
            if shape.offset is not None and shape.column not in means:
                means[shape.column] = float(np.mean([float(by_case[c][shape.column])
                                                     for c in analysis.subjects.cases]))
    for shape in analysis.shapes:
        found.append({"file": f"{SHAPES}/{io.case_file('', shape.name).name}",
                      "label": shape.label, "column": shape.column, "level": shape.level,
                      "percentile": shape.percentile,
                      "value": (None if shape.offset is None
                                else means[shape.column] + shape.offset),
                      "largest_normal_displacement_mm":
                          float(np.abs(shape.normal_displacement).max())})
    return found


def design_summary(design) -> dict:
    """analysis.json's ``design``: independent cases, or repeated measures and how."""
    repeated = design.repeated
    if repeated is None:
        return {"kind": "independent cases"}
    return {"kind": ("change between two times" if repeated.design == "change" else
                     "time within subjects" if repeated.design == "within" else
                     "whole subjects exchanged"),
            "subject": repeated.subject, "time": repeated.time, "times": repeated.times,
            "n_subjects": len(repeated.subjects),
            "mean_change_tested": design.mean_change_tested}


def long_table(analysis: Analysis, table) -> tuple[list, list]:
    """The header and rows of long.csv: per used case and model point, the case's displacement
    from the mean along the mean's normal (mm, as tested with ``--displacement normal``), its
    principal scores (those of the global test) and its row of the subjects table."""
    header_of_table, rows = read_table(table)
    columns = [c for c in header_of_table if c != CASE]
    by_case = {row[CASE]: row for row in rows}
    normal = np.einsum("npd,pd->np", analysis.aligned - analysis.mean, analysis.normals)
    k = analysis.scores.shape[1]
    header = (["case", "point", "part", "normal_displacement_mm"]
              + [f"score_{j + 1}" for j in range(k)] + columns)
    body = []
    for i, case in enumerate(analysis.subjects.cases):
        per_case = ([f"{v:.6g}" for v in analysis.scores[i]]
                    + [by_case[case].get(c, "") for c in columns])
        body += [[case, point, int(analysis.parts[point]), f"{normal[i, point]:.6g}", *per_case]
                 for point in range(normal.shape[1])]
    return header, body


def size_summary(analysis: Analysis) -> dict:
    """analysis.json's ``centroid_size``: the cases' mean centroid size (mm, before alignment),
    per group, each effect column's effect on it and the design's test of it (how much of the
    shape difference is a difference of size; pose is left out, the cases' positions being
    those of their scans)."""
    size, design = analysis.size, analysis.subjects
    per_group = (None if design.groups is None or design.repeated is not None else
                 {level: float(np.mean([s for s, g in zip(size.sizes, design.groups)
                                        if g == level])) for level in design.levels})
    return {"mean_mm": float(size.sizes.mean()), "per_group_mm": per_group,
            "effects_mm": dict(zip(design.interest_names, size.effects.tolist())),
            "statistic": float(size.test.statistic[0]), "test": size.test.name,
            "p": float(size.test.p[0])}


def tfce_summary(test, alpha: float) -> dict | None:
    """analysis.json's ``tfce`` of a test: what was enhanced, the settings, the family-wise
    significant points (None without TFCE)."""
    if test.tfce is None:
        return None
    r, _, q = test.effect.shape
    enhanced = ("the signed t" if test.t is not None and test.variance == "pooled" else
                "the normal quantile of Welch's v's p, with v's sign" if test.t is not None else
                "the square root of the F" if test.variance == "pooled" else
                "the normal quantile of Welch's G's p" if q == 1 else
                "the square root of James' statistic")
    return {"enhanced": enhanced, "extent_power": TFCE_EXTENT, "height_power": TFCE_HEIGHT,
            "step": TFCE_STEP, "family_wise": "maximum of the enhanced maps",
            "significant_points": int(np.sum(test.tfce_p_fwer <= alpha))}


def classification_summary(analysis: Analysis) -> dict:
    """analysis.json's ``classification``: the repeated cross-validated shrinkage LDA of the
    groups (:mod:`~mdlshapemodel.analysis.classification`), its AUC and balanced accuracy with
    their corrected resampled intervals, the AUC's permutation p-value and null distribution,
    and the per-fold values they are computed from; ``subject``: the column whose subjects are
    held out and permuted whole (None: the cases)."""
    c = analysis.classification
    design = analysis.subjects
    return {"levels": c.levels, "folds": c.folds, "repeats": c.repeats,
            "adjusted_for": [column for column in design.adjusted_for]
            + [column for column in dict.fromkeys(design.interest_columns)
               if design.group not in column.split(":")],
            "subject": None if design.repeated is None else design.repeated.subject,
            "classifier": "shrinkage LDA (Ledoit-Wolf, equal priors) on the principal scores, "
                          "nuisance regressed out in each training fold",
            "auc": c.auc, "auc_interval": list(c.auc_interval),
            "auc_kind": "binary" if len(c.levels) == 2 else "macro one-vs-rest",
            "balanced_accuracy": c.balanced_accuracy,
            "balanced_accuracy_interval": list(c.balanced_accuracy_interval),
            "interval": "95% corrected resampled t (Nadeau and Bengio 2003) over the folds",
            "p": c.p, "permutations": c.permutations, "exact": c.exact,
            "null_auc": c.null_auc.tolist(),
            "fold_auc": c.fold_auc.tolist(),
            "fold_balanced_accuracy": c.fold_balanced_accuracy.tolist()}


def summary_of(analysis: Analysis, build, table) -> dict:
    """The content of analysis.json."""
    config, design = analysis.config, analysis.subjects
    summary = {
        "version": __version__, "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "build": str(build), "table": str(table), "settings": asdict(config),
        "n_cases": len(design.cases),
        "design": design_summary(design),
        "n_per_group": design.n_per_group(),
        "tested": design.tested,
        "adjusted_for": design.adjusted_for,
        "effects": design.interest_names,
        "left_out": [asdict(case) for case in design.left_out],
        "unmatched_rows": design.unmatched,
        "notes": design.notes,
        "global_test": {"modes": analysis.global_test.modes,
                        "statistic": analysis.global_test.statistic,
                        "p": analysis.global_test.p,
                        "permutations": analysis.global_test.permutations},
        "centroid_size": size_summary(analysis),
        "significant_points": {"fwer": int(analysis.significant("fwer").sum()),
                               "fdr": int(analysis.significant("fdr").sum()),
                               "of": len(analysis.mean)},
        "degrees_of_freedom": analysis.points.df,
        "point_test": {"statistic": analysis.points.name,
                       "variance": analysis.points.variance,
                       "variance_groups": (design.n_per_group() if analysis.points.variance
                                           == "groups" else None),
                       "family_wise": analysis.points.family_wise,
                       "resampling": analysis.points.resampling,
                       "tail": analysis.points.tail,
                       "permutations": analysis.points.permutations,
                       "p": "each point's own permutation p-value",
                       "smallest_p": 1.0 / (analysis.points.permutations + 1),
                       "uncorrected_significant": int(np.sum(analysis.points.p
                                                             <= config.alpha)),
                       "tfce": tfce_summary(analysis.points, config.alpha)},
        "effect_tests": [{"name": found.name, "column": found.column,
                          "statistic": ("Welch's v" if found.test.variance == "groups"
                                        else "Student's t"),
                          "tail": found.test.tail, "resampling": found.test.resampling,
                          "degrees_of_freedom": found.test.df,
                          "the_point_test": found.joint, "contrast": found.contrast,
                          "significant_points": {
                              "fwer": int(np.sum(found.test.p_fwer <= config.alpha)),
                              "fdr": int(np.sum(found.test.q_fdr <= config.alpha))},
                          "tfce": tfce_summary(found.test, config.alpha)}
                         for found in analysis.signed],
        "effect_sizes": effects_summary(analysis),
        "shapes": shapes_summary(analysis, table),
        "classification": None, "discriminant": None,
        "unusual": {"modes": analysis.unusual.distances.modes,
                    "thresholds": analysis.unusual.distances.threshold.tolist(),
                    "null": analysis.unusual.distances.null.to_json(),
                    "flagged": [n for n, o in zip(analysis.unusual.names,
                                                  analysis.unusual.distances.outlier) if o]},
    }
    if analysis.classification is not None:
        summary["classification"] = classification_summary(analysis)
    if analysis.discriminant is not None:
        summary["discriminant"] = {"modes": analysis.discriminant.modes,
                                   "shrinkage": analysis.discriminant.shrinkage}
    return summary


def _write(folder: Path, analysis: Analysis, summary: dict, model, table):
    io.write_text(folder / SUMMARY, json.dumps(summary, indent=2))
    if analysis.config.long_table:
        io.write_csv(folder / "long.csv", *long_table(analysis, table))
    header, rows = _columns(analysis)
    io.write_csv(folder / POINTS, header, rows)
    arrays = {"statistic": analysis.points.statistic, "p": analysis.points.p,
              "p_fwer": analysis.points.p_fwer, "q_fdr": analysis.points.q_fdr,
              "minus_log10_p_fwer": -np.log10(analysis.points.p_fwer),
              "significant_fwer": analysis.significant("fwer").astype(np.uint8),
              "significant_fdr": analysis.significant("fdr").astype(np.uint8),
              **tfce_columns(analysis.points)}
    for name, difference, normal in zip(analysis.subjects.interest_names, analysis.difference,
                                        analysis.normal_difference):
        suffix = "" if len(analysis.subjects.interest_names) == 1 else f"_{name}"
        arrays[f"difference{suffix}"] = difference
        arrays[f"normal_difference{suffix}_mm"] = normal
    arrays.update(signed_columns(analysis))
    arrays.update(effect_columns(analysis))
    parts = model.part_meshes()
    if len(parts) == 1:
        io.write_polydata(folder / EFFECTS, analysis.mean, model.triangles,
                          point_data=arrays)
    else:
        (folder / EFFECTS_PARTS).mkdir()
        for part in parts:
            io.write_polydata(folder / EFFECTS_PARTS / f"{part.name}.vtp", analysis.mean[part.rows],
                              part.triangles,
                              point_data={k: v[part.rows] for k, v in arrays.items()})
    if analysis.shapes:
        (folder / SHAPES).mkdir()
    for shape in analysis.shapes:
        io.write_polydata(io.case_file(folder / SHAPES, shape.name), shape.points,
                          model.triangles,
                          point_data={"displacement": shape.displacement,
                                      "normal_displacement_mm": shape.normal_displacement})
    unusual = analysis.unusual
    io.write_csv(folder / "unusual.csv",
                 ["case", "mahalanobis", "p", "p_normal", "flagged", "max_departure_mm",
                  "at_point"],
                 [[name, f"{d:.6g}", f"{p:.6g}", f"{p_normal:.6g}", bool(o), f"{dep.max():.6g}",
                   int(dep.argmax())]
                  for name, d, p, p_normal, o, dep in zip(
                      unusual.names, unusual.distances.distance, unusual.distances.p,
                      unusual.distances.p_normal, unusual.distances.outlier, unusual.departure)])
    (folder / "unusual").mkdir()
    for name, departure in zip(unusual.names, unusual.departure):
        io.write_polydata(io.case_file(folder / "unusual", name), model.mean, model.triangles,
                          point_data={"departure_mm": departure})
    write_analysis_page(folder / PAGE, summary, analysis, model)


def earlier_analysis(output) -> list:
    """The files of an earlier analysis in ``output`` (empty when there is none)."""
    return io.earlier_outputs(output, ANALYSIS_FILES)


def analyze_build(build, table, output, config: AnalysisConfig | None = None, progress=None,
                  overwrite: bool = False) -> AnalysisResult:
    """Analyse a build's shapes against a subjects table and write the output folder.

    Parameters
    ----------
    build : path
        A build's output folder (``mdlshapemodel build -o BUILD``).
    table : path
        The subjects table (CSV with a ``case`` column).
    output : path
        The analysis's folder (created; an earlier analysis there is refused unless
        ``overwrite``).
    config : AnalysisConfig
        What to test and how (``group`` and/or ``covariates`` must be set).
    progress : callable, optional
        The library's progress protocol.

    Returns
    -------
    AnalysisResult

    Examples
    --------
    ::

        from mdlshapemodel.analyze import analyze_build
        from mdlshapemodel.config import AnalysisConfig

        result = analyze_build("out", "subjects.csv", "findings",
                               AnalysisConfig(group="diagnosis", nuisance=["age"]))
        result.summary["significant_points"], result.summary["global_test"]["p"]
    """
    config = (config or AnalysisConfig()).validate()
    output = Path(output)
    built = read_build(build)
    design = subjects(table, built.model.names, config.group, config.covariates,
                      config.nuisance, config.reference, config.categorical, config.test,
                      config.subject, config.time, config.baseline, config.interactions)
    contrasts_of(design, config)          # a contrast of untested levels: refused up front
    if output.resolve() == Path(build).resolve():
        raise InputError(f"{output}: the output folder is the build folder; choose another")
    io.refuse_earlier(output, earlier_analysis(output), overwrite, "analysis")
    analysis = analyze_shapes(built.model, built.shapes, design, config, progress)
    summary = summary_of(analysis, build, table)
    with io.written_folder(output, ANALYSIS_FILES) as folder:
        _write(folder, analysis, summary, built.model, table)
    return AnalysisResult(output, analysis, summary)
