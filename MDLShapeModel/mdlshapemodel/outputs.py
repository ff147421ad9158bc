"""The files of a build's output folder: model.h5, mean.vtp, correspondence/, aligned/ (with a
sub-folder per part of a multi-part object), the tables, metrics.json, the checkpoint, and (through
:mod:`.report`) report.html."""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .config import BuildConfig
from .correspondence.state import CorrespondenceState, state_record
from .correspondence.strategies.base import PhasePoint
from .correspondence.trace import TraceRow
from .errors import BuildError
from .model.evaluation import evaluate_state, measure_differences
from .model.normals import CASE_OFF_SHARE, OFF_DEGREES, SPREAD_DEGREES, normal_agreement
from .model.shape_model import ShapeModel, score_outliers
from .prepare import io
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


# What a build writes into its output folder. Other entries are not a build's: the inputs/ that the
# demo and the Slicer module write there first, or anything else a user keeps there.
BUILD_FILES = ("model.h5", "mean.vtp", "correspondence", "aligned", "scores.csv", "cases.csv",
               "landmarks.csv", "metrics.json", "report.html", "rejected.csv", "convergence.csv",
               "config.json", "checkpoint.npz", "build.log")


def previous_build(output) -> list:
    """The files and (non-empty) folders of an earlier build in ``output``, in
    :data:`BUILD_FILES` order; empty when there is none."""
    output = Path(output)
    found = []
    for name in BUILD_FILES:
        path = output / name
        if path.is_file() or (path.is_dir() and any(path.iterdir())):
            found.append(path)
    return found


# The files whose presence makes a folder hold a build that a new one must not replace unasked:
# a finished build's model, or the checkpoint of one that can be resumed. What a failed or
# cancelled start leaves (build.log, config.json, rejected.csv, empty folders) is cleared by the
# next build without asking.
KEPT_BUILD_FILES = ("model.h5", "checkpoint.npz")


def earlier_build(output) -> list:
    """The files of a finished or resumable build in ``output`` (:data:`KEPT_BUILD_FILES`);
    empty when there is none, also when a failed start left other files there."""
    return [Path(output) / name for name in KEPT_BUILD_FILES if (Path(output) / name).is_file()]


def clear_previous_build(output) -> None:
    """Remove an earlier build's files and folders from ``output`` (and nothing else)."""
    for path in previous_build(output):
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()
    remove_partial_files(output)


def remove_partial_files(output) -> None:
    """Remove the temporary files of writes that a killed build left unfinished
    (:func:`~.prepare.io.written_whole`; they never hold a final name)."""
    for name in BUILD_FILES:
        folder = Path(output) / name
        if folder.is_dir():
            for path in folder.rglob(f".*{io.PARTIAL}*"):   # parts have folders of their own
                path.unlink(missing_ok=True)
    for path in Path(output).glob(f".*{io.PARTIAL}*"):
        path.unlink(missing_ok=True)


@dataclass
class Checkpoint:
    """What ``--resume`` needs of a checkpoint: the state's record, the point the optimisation
    had reached (``PhasePoint.DONE`` once it ended), the random generator's state, the trace so
    far and the evaluation count, and the fingerprint of the inputs and settings it is of."""

    record: dict              # :func:`~.correspondence.state.state_record` arrays
    point: PhasePoint
    rng_state: dict | None    # ``numpy.random.Generator.bit_generator.state``
    trace_rows: list          # TraceRow
    evaluations: int
    fingerprint: dict


def save_checkpoint(path: Path, state: CorrespondenceState, point: PhasePoint | None = None,
                    rng=None, trace=None, fingerprint: dict | None = None):
    """The state's correspondence (:func:`~.correspondence.state.state_record`: every accepted
    warp, every pose, the area weights) and, for resuming, the point reached, the generator's
    state, the trace and the fingerprint: data only (numbers, strings, JSON; no pickle), written
    whole or not at all."""
    arrays = dict(state_record(state))
    arrays["evaluations"] = np.array(state.evaluations)
    if point is not None:
        arrays["point"] = np.array(point.to_json())
    if rng is not None:
        arrays["rng_state"] = np.array(json.dumps(rng.bit_generator.state))
    if trace is not None:
        rows = trace.rows
        arrays["trace_numbers"] = np.array([[r.wall_seconds, r.cpu_seconds, r.evaluations,
                                             r.objective, r.sweep] for r in rows],
                                           dtype=np.float64).reshape(-1, 5)
        arrays["trace_phases"] = np.array([r.phase for r in rows], dtype=str)
    if fingerprint is not None:
        arrays["fingerprint"] = np.array(json.dumps(fingerprint, sort_keys=True))
    with io.written_whole(path) as temporary, open(temporary, "wb") as handle:
        np.savez(handle, **arrays)


