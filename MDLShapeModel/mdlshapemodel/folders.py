"""The folders a build and a fit leave: every file name and column of them, read and written here.

A build's output folder (``mdlshapemodel build -o FOLDER``) is the interface between the stages
that make a model and the ones that use it (``fit``, ``compare``, ``analyze``, the VTK reader, the
3D Slicer module). :class:`BuildFolder` is its one owner:

- reading: :meth:`~BuildFolder.model`, :meth:`~BuildFolder.shapes` (the corresponded shapes in
  the model's frame: a mirrored case reflected again, here alone), :meth:`~BuildFolder.metrics`,
  :meth:`~BuildFolder.measures`, :meth:`~BuildFolder.cases`, :meth:`~BuildFolder.scores`,
  :meth:`~BuildFolder.landmarks`, :meth:`~BuildFolder.rejected`, the checkpoint
  (:meth:`~BuildFolder.checkpoint`) and the files of an earlier build;
- writing: the model, the meshes, the tables (one landmarks.csv schema, :data:`LANDMARK_COLUMNS`,
  and one scores.csv writer, :func:`write_scores`, for builds and fits alike), metrics.json,
  config.json, convergence.csv, the checkpoint.

:class:`FitFolder` is the same for the folder of ``mdlshapemodel fit``.

Every file is written whole or not at all (:func:`~.prepare.io.written_whole`).
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .config import BuildConfig
from .correspondence.state import CorrespondenceState, state_record
from .correspondence.strategies.base import PhasePoint
from .correspondence.trace import Trace, TraceRow
from .errors import BuildError, InputError
from .model.evaluation import GeneralizationJackknife
from .model.shape_model import ShapeModel
from .prepare import io
from .prepare.case import Rejection
from .prepare.surface import mirror_points

# the entries of a build's output folder
MODEL = "model.h5"
MEAN = "mean.vtp"
CORRESPONDENCE = "correspondence"    # each case's corresponded mesh in its input's space
ALIGNED = "aligned"                  # the same in the model's frame
SCORES = "scores.csv"
CASES = "cases.csv"
LANDMARKS = "landmarks.csv"
METRICS = "metrics.json"
REPORT = "report.html"
REJECTED = "rejected.csv"
CONVERGENCE = "convergence.csv"
CONFIG = "config.json"
CHECKPOINT = "checkpoint.npz"
BASELINES = "baselines.json"         # the baselines' evaluations, for --resume (kept with it)
LOG = "build.log"
SURFACES = "prepared-surfaces.tmp"   # the prepared cases' surfaces while a build runs (removed)

# What a build writes into its output folder. Other entries are not a build's: the inputs/ that the
# demo and the Slicer module write there first, or anything else a user keeps there.
BUILD_FILES = (MODEL, MEAN, CORRESPONDENCE, ALIGNED, SCORES, CASES, LANDMARKS, METRICS, REPORT,
               REJECTED, CONVERGENCE, CONFIG, CHECKPOINT, BASELINES, LOG)

# The files whose presence makes a folder hold a build that a new one must not replace unasked:
# a finished build's model, or the checkpoint of one that can be resumed. What a failed or
# cancelled start leaves (build.log, config.json, rejected.csv, empty folders) is cleared by the
# next build without asking.
KEPT_BUILD_FILES = (MODEL, CHECKPOINT)

# the entries of a fit's output folder (beside correspondence/, scores.csv, rejected.csv and
# landmarks.csv, which are as a build's)
RECONSTRUCTION = "reconstruction"    # the model's reconstruction of each fitted case
FIT_SUMMARY = "fit.json"
FIT_FILES = (CORRESPONDENCE, RECONSTRUCTION, SCORES, FIT_SUMMARY, REJECTED, LANDMARKS)

REJECTED_COLUMNS = ("case", "file", "reason")
LANDMARK_COLUMNS = ("case", "label", "x", "y", "z", "given_x", "given_y", "given_z",
                    "distance_mm")

# metrics.json's measures per number of modes (each with its standard error under NAME_se), and
# the titles of :meth:`BuildFolder.measures`
MODE_MEASURES = {"compactness": "C", "generalization": "G", "specificity": "S",
                 "generalization_mm": "G (mm)", "specificity_mm": "S (mm)"}


# -- the rows of the tables ---------------------------------------------------------------------

def score_header(n_modes: int) -> list:
    """The columns of scores.csv: the case, then mode_1 .. mode_n."""
    return ["case"] + [f"mode_{m + 1}" for m in range(n_modes)]


def write_scores(path, names, scores) -> None:
    """scores.csv (:func:`score_header`) of the cases ``names`` and their scores (n, n_modes),
    a build's or a fit's."""
    scores = np.asarray(scores, dtype=np.float64).reshape(len(names), -1)
    io.write_csv(path, score_header(scores.shape[1]),
                 [[name] + [f"{v:.6g}" for v in row] for name, row in zip(names, scores)])


def write_rejected(path, rejected) -> None:
    """rejected.csv (:data:`REJECTED_COLUMNS`) of :class:`~.prepare.case.Rejection`\\ s."""
    io.write_csv(path, REJECTED_COLUMNS, [(r.name, r.path, r.reason) for r in rejected])


def read_rejected(path) -> list:
    """The :class:`~.prepare.case.Rejection`\\ s of a rejected.csv (none when it is absent)."""
    path = Path(path)
    if not path.is_file():
        return []
    return [Rejection(row["case"], row["file"], row["reason"]) for row in io.read_csv(path)]


@dataclass(frozen=True)
class CorrespondedLandmark:
    """One case's corresponded point of one of the model's landmarks, in its input's coordinates,
    and the landmark it was given (None where it has none): a row of landmarks.csv."""

    case: str
    label: str
    point: np.ndarray
    given: np.ndarray | None = None

    @property
    def distance(self) -> float | None:
        """mm between the corresponded point and the given landmark (None: none given)."""
        return None if self.given is None else float(np.linalg.norm(self.point - self.given))

    def row(self) -> list:
        """The row of landmarks.csv (:data:`LANDMARK_COLUMNS`)."""
        given = (["", "", "", ""] if self.given is None else
                 [*(f"{v:.6f}" for v in self.given), f"{self.distance:.6f}"])
        return [self.case, self.label, *(f"{v:.6f}" for v in self.point)] + given

    @classmethod
    def of_row(cls, row: dict) -> "CorrespondedLandmark":
        """The record of a row of landmarks.csv (as :func:`~.prepare.io.read_csv` gives it)."""
        given = None
        if row.get("given_x"):
            given = np.array([float(row[f"given_{c}"]) for c in "xyz"])
        return cls(row["case"], row["label"], np.array([float(row[c]) for c in "xyz"]), given)


def write_landmarks(path, records) -> None:
    """landmarks.csv (:data:`LANDMARK_COLUMNS`) of :class:`CorrespondedLandmark` records."""
    io.write_csv(path, LANDMARK_COLUMNS, [record.row() for record in records])


def read_landmarks(path) -> list:
    """The :class:`CorrespondedLandmark` records of a landmarks.csv (none when it is absent)."""
    path = Path(path)
    return [CorrespondedLandmark.of_row(row) for row in io.read_csv(path)] if path.is_file() else []


def physical_shapes(raw, mirrored) -> list:
    """Corresponded shapes in the physical space of their inputs, so that they overlay them:
    ``raw`` (samples of the prepared surfaces, a mirrored case's reflected) with those of the
    mirrored cases (``mirrored``: a flag per shape) reflected back. The reflection is its own
    inverse, so the same turns physical shapes into the model's frame."""
    return [mirror_points(points) if flip else points for points, flip in zip(raw, mirrored)]


# -- the checkpoint -----------------------------------------------------------------------------

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
    """The state's correspondence (:func:`~.correspondence.state.state_record`: every part's
    positions and accepted warps, or carried positions, every pose, the area weights) and, for
    resuming, the point reached, the generator's state, the trace and the fingerprint: data only
    (numbers, strings, JSON; no pickle), written whole or not at all."""
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
    """The :class:`Checkpoint` of a build's checkpoint file; :class:`~.errors.BuildError` when
    it is not one that can be resumed from."""
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


def _digest(fingerprint: dict) -> str:
    """A short stand-in of a build's fingerprint (its settings and every case's file digests)."""
    return hashlib.sha256(json.dumps(fingerprint, sort_keys=True).encode()).hexdigest()


# -- the build folder ---------------------------------------------------------------------------

@dataclass
class BuildShapes:
    """A build's model and its cases' corresponded points in the model's frame (unaligned)."""

    model: ShapeModel
    shapes: np.ndarray        # (n_s, n_p, 3), in the model's order
    folder: Path


class BuildFolder:
    """A build's output folder: its files by name, read and written.

    ``path`` is the folder, or a model file in it (or anywhere: a model written by itself, whose
    folder then holds no other file of a build).

    Examples
    --------
    >>> import tempfile
    >>> folder = BuildFolder(tempfile.mkdtemp())
    >>> folder.earlier_build(), folder.metrics(), folder.rejected()
    ([], None, [])
    """

    def __init__(self, path):
        path = Path(path)
        # a model file named (or one that is not there, named as model files are)
        self.named_model = path.is_file() or (not path.exists()
                                              and path.suffix == Path(MODEL).suffix)
        if self.named_model:
            self.path, self.model_file = path.parent, path
        else:
            self.path, self.model_file = path, path / MODEL
        # the model file is the one a build writes into its folder (one of another name is a
        # model alone)
        self.is_build_model = self.model_file == self.path / MODEL
        # the files that other rooms open or link to by path
        self.report_file = self.path / REPORT
        self.log_file = self.path / LOG
        self.rejected_file = self.path / REJECTED
        self.checkpoint_file = self.path / CHECKPOINT
        self.baselines_file = self.path / BASELINES
        self.convergence_file = self.path / CONVERGENCE
        self.surfaces_file = self.path / SURFACES

    def __repr__(self) -> str:
        return f"BuildFolder({str(self.path)!r})"

    def case_mesh(self, part: str, name: str, aligned: bool = False) -> Path:
        """The file of a case's corresponded mesh of one part (``part`` '' for a one-part
        model), in its input's space (``correspondence/``) or the model's frame (``aligned/``)."""
        return io.case_file(self.path / (ALIGNED if aligned else CORRESPONDENCE) / part, name)

    # -- reading ---------------------------------------------------------------------------

    def is_build(self) -> bool:
        """Whether the folder holds a build (its model and its settings): its meshes and tables
        are no inputs."""
        return self.model_file.is_file() and (self.path / CONFIG).is_file()

    def model(self) -> ShapeModel:
        """The model; :class:`~.errors.InputError` naming the folder or file when there is
        none."""
        if not self.named_model:
            if not self.path.exists():
                raise InputError(f"{self.path}: no such model file or build folder")
            if not self.model_file.is_file():
                raise InputError(f"{self.path}: not a build folder (no {MODEL})")
        return ShapeModel.load(self.model_file)

    def cases(self) -> list:
        """The rows of cases.csv (dicts of strings); :class:`~.errors.InputError` when the build
        did not finish (there is none)."""
        path = self.path / CASES
        if not path.is_file():
            raise InputError(f"{self.path}: not a finished build (no {CASES})")
        return io.read_csv(path)

    def shapes(self, model: ShapeModel | None = None) -> BuildShapes:
        """The model and every case's corresponded points in the model's frame: the meshes of
        correspondence/ (the inputs' space), a mirrored case's reflected again so that all are of
        one side. :class:`~.errors.InputError` naming what is missing or does not fit."""
        model = model or self.model()
        mirrored = {row["case"]: row.get("mirrored") == "True" for row in self.cases()}
        shapes = []
        for name in model.names:
            points = []
            for part in model.part_meshes():
                path = self.case_mesh(part.name, name)
                if not path.is_file():
                    raise InputError(f"{self.path}: no corresponded shape of case {name!r} "
                                     f"({path})")
                points.append(mesh_points(path))
            shape = np.concatenate(points)
            if shape.shape != model.mean.shape:
                raise InputError(f"{path}: {len(shape)} points; the model has "
                                 f"{len(model.mean)}")
            shapes.append(shape)
        flips = [mirrored.get(name, False) for name in model.names]
        return BuildShapes(model, np.stack(physical_shapes(shapes, flips)), self.path)

    def metrics(self) -> dict | None:
        """metrics.json (None when the folder has none)."""
        path = self.path / METRICS
        return json.loads(path.read_text()) if path.is_file() else None

    def measures(self) -> dict | None:
        """metrics.json's measures per number of modes as columns: ``mode``, then of each of
        :data:`MODE_MEASURES` its title and ``TITLE SE`` (None when there is no metrics.json)."""
        metrics = self.metrics()
        if metrics is None:
            return None
        modes = metrics.get("modes") or list(range(1, len(metrics.get("compactness", [])) + 1))
        columns = {"mode": [float(m) for m in modes]}
        for key, title in MODE_MEASURES.items():
            if key in metrics:
                columns[title] = [float(v) for v in metrics[key]]
                columns[f"{title} SE"] = [float(v) for v in metrics.get(f"{key}_se",
                                                                        metrics[key])]
        return columns

    def scores(self) -> tuple[list, np.ndarray] | None:
        """The case names and scores (n, n_modes) of scores.csv (None when there is none)."""
        path = self.path / SCORES
        rows = io.read_csv(path) if path.is_file() else []
        if not rows:
            return None
        modes = [key for key in rows[0] if key != "case"]
        return ([row["case"] for row in rows],
                np.array([[float(row[key]) for key in modes] for row in rows]).reshape(
                    len(rows), len(modes)))

    def landmarks(self) -> list:
        """The :class:`CorrespondedLandmark` records of landmarks.csv (none for a build without
        landmarks)."""
        return read_landmarks(self.path / LANDMARKS)

    def rejected(self) -> list:
        """The inputs the build rejected (:class:`~.prepare.case.Rejection`)."""
        return read_rejected(self.rejected_file)

    def settings(self) -> dict:
        """config.json: every setting of the build ({} when there is none)."""
        path = self.path / CONFIG
        return json.loads(path.read_text()) if path.is_file() else {}

    def convergence(self) -> list:
        """The rows of convergence.csv (dicts of strings; none when there is none)."""
        return io.read_csv(self.convergence_file) if self.convergence_file.is_file() else []

    def checkpoint(self) -> Checkpoint | None:
        """The checkpoint to resume from (None when there is none; :class:`~.errors.BuildError`
        when the file is not one)."""
        return read_checkpoint(self.checkpoint_file) if self.checkpoint_file.exists() else None

    def baselines(self, fingerprint: dict) -> dict:
        """The baselines' evaluations that :meth:`write_baselines` kept for a build of
        ``fingerprint`` (its inputs and settings): baseline name -> the evaluation as
        :func:`~.model.evaluation.evaluate` gave it, its ``jackknife`` included. Empty when there
        is no such file, or when it is of other inputs or settings or not whole (they are then
        evaluated again)."""
        try:
            kept = json.loads(self.baselines_file.read_text())
            if kept["fingerprint"] != _digest(fingerprint):
                return {}
            evaluations = kept["baselines"]
            for values in evaluations.values():
                if "jackknife" in values:
                    values["jackknife"] = GeneralizationJackknife(
                        np.array(values["jackknife"]["per_case"], dtype=np.float64),
                        np.array(values["jackknife"]["left_out"], dtype=np.float64))
            return evaluations
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            return {}

    def unfinished(self) -> bool:
        """Whether the folder holds a build that ``resume`` carries on: a checkpoint of an
        optimisation that had not ended (cancelled, killed, out of time), or of one that had
        ended but whose outputs were not all written (no cases.csv)."""
        checkpoint = self.checkpoint()
        return checkpoint is not None and (checkpoint.point.phase != PhasePoint.DONE
                                           or not (self.path / CASES).is_file())

    def previous_build(self) -> list:
        """The files and (non-empty) folders of an earlier build, in :data:`BUILD_FILES` order;
        empty when there is none."""
        found = []
        for name in BUILD_FILES:
            path = self.path / name
            if path.is_file() or (path.is_dir() and any(path.iterdir())):
                found.append(path)
        return found

    def earlier_build(self) -> list:
        """The files of a finished or resumable build (:data:`KEPT_BUILD_FILES`); empty when
        there is none, also when a failed start left other files there."""
        return [self.path / name for name in KEPT_BUILD_FILES if (self.path / name).is_file()]

    def existing(self) -> list:
        """The files of :data:`BUILD_FILES` there are, as links of the report: names, a folder's
        with a slash."""
        return [name + "/" if (self.path / name).is_dir() else name for name in BUILD_FILES
                if (self.path / name).exists()]

    # -- writing ---------------------------------------------------------------------------

    def clear(self) -> None:
        """Remove an earlier build's files and folders (and nothing else)."""
        for path in self.previous_build():
            if path.is_dir():
                shutil.rmtree(path)
            else:
                path.unlink()
        self.remove_partial_files()

    def remove_partial_files(self) -> None:
        """Remove the temporary files of writes that a killed build left unfinished
        (:func:`~.prepare.io.written_whole`; they never hold a final name)."""
        for name in BUILD_FILES:
            folder = self.path / name
            if folder.is_dir():
                for path in folder.rglob(f".*{io.PARTIAL}*"):   # parts have folders of their own
                    path.unlink(missing_ok=True)
        for path in self.path.glob(f".*{io.PARTIAL}*"):
            path.unlink(missing_ok=True)

    def write_settings(self, config: BuildConfig) -> None:
        io.write_text(self.path / CONFIG, json.dumps(config.to_dict(), indent=2))

    def write_rejected(self, rejected) -> None:
        write_rejected(self.rejected_file, rejected)

    def write_convergence(self, trace: Trace) -> None:
        io.write_csv(self.convergence_file, Trace.HEADER, trace.rows)

    def save_checkpoint(self, state: CorrespondenceState, point: PhasePoint | None = None,
                        rng=None, trace=None, fingerprint: dict | None = None) -> None:
        """:func:`save_checkpoint` into the folder's checkpoint file."""
        save_checkpoint(self.checkpoint_file, state, point, rng, trace, fingerprint)

    def write_baselines(self, evaluations: dict, fingerprint: dict) -> None:
        """Keep the baselines' evaluations (name -> :func:`~.model.evaluation.evaluate`'s dict,
        with its ``jackknife``) of a build of ``fingerprint``, so that a ``--resume``d build
        takes them (:meth:`baselines`) instead of evaluating them again: JSON, whose numbers
        read back bit for bit."""
        kept = {}
        for name, values in evaluations.items():
            kept[name] = {key: value for key, value in values.items() if key != "jackknife"}
            if "jackknife" in values:       # (none with fewer than four cases)
                kept[name]["jackknife"] = {"per_case": values["jackknife"].per_case.tolist(),
                                           "left_out": values["jackknife"].left_out.tolist()}
        io.write_text(self.baselines_file, json.dumps({"fingerprint": _digest(fingerprint),
                                                       "baselines": kept}))

    def write_model(self, model: ShapeModel, normals=None) -> None:
        """The model file and the mean mesh (with the normals' agreement per point, a
        :class:`~.model.normals.NormalAgreement`, when given; each triangle's part for a model
        of several)."""
        model.save(self.model_file)
        io.write_polydata(self.path / MEAN, model.mean, model.triangles,
                          point_data=None if normals is None else {
                              "normal_spread_degrees": normals.spread_degrees,
                              "normal_agreement": normals.resultant},
                          cell_data=({"part": model.part_of_triangles()} if model.part_names
                                     else None))

    def write_case_meshes(self, model: ShapeModel, names, physical, aligned) -> None:
        """Every case's corresponded mesh per part, in its input's space (``physical``) and in
        the model's frame (``aligned``)."""
        parts = model.part_meshes()
        write_meshes(self.path / CORRESPONDENCE, parts, names, physical)
        write_meshes(self.path / ALIGNED, parts, names, aligned)

    def write_scores(self, names, scores) -> None:
        write_scores(self.path / SCORES, names, scores)

    def write_cases(self, rows: list) -> None:
        """cases.csv: a row per case (dicts of the same keys, the columns)."""
        io.write_csv(self.path / CASES, list(rows[0].keys()),
                     [[row.get(key, "") for key in rows[0]] for row in rows])

    def write_landmarks(self, records) -> None:
        """landmarks.csv, when there are records (a build guided by landmarks)."""
        if records:
            write_landmarks(self.path / LANDMARKS, records)

    def write_metrics(self, metrics: dict) -> None:
        io.write_text(self.path / METRICS, json.dumps(metrics, indent=2))


def write_meshes(folder: Path, parts, names, shapes) -> None:
    """Each shape's mesh per part (a :class:`~.model.shape_model.PartMesh`) into
    ``folder/<part>/<case>.vtp`` (a one-part model's part is '': no sub-folder)."""
    for part in parts:
        (folder / part.name).mkdir(parents=True, exist_ok=True)
    for name, shape in zip(names, shapes):
        for part in parts:
            io.write_polydata(io.case_file(folder / part.name, name), shape[part.rows],
                              part.triangles)


def mesh_points(path) -> np.ndarray:
    """The points of a corresponded mesh file (n, 3): a surface's (its polygons checked to be
    triangles) or a curve's."""
    from vtk.util.numpy_support import vtk_to_numpy

    from .prepare.surface import polydata_to_arrays

    polydata = io.read_polydata(path)
    if polydata.GetNumberOfPolys():
        return polydata_to_arrays(polydata)[0]
    return vtk_to_numpy(polydata.GetPoints().GetData()).astype(np.float64)


def find_inputs(paths) -> list:
    """:func:`~.prepare.io.find_inputs`, a build's output folder refused: its meshes and tables
    are not inputs (:class:`~.errors.InputError`)."""
    for path in map(Path, paths):
        if path.is_dir() and BuildFolder(path).is_build():
            raise InputError(f"{path}: a build's output folder (it holds {MODEL}), not a "
                             "folder of inputs")
    return io.find_inputs(paths)


# -- the fit folder -----------------------------------------------------------------------------

class FitFolder:
    """The output folder of ``mdlshapemodel fit`` (:data:`FIT_FILES`): each fitted case's
    corresponded points and reconstruction, scores.csv, landmarks.csv and rejected.csv as a
    build's, and fit.json."""

    def __init__(self, path):
        self.path = Path(path)

    def earlier_fit(self) -> list:
        """The entries of an earlier fit there are."""
        return io.earlier_outputs(self.path, FIT_FILES)

    def write_meshes(self, parts, names, corresponded, reconstructed) -> None:
        """Each case's corresponded points and their reconstruction by the model, per part."""
        write_meshes(self.path / CORRESPONDENCE, parts, names, corresponded)
        write_meshes(self.path / RECONSTRUCTION, parts, names, reconstructed)

    def write_tables(self, names, scores, rejected, landmarks, summary: dict) -> None:
        """scores.csv, rejected.csv, landmarks.csv (when there are landmarks) and fit.json
        (``summary``)."""
        write_scores(self.path / SCORES, names, scores)
        write_rejected(self.path / REJECTED, rejected)
        if landmarks:
            write_landmarks(self.path / LANDMARKS, landmarks)
        io.write_text(self.path / FIT_SUMMARY, json.dumps(summary, indent=2))

    @property
    def summary_file(self) -> Path:
        return self.path / FIT_SUMMARY

    def case_mesh(self, part: str, name: str, reconstruction: bool = False) -> Path:
        """The file of a fitted case's corresponded points of one part (``part`` '' for a
        one-part model), or of their reconstruction by the model."""
        return io.case_file(self.path / (RECONSTRUCTION if reconstruction else CORRESPONDENCE)
                            / part, name)

    def summary(self) -> dict:
        """fit.json: each fitted case's errors, scores' distance and objective, by name."""
        return json.loads(self.summary_file.read_text())
