"""A build's outputs: what goes into its folder's files (the model, the meshes, the tables of the
cases, scores and landmarks, the metrics) and the report, written through
:class:`~.folders.BuildFolder`, which alone knows the files' names and columns. In two steps:
:func:`write_shapes` (the model, meshes and tables), then, once the build has evaluated the model
(:func:`~.model.evaluation.evaluate_state`), :func:`write_outputs` (metrics.json and the report)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .folders import BuildFolder, CorrespondedLandmark, physical_shapes
from .model.evaluation import measure_differences
from .model.normals import CASE_OFF_SHARE, OFF_DEGREES, SPREAD_DEGREES, normal_agreement
from .model.shape_model import ShapeModel, score_outliers
from .prepare.curve import CurveMap, point_curve_distances
from .prepare.surface import point_surface_distances
from .report.html import write_report

log = logging.getLogger("mdlshapemodel")


@dataclass
class BuildResult:
    """What a build produced and measured."""

    output: Path
    model: ShapeModel
    metrics: dict
    initial_objective: float
    final_objective: float
    cases: list
    rejected: list
    interrupted: bool = False
    warnings: list = field(default_factory=list)   # what the user should know (metrics.json)
    # the optimisation ended by its stopping rule (None: nothing was optimised); metrics.json's
    # ``optimisation`` says more
    converged: bool | None = None


def warp_summary(example) -> str:
    """What an example's reparameterization is made of, e.g. ``field:9`` or
    ``symmetric_theta:12 rotation:3`` ('' for the initial correspondence)."""
    counts = {}
    for part in getattr(example, "parts", []):
        for kind, count in part.warp_counts().items():
            counts[kind] = counts.get(kind, 0) + count
    return " ".join(f"{kind}:{count}" for kind, count in counts.items() if count)


def _input_points(mapped) -> np.ndarray:
    """The input surface's vertices, or a 2-D curve's points (n, 2)."""
    return mapped.points if isinstance(mapped, CurveMap) else mapped.vertices


def input_distances(mapped, corresponded: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """From each vertex of a part's input surface (point of its curve) to the corresponded
    points meshed with ``cells`` (triangles, or segments for a curve)."""
    if isinstance(mapped, CurveMap):
        return point_curve_distances(mapped.points, corresponded[:, :2], cells)
    return point_surface_distances(mapped.vertices, corresponded, cells)


def sphere_quality(case) -> dict:
    """The sphere maps' quality columns of cases.csv (all parts together; empty for curves,
    whose arc-length map on the circle has no distortion to report)."""
    keys = ("sphere_flips", "sphere_mean_abs_log_area", "sphere_p95_abs_log_area",
            "sphere_seconds")
    if case.is_curve:
        return dict.fromkeys(keys, "")
    qualities = [part.map.quality for part in case.parts]
    return dict(zip(keys, (sum(q["flipped_triangles"] for q in qualities),
                           float(np.mean([q["mean_abs_log_area_ratio"] for q in qualities])),
                           max(q["p95_abs_log_area_ratio"] for q in qualities),
                           sum(q["seconds"] for q in qualities))))


def corresponded_distances(raw: np.ndarray, prepared: list, parts: list) -> np.ndarray | None:
    """How far each case's corresponded mesh is from its input surface, as a value per
    corresponded point (n_s, n_p), mm: every input vertex's distance to the corresponded mesh
    (as cases.csv measures fidelity), the largest of those nearest to each point (0 where none
    is). The points themselves lie on the input surface; the mesh between them need not. The
    viewer colours a case by it; None for 2-D curves."""
    from scipy.spatial import cKDTree

    if any(case.is_curve for case in prepared):
        return None
    result = np.zeros((len(prepared), len(raw[0])))
    for i, case in enumerate(prepared):
        for prepared_part, part in zip(case.parts, parts):
            points = raw[i][part.rows]
            away = input_distances(prepared_part.map, points, part.triangles)
            _, nearest = cKDTree(points).query(prepared_part.map.vertices)
            np.maximum.at(result[i, part.rows], nearest, away)
    return result


def corresponded_landmarks(model, physical: list, prepared: list, given: dict | None) -> list:
    """Every case's :class:`CorrespondedLandmark` of each of the model's landmarks
    (``model.landmarks``; ``physical``: the corresponded shapes in the inputs' coordinates;
    ``given``: case name -> Landmarks)."""
    records = []
    for points, case in zip(physical, prepared):
        marks = (given or {}).get(case.name)
        for label, row in model.landmarks.items():
            records.append(CorrespondedLandmark(case.name, label, points[row],
                                                None if marks is None else marks.get(label)))
    return records


def landmark_summary(model, records: list) -> dict | None:
    """metrics.json's ``landmarks`` from the :class:`CorrespondedLandmark` records: the labels,
    how many were given, the distance of every corresponded landmark from the given one (mean,
    max) and per label (cases, mean, max and the case of the max); None for a model without
    landmarks."""
    if not model.landmarks:
        return None
    given = [record for record in records if record.given is not None]
    per_label = {}
    for label in model.landmarks:
        mine = [(record.distance, record.case) for record in given if record.label == label]
        if mine:
            worst = max(mine)
            per_label[label] = {"cases": len(mine),
                                "mean_mm": float(np.mean([d for d, _ in mine])),
                                "max_mm": worst[0], "max_case": worst[1]}
    distances = [record.distance for record in given]
    return {"labels": list(model.landmarks), "given": len(given),
            "distance_mm": {"mean": float(np.mean(distances)), "max": float(np.max(distances))}
            if distances else None, "per_label": per_label}


def flagged_cases(names, outlier: dict, normals) -> dict:
    """metrics.json's ``flagged_cases``: each case a check of the build marks, with what marks
    it (the column ``flags`` of cases.csv): its scores' Mahalanobis distance has p < 0.01
    (``outlier``, :func:`~.model.shape_model.score_outliers`), or its normals are off at more
    than :data:`~.model.normals.CASE_OFF_SHARE` of the points (``normals``, a
    :class:`~.model.normals.NormalAgreement`, None for none)."""
    off = None if normals is None else normals.cases_off()
    marked = None if normals is None else normals.cases_flagged()
    flagged = {}
    for i, name in enumerate(names):
        reasons = []
        if outlier["outlier"][i]:
            reasons.append(f"score outlier (Mahalanobis distance {outlier['distance'][i]:.2f}, "
                           f"p = {outlier['p'][i]:.2g})")
        if marked is not None and marked[i]:
            reasons.append(f"normals off at {int(off[i])} points (more than "
                           f"{OFF_DEGREES:.0f}° from the mean direction)")
        if reasons:
            flagged[name] = reasons
    return flagged


def against_baselines(quality: dict, baselines: dict) -> dict:
    """metrics.json's ``baselines``: each baseline's measures (as from
    :func:`~.model.evaluation.evaluate`) and, under ``differences``, the model's measures minus
    the baseline's with their standard errors and verdicts
    (:func:`~.model.evaluation.measure_differences`: the rule of ``mdlshapemodel compare``;
    "better": the model's value is lower). The generalization's jackknifes (``jackknife`` of
    ``quality`` and of each baseline) are taken out: they are not JSON."""
    mine = quality.pop("jackknife", None)
    recorded = {}
    for name, values in baselines.items():
        values = dict(values)
        theirs = values.pop("jackknife", None)
        values["differences"] = measure_differences(values, quality, theirs, mine)
        recorded[name] = values
    return recorded


@dataclass
class WrittenShapes:
    """What :func:`write_shapes` wrote and found, for metrics.json and the report."""

    cases: list               # the rows of cases.csv
    landmarks: list           # CorrespondedLandmark, the rows of landmarks.csv
    normals: object           # NormalAgreement, None for 2-D curves
    outlier: dict             # score_outliers
    flagged: dict             # flagged_cases
    aligned: np.ndarray       # the corresponded shapes in the model's frame
    distances: np.ndarray | None   # corresponded_distances


def write_shapes(output: Path, corresponded, prepared: list) -> WrittenShapes:
    """The first files of a build's folder (:class:`~.folders.BuildFolder`): the model, the
    mean, correspondence/, aligned/, scores.csv, cases.csv and for a guided build landmarks.csv,
    of the :class:`~mdlshapemodel.build.Correspondence` of the ``prepared`` cases."""
    folder = BuildFolder(output)
    state, model = corresponded.state, corresponded.model
    triangles = model.triangles
    aligned = state.aligned_shapes()
    raw = state.raw_shapes()
    names = model.names
    started = time.perf_counter()
    parts = model.part_meshes()
    normals = None if triangles is None else normal_agreement(aligned, triangles,
                                                              model.part_of_triangles())
    folder.write_model(model, normals)
    outlier = score_outliers(model)
    normals_off = None if normals is None else normals.cases_off()
    flagged = flagged_cases(names, outlier, normals)
    cases = []
    physical = physical_shapes(raw, [case.mirrored for case in prepared])
    folder.write_case_meshes(model, [case.name for case in prepared], physical, aligned)
    for i, case in enumerate(prepared):
        # from each input-surface vertex (curve point) to the corresponded mesh of its part
        distances = np.concatenate([
            input_distances(prepared_part.map, raw[i][part.rows], part.triangles)
            for prepared_part, part in zip(case.parts, parts)])
        cases.append({"case": case.name, "flags": "; ".join(flagged.get(case.name, [])),
                      "file": ";".join(case.paths),
                      "surface_vertices": int(sum(len(_input_points(p.map))
                                                  for p in case.parts)),
                      "mean_distance_mm": float(distances.mean()),
                      "max_distance_mm": float(distances.max()),
                      "mean_distance_voxels": float(distances.mean() / case.voxel_size),
                      **sphere_quality(case),
                      "warps": int(sum(sum(p.warp_counts().values())
                                       for p in getattr(state.examples[i], "parts", []))),
                      "warp_kinds": warp_summary(state.examples[i]),
                      "normals_off": "" if normals_off is None else int(normals_off[i]),
                      "mahalanobis": float(outlier["distance"][i]),
                      "unusual_p": float(outlier["p"][i]),
                      "unusual_p_normal": float(outlier["p_normal"][i]),
                      "score_outlier": bool(outlier["outlier"][i]),
                      "smoothing_sigma": ("" if case.smoothing_sigma is None
                                          else case.smoothing_sigma),
                      "repair": case.repair, "mirrored": case.mirrored})
    folder.write_scores(names, model.scores)
    folder.write_cases(cases)
    landmarks = corresponded_landmarks(model, physical, prepared, corresponded.landmarks)
    folder.write_landmarks(landmarks)
    log.info("wrote the model, meshes and tables in %.1f s", time.perf_counter() - started)
    return WrittenShapes(cases, landmarks, normals, outlier, flagged, aligned,
                         corresponded_distances(raw, prepared, parts))


def write_outputs(output: Path, corresponded, rejected: list, written: WrittenShapes,
                  quality: dict, baselines: dict | None = None, warnings=(),
                  landmark_check=None) -> BuildResult:
    """The last files of a build's folder, after :func:`write_shapes` (``written``):
    metrics.json and report.html. ``quality`` is the model's measures
    (:func:`~.model.evaluation.evaluate_state`) and ``baselines`` the baselines' with their
    differences (:func:`against_baselines`); ``landmark_check`` (a
    :class:`~mdlshapemodel.model.landmarks.LandmarkCheck`, optional) goes to metrics.json and
    the report."""
    state, model = corresponded.state, corresponded.model
    initial, final = corresponded.initial_objective, corresponded.final_objective
    voxel, data_range = corresponded.voxel_size, corresponded.data_range
    interrupted = corresponded.interrupted
    names = model.names
    cases, normals, outlier = written.cases, written.normals, written.outlier
    metrics = {"objective": {"initial": initial, "final": final,
                             "parts": {"initial": corresponded.initial.to_json(),
                                       "final": corresponded.final.to_json()},
                             "n_points": corresponded.objective_points,
                             "units": "nats: the description length (eq. 14, Delta averaged over "
                                      "delta_range) + the smoothness prior + the landmark "
                                      "guides' term"},
               "strategy": model.metadata["strategy"], "n_shapes": state.n_shapes,
               "n_points": state.n_points,
               "n_rejected": len(rejected), "voxel_size_mm": voxel, "data_range_mm": data_range,
               "interrupted": interrupted,
               "optimisation": corresponded.optimisation.to_json(),
               "evaluations": state.evaluations,
               "variances": model.variances.tolist(), **quality,
               "score_outliers": {"modes": outlier["modes"],
                                  "thresholds": np.asarray(outlier["threshold"]).tolist(),
                                  "null": (None if outlier["null"] is None
                                           else outlier["null"].to_json()),
                                  "cases": [n for n, o in zip(names, outlier["outlier"]) if o]},
               "flagged_cases": written.flagged,
               "normals": None if normals is None else {
                   "spread_degrees_median": float(np.median(normals.spread_degrees)),
                   "flagged_points": int(np.count_nonzero(normals.flagged)),
                   "flagged_fraction": float(np.mean(normals.flagged)),
                   "spread_threshold_degrees": SPREAD_DEGREES,
                   "off_degrees": OFF_DEGREES, "case_off_share": CASE_OFF_SHARE},
               "surface_distance_mm": {
                   "mean": float(np.mean([c["mean_distance_mm"] for c in cases])),
                   "max": float(np.max([c["max_distance_mm"] for c in cases]))},
               "landmarks": landmark_summary(model, written.landmarks),
               "landmark_check": None if landmark_check is None else landmark_check.to_json(),
               "baselines": baselines or {}, "warnings": list(warnings)}
    BuildFolder(output).write_metrics(metrics)
    started = time.perf_counter()
    write_report(output, metrics, cases, rejected, model, written.aligned, names,
                 written.distances, normals)
    log.info("wrote the report in %.1f s", time.perf_counter() - started)
    return BuildResult(output, model, metrics, initial, final, cases, rejected, interrupted,
                       list(warnings), corresponded.optimisation.converged)