def load_checkpoint(path: Path) -> dict:
    """The arrays of a checkpoint written by :func:`save_checkpoint`, for
    :func:`~.correspondence.state.replay_record` (data only: no pickle is read)."""
    with np.load(path, allow_pickle=False) as data:
        return {name: data[name] for name in data.files}


def read_checkpoint(path: Path) -> Checkpoint:
    """The :class:`Checkpoint` of a build's ``checkpoint.npz``; :class:`~.errors.BuildError`
    when it is not one that can be resumed from."""
    try:
        arrays = load_checkpoint(path)
        numbers, phases = arrays["trace_numbers"], arrays["trace_phases"]
        rows = [TraceRow(float(w), float(c), int(e), float(f), str(phase), int(s))
                for (w, c, e, f, s), phase in zip(numbers, phases)]
        return Checkpoint(arrays, PhasePoint.from_json(str(arrays["point"])),
                          json.loads(str(arrays["rng_state"])), rows,
                          int(arrays["evaluations"]), json.loads(str(arrays["fingerprint"])))
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise BuildError(f"{path}: not a checkpoint to resume from ({error})") from None


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


def physical_shapes(raw: np.ndarray, prepared: list) -> list:
    """The corresponded shapes in the physical space of their inputs, so that they overlay them:
    ``raw`` (the state's samples of the prepared surfaces) with those of mirrored cases
    reflected back (x -> -x)."""
    return [points * [-1.0, 1.0, 1.0] if case.mirrored else points
            for points, case in zip(raw, prepared)]


LANDMARK_COLUMNS = ("case", "label", "x", "y", "z", "given_x", "given_y", "given_z",
                    "distance_mm")


@dataclass(frozen=True)
class CorrespondedLandmark:
    """One case's corresponded point of one of the model's landmarks, in its input's coordinates,
    and the landmark it was given (None where it has none): a row of landmarks.csv."""

    case: str
    label: str
    point: np.ndarray
    given: np.ndarray | None

    @property
    def distance(self) -> float | None:
        """mm between the corresponded point and the given landmark (None: none given)."""
        return None if self.given is None else float(np.linalg.norm(self.point - self.given))

    def row(self) -> list:
        """The row of landmarks.csv (:data:`LANDMARK_COLUMNS`)."""
        given = (["", "", "", ""] if self.given is None else
                 [*(f"{v:.6f}" for v in self.given), f"{self.distance:.6f}"])
        return [self.case, self.label, *(f"{v:.6f}" for v in self.point)] + given


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


def write_outputs(output: Path, corresponded, prepared: list, rejected: list,
                  config: BuildConfig, baselines: dict | None = None, pool=None,
                  warnings=(), landmark_check=None) -> BuildResult:
    """model.h5, mean.vtp, correspondence/, aligned/, scores.csv, metrics.json, report.html (and
    for a guided build landmarks.csv), of the :class:`~mdlshapemodel.build.Correspondence` of
    the ``prepared`` cases; ``landmark_check`` (a
    :class:`~mdlshapemodel.model.landmarks.LandmarkCheck`, optional) goes to metrics.json and
    the report."""
    state, model = corresponded.state, corresponded.model
    initial, final = corresponded.initial_objective, corresponded.final_objective
    voxel, data_range = corresponded.voxel_size, corresponded.data_range
    interrupted = corresponded.interrupted
    triangles = model.triangles
    aligned = state.aligned_shapes()
    raw = state.raw_shapes()
    names = model.names
    started = time.perf_counter()
    model.save(output / "model.h5")
    parts = model.part_meshes()
    normals = None if triangles is None else normal_agreement(aligned, triangles,
                                                              model.part_of_triangles())
    io.write_polydata(output / "mean.vtp", model.mean, triangles,
                      point_data=None if normals is None else {
                          "normal_spread_degrees": normals.spread_degrees,
                          "normal_agreement": normals.resultant},
                      cell_data={"part": model.part_of_triangles()} if model.part_names else None)
    outlier = score_outliers(model)
    normals_off = None if normals is None else normals.cases_off()
    flagged = flagged_cases(names, outlier, normals)
    cases = []
    physical = physical_shapes(raw, prepared)
    for folder in ("correspondence", "aligned"):
        for part in parts:
            (output / folder / part.name).mkdir(parents=True, exist_ok=True)
    for i, case in enumerate(prepared):
        for folder, shape in (("correspondence", physical[i]), ("aligned", aligned[i])):
            for part in parts:
                io.write_polydata(io.case_file(output / folder / part.name, case.name),
                                  shape[part.rows], part.triangles)
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
                      "warps": int(sum(len(p.warps) for p in getattr(state.examples[i], "parts",
                                                                      []))),
                      "warp_kinds": warp_summary(state.examples[i]),
                      "normals_off": "" if normals_off is None else int(normals_off[i]),
                      "mahalanobis": float(outlier["distance"][i]),
                      "score_outlier": bool(outlier["outlier"][i]),
                      "smoothing_sigma": ("" if case.smoothing_sigma is None
                                          else case.smoothing_sigma),
                      "repair": case.repair, "mirrored": case.mirrored})
    n_modes = model.n_modes
    io.write_csv(output / "scores.csv", ["case"] + [f"mode_{m + 1}" for m in range(n_modes)],
                 [[name] + [f"{v:.6g}" for v in row] for name, row in zip(names, model.scores)])
    io.write_csv(output / "cases.csv", list(cases[0].keys()),
                 [[c.get(k, "") for k in cases[0]] for c in cases])
    landmarks = corresponded_landmarks(model, physical, prepared, corresponded.landmarks)
    if landmarks:
        io.write_csv(output / "landmarks.csv", LANDMARK_COLUMNS,
                     [record.row() for record in landmarks])
    log.info("wrote the model, meshes and tables in %.1f s", time.perf_counter() - started)
    started = time.perf_counter()
    quality = evaluate_state(state, config, prepared, model, pool=pool, background=False,
                             jackknife=bool(baselines))
    baselines = against_baselines(quality, baselines or {})
    log.info("evaluated the model in %.1f s", time.perf_counter() - started)
    metrics = {"objective": {"initial": initial, "final": final,
                             "n_points": corresponded.objective_points,
                             "units": "nats (eq. 14, Delta averaged over delta_range)"},
               "strategy": model.metadata["strategy"], "n_shapes": state.n_shapes,
               "n_points": state.n_points,
               "n_rejected": len(rejected), "voxel_size_mm": voxel, "data_range_mm": data_range,
               "interrupted": interrupted,
               "optimisation": corresponded.optimisation.to_json(),
               "evaluations": state.evaluations,
               "variances": model.variances.tolist(), **quality,
               "score_outliers": {"modes": outlier["modes"], "threshold": outlier["threshold"],
                                  "cases": [n for n, o in zip(names, outlier["outlier"]) if o]},
               "flagged_cases": flagged,
               "normals": None if normals is None else {
                   "spread_degrees_median": float(np.median(normals.spread_degrees)),
                   "flagged_points": int(np.count_nonzero(normals.flagged)),
                   "flagged_fraction": float(np.mean(normals.flagged)),
                   "spread_threshold_degrees": SPREAD_DEGREES,
                   "off_degrees": OFF_DEGREES, "case_off_share": CASE_OFF_SHARE},
               "surface_distance_mm": {
                   "mean": float(np.mean([c["mean_distance_mm"] for c in cases])),
                   "max": float(np.max([c["max_distance_mm"] for c in cases]))},
               "landmarks": landmark_summary(model, landmarks),
               "landmark_check": None if landmark_check is None else landmark_check.to_json(),
               "baselines": baselines, "warnings": list(warnings)}
    io.write_text(output / "metrics.json", json.dumps(metrics, indent=2))
    started = time.perf_counter()
    write_report(output, metrics, cases, rejected, model, aligned, names,
                 corresponded_distances(raw, prepared, parts), normals)
    log.info("wrote the report in %.1f s", time.perf_counter() - started)
    return BuildResult(output, model, metrics, initial, final, cases, rejected, interrupted,
                       list(warnings), corresponded.optimisation.converged)
