"""build_model(): files -> surfaces -> sphere maps -> optimised correspondence -> model -> outputs.

Per-case preprocessing runs in a process pool (``workers``). A case that cannot be used is
*rejected* with a one-line reason (logged, and listed in ``rejected.csv``) and the build goes on.
The optimisation state is checkpointed after every sweep, and an interrupted optimisation
(Ctrl-C, a cancelling progress callback, or the time limit) still writes a model of the state
reached.
"""

from __future__ import annotations

import contextlib
import fnmatch
import hashlib
import json
import logging
import multiprocessing
import os
import time
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from . import io, surface
from .config import BuildConfig
from .correspond import CorrespondenceState, Example, FixedExample, PartState
from .errors import InputError, MDLShapeModelError
from .evaluation import evaluate
from .surface import point_surface_distances
from .mdl import Objective
from .model import ShapeModel
from .sampling import sphere_grid
from .sphere import SphereMap, align_parameterizations, sphere_map
from .strategies import Cancelled, OptimisationSettings, Trace, optimise

log = logging.getLogger("mdlshapemodel")


class BuildError(MDLShapeModelError):
    """No model can be built (e.g. fewer than 3 usable cases)."""


@dataclass
class PreparedCase:
    """One input after preprocessing: its surface and bijective sphere map."""

    name: str
    path: str
    map: SphereMap
    voxel_size: float
    notes: dict = field(default_factory=dict)


@dataclass
class Rejection:
    name: str
    path: str
    reason: str


def mask_components(mask: np.ndarray, min_fraction: float = 0.1) -> tuple[np.ndarray, str]:
    """Fill cavities and keep the largest 26-connected component.

    Raises :class:`SurfaceError` when another component has at least ``min_fraction`` of the
    largest one's voxels (two objects, not one object with debris). Returns the mask and a note.
    """
    from .errors import SurfaceError

    labels, count = ndimage.label(mask, structure=np.ones((3, 3, 3)))
    notes = []
    if count > 1:
        sizes = np.bincount(labels.ravel())[1:]
        order = np.argsort(sizes)[::-1]
        if sizes[order[1]] >= min_fraction * sizes[order[0]]:
            raise SurfaceError(f"{count} disjoint objects in the mask (voxels: "
                               f"{', '.join(str(int(s)) for s in sizes[order[:4]])}); expected one")
        mask = labels == order[0] + 1
        notes.append(f"dropped {count - 1} small component(s) of {int(sizes[order[1:]].sum())} voxels")
    filled = ndimage.binary_fill_holes(mask)
    cavities = int(filled.sum() - mask.sum())
    if cavities:
        notes.append(f"filled {cavities} cavity voxels")
    return filled, "; ".join(notes)


def prepare_case(path: str, config: BuildConfig) -> PreparedCase | Rejection:
    """Read one input, make its closed genus-0 surface and its bijective sphere map."""
    from threadpoolctl import threadpool_limits

    name = io.case_name(path)
    try:
        with threadpool_limits(limits=1, user_api="blas"):
            return _prepare(path, name, config)
    except MDLShapeModelError as error:
        return Rejection(name, str(path), str(error))
    except (ValueError, RuntimeError, MemoryError, OSError) as error:
        return Rejection(name, str(path), f"{type(error).__name__}: {error}")


def _prepare(path, name: str, config: BuildConfig) -> PreparedCase:
    if True:
        notes = {}
        if io.is_image(path):
            label_map = io.read_label_map(path, config.labels)
            mask, note = mask_components(label_map.mask)
            if note:
                notes["repair"] = note
            vertices, faces, info = surface.mask_to_surface(
                mask, label_map.spacing, label_map.origin, label_map.direction,
                smoothing_sigma=config.smoothing_sigma,
                max_smoothing_sigma=config.max_smoothing_sigma, edge_length=config.edge_length,
                target_vertices=config.target_vertices, method=config.surface_method,
                smoothing_factor=config.smoothing_factor, decimation=config.decimation)
            notes.update(info)
            voxel_size = label_map.voxel_size
        elif io.is_mesh(path):
            vertices, faces = io.read_mesh(path)
            vertices, faces, voxel_size, note = clean_mesh(vertices, faces, config)
            if note:
                notes["repair"] = note
        else:
            raise InputError("not a label map or mesh (unknown file type)")
        if is_mirrored(path, config):
            vertices, faces = mirror(vertices, faces)
            notes["mirrored"] = True
        mapped = sphere_map(vertices, faces)
        return PreparedCase(name, str(path), mapped, float(voxel_size), notes)


CACHE_FORMAT = 1
# Version of the preprocessing algorithm (surface extraction and sphere map): raise it whenever a
# change alters the surfaces or maps, so that entries made by the old algorithm are not reused.
# 2: compiled distortion minimisation and our own Moebius balancing (maps differ in rounding).
# 3: a deterministic isotropic remesher (gpytoolbox's) and one BLAS thread while preparing.
PREPROCESSING_VERSION = 3
PREPROCESSING_FIELDS = ("labels", "voxel_size", "surface_method", "smoothing_factor", "decimation",
                        "smoothing_sigma", "max_smoothing_sigma", "edge_length",
                        "target_vertices")


def default_cache_dir() -> Path:
    """``$MDLSHAPEMODEL_CACHE``, else ``$XDG_CACHE_HOME/mdlshapemodel``, else ``~/.cache/...``."""
    if os.environ.get("MDLSHAPEMODEL_CACHE"):
        return Path(os.environ["MDLSHAPEMODEL_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "mdlshapemodel"


def cache_key(path: str, config: BuildConfig) -> str:
    """Hash of the file's bytes, the preprocessing settings, algorithm and package versions."""
    from . import __version__

    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    settings = {name: getattr(config, name) for name in PREPROCESSING_FIELDS}
    settings["mirrored"] = is_mirrored(path, config)
    digest.update(json.dumps([CACHE_FORMAT, PREPROCESSING_VERSION, __version__, settings],
                             sort_keys=True).encode())
    return digest.hexdigest()


def _load_cached(file: Path, name: str, path: str):
    with np.load(file, allow_pickle=False) as data:
        if "reason" in data:
            return Rejection(name, path, str(data["reason"]))
        quality = json.loads(str(data["quality"]))
        notes = json.loads(str(data["notes"]))
        mapped = SphereMap(data["vertices"], data["faces"], data["sphere"], quality)
        return PreparedCase(name, path, mapped, float(data["voxel_size"]), notes)


def _store_cached(file: Path, result):
    file.parent.mkdir(parents=True, exist_ok=True)
    temporary = file.with_name(file.name + f".{os.getpid()}.tmp.npz")
    if isinstance(result, Rejection):
        np.savez(temporary, reason=np.array(result.reason))
    else:
        np.savez(temporary, vertices=result.map.vertices, faces=result.map.faces,
                 sphere=result.map.sphere, quality=np.array(json.dumps(result.map.quality)),
                 notes=np.array(json.dumps(result.notes)), voxel_size=result.voxel_size)
    temporary.replace(file)


def prepare_case_cached(path: str, config: BuildConfig, cache_dir: str | None):
    """:func:`prepare_case`, reusing the stored result of an identical file and settings.

    Returns (result, whether it came from the cache). Unreadable cache entries are recomputed.
    """
    if cache_dir is None or not Path(path).is_file():
        return prepare_case(path, config), False
    name = io.case_name(path)
    file = Path(cache_dir) / f"{cache_key(path, config)}.npz"
    if file.exists():
        try:
            return _load_cached(file, name, str(path)), True
        except (OSError, ValueError, KeyError):
            pass
    result = prepare_case(path, config)
    try:
        _store_cached(file, result)
    except OSError as error:
        log.warning("could not write the preprocessing cache %s: %s", file, error)
    return result, False


def is_mirrored(path, config: BuildConfig) -> bool:
    """Whether the file name matches one of the ``mirror`` patterns (shell-style, e.g. ``*_r*``)."""
    name = Path(path).name
    return any(fnmatch.fnmatch(name, pattern) for pattern in config.mirror)


def mirror(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reflect x -> -x (left <-> right in RAS/LPS) keeping the normals outwards."""
    mirrored = vertices.copy()
    mirrored[:, 0] *= -1.0
    return mirrored, faces[:, [0, 2, 1]].copy()


def clean_mesh(vertices: np.ndarray, faces: np.ndarray, config: BuildConfig):
    """Merge duplicate points, drop degenerate faces, make the orientation consistent, check the
    topology, decimate and remesh; returns vertices, faces, voxel size and a repair note."""
    if not np.all(np.isfinite(vertices)):
        raise surface.SurfaceError("the mesh has non-finite (NaN or infinite) coordinates")
    vertices, faces = surface.merge_close_vertices(vertices, faces)
    vertices, faces = surface.drop_degenerate_faces(vertices, faces)
    topo = surface.topology(vertices, faces)
    note = ""
    if topo.is_closed_manifold and topo.n_components == 1 and not topo.consistently_oriented:
        faces, flipped = surface.make_orientation_consistent(vertices, faces)
        note = f"made the orientation of {flipped} faces consistent"
    surface.require_sphere_like(vertices, faces)
    faces = surface.orient_outwards(vertices, faces)
    if len(vertices) > config.target_vertices:
        vertices, faces = surface.decimate(vertices, faces, config.target_vertices)
    edges = surface.edges_of(faces)
    mean_edge = float(np.mean(np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)))
    vertices, faces = surface.remesh(vertices, faces, mean_edge)
    surface.require_sphere_like(vertices, faces)
    return vertices, faces, config.voxel_size or mean_edge, note


BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


@contextlib.contextmanager
def _one_blas_thread_per_worker():
    """Worker processes started inside use one BLAS thread each (unless the user set one): with
    a process per core, threaded BLAS in every worker oversubscribes the cores."""
    added = [name for name in BLAS_THREAD_VARIABLES if name not in os.environ]
    for name in added:
        os.environ[name] = "1"
    try:
        yield
    finally:
        for name in added:
            os.environ.pop(name, None)


@contextlib.contextmanager
def helper_pool(workers: int):
    """One spawn worker process for work that overlaps the main process's (evaluating baselines
    during the optimisation, which uses one core); None when ``workers`` <= 1."""
    if workers <= 1:
        yield None
        return
    with _one_blas_thread_per_worker(), ProcessPoolExecutor(
            max_workers=1, mp_context=multiprocessing.get_context("spawn")) as pool:
        yield pool


def map_cases(function, arguments: list, workers: int, progress=None, message: str = "cases"
              ) -> list:
    """``[function(*a) for a in arguments]``, in a spawn process pool when ``workers`` > 1 (results in
    input order), reporting progress after each."""
    results = []
    if workers > 1 and len(arguments) > 1:
        context = multiprocessing.get_context("spawn")
        with _one_blas_thread_per_worker(), ProcessPoolExecutor(
                max_workers=min(workers, len(arguments)), mp_context=context) as pool:
            futures = [pool.submit(function, *a) for a in arguments]
            for k, future in enumerate(futures):
                results.append(future.result())
                _report(progress, (k + 1) / len(arguments), f"{message} {k + 1}/{len(arguments)}")
    else:
        for k, a in enumerate(arguments):
            results.append(function(*a))
            _report(progress, (k + 1) / len(arguments), f"{message} {k + 1}/{len(arguments)}")
    return results


def preprocess(paths, config: BuildConfig, progress=None) -> tuple[list, list]:
    """Prepare every case (in parallel, reusing cached results); (prepared, rejected) in input
    order."""
    paths = [str(p) for p in paths]
    cache_dir = None if config.cache_dir == "" else (config.cache_dir or str(default_cache_dir()))
    results = map_cases(prepare_case_cached, [(p, config, cache_dir) for p in paths],
                        config.workers, progress, "prepared")
    reused = sum(hit for _, hit in results)
    if reused:
        log.info("reused %d of %d preprocessed cases from the cache %s", reused, len(paths),
                 cache_dir)
    prepared = [r for r, _ in results if isinstance(r, PreparedCase)]
    rejected = [r for r, _ in results if isinstance(r, Rejection)]
    return prepared, rejected


def _report(progress, fraction, message):
    if progress is not None:
        progress(fraction, message)


def surface_distances(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray,
                      triangles: np.ndarray) -> np.ndarray:
    """Distance from each input-surface vertex to the corresponded mesh (points, triangles)."""
    return point_surface_distances(vertices, points, triangles)


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


def build_model(inputs, output, config: BuildConfig | None = None, progress=None) -> BuildResult:
    """Build an optimised statistical shape model from label maps or meshes.

    Parameters
    ----------
    inputs : list of paths
        Label-map or mesh files, or folders of them.
    output : path
        Output folder (created); see the README for its layout.
    config : BuildConfig
    progress : callable(fraction or None, message), optional
        May raise :class:`Cancelled` to stop the optimisation early; the model of the state
        reached is still written.
    """
    config = (config or BuildConfig()).validate()
    output = Path(output)
    (output / "correspondence").mkdir(parents=True, exist_ok=True)
    (output / "aligned").mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(output / "build.log", mode="w")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    log.addHandler(handler)
    if log.level == logging.NOTSET or log.level > logging.INFO:
        log.setLevel(logging.INFO)
    try:
        return _build(inputs, output, config, progress)
    finally:
        log.removeHandler(handler)
        handler.close()


def _build(inputs, output: Path, config: BuildConfig, progress) -> BuildResult:
    started = time.perf_counter()
    (output / "config.json").write_text(json.dumps(config.to_dict(), indent=2))
    paths = io.find_inputs(inputs)
    if not paths:
        raise BuildError("no input files found (label maps: .nii/.nii.gz/.nrrd/.mha...; meshes: "
                         ".vtk/.vtp/.stl/.ply/.obj)")
    log.info("preprocessing %d inputs with %d workers", len(paths), config.workers)
    prepared, rejected = preprocess(paths, config, progress)
    names = [case.name for case in prepared]
    duplicates = {n for n in names if names.count(n) > 1}
    if duplicates:
        raise BuildError(f"several inputs have the same case name: {', '.join(sorted(duplicates))}")
    for rejection in rejected:
        log.warning("rejected %s: %s", rejection.path, rejection.reason)
    io.write_csv(output / "rejected.csv", ("case", "file", "reason"),
                 [(r.name, r.path, r.reason) for r in rejected])
    if rejected and config.strict:
        raise BuildError(f"{len(rejected)} input(s) rejected and --strict is set")
    if len(prepared) < 3:
        raise BuildError(f"only {len(prepared)} usable case(s); at least 3 are needed")
    log.info("prepared %d cases in %.1f s", len(prepared), time.perf_counter() - started)

    state, (fixed, integrated), voxel, data_range = initial_state(prepared, config)
    initial = integrated(state.covariance())
    log.info("initial objective %.4f (n_s=%d, n_p=%d, voxel %.3f mm, range %.2f mm)", initial,
             state.n_shapes, state.n_points, voxel, data_range)

    with helper_pool(config.workers) as pool:
        pending = {}   # baseline -> (objective and notes, its evaluation: running or done)
        if "none" in config.baselines and (config.strategy != "none"
                                           or config.correspondence == "cpd"):
            log.info("evaluating the initial (equal-spacing) correspondence as a baseline")
            pending["none"] = ({"objective": initial},
                               evaluate_state(state, config, prepared, pool=pool))
        cpd = None
        if config.correspondence == "cpd" or "cpd" in config.baselines:
            cpd, template = cpd_state(state, prepared, config, progress)
            if config.correspondence != "cpd":
                log.info("evaluating the CPD template correspondence as a baseline")
                pending["cpd"] = ({"objective": integrated(cpd.covariance()),
                                   "template": template},
                                  evaluate_state(cpd, config, prepared, pool=pool))

        trace = Trace()
        interrupted = False
        if config.correspondence == "cpd":
            state = cpd
            state.objective = integrated
            initial = final = state.value()
            trace.record(state, final, "integrated", 0)
            log.info("CPD correspondence (template %s): objective %.4f", template, final)
        else:
            settings = optimisation_settings(config)

            def checkpoint():
                save_checkpoint(output / "checkpoint.npz", state)

            try:
                optimise(state, (fixed, integrated), settings, np.random.default_rng(config.seed),
                         trace, progress, checkpoint)
            except (KeyboardInterrupt, Cancelled):
                interrupted = True
                log.warning("optimisation interrupted: writing the model of the state reached")
            if trace.rows and trace.rows[-1][4] == "restored-initial":
                log.warning("the optimisation did not lower the objective within --max-time "
                            "(%.0f s): keeping the initial correspondence", config.max_time)
            state.rebuild()  # also makes the state consistent after an interruption mid-step
            final = integrated(state.covariance())
            log.info("final objective %.4f after %.1f s, %d evaluations", final,
                     trace.rows[-1][0] if trace.rows else 0.0, state.evaluations)
            checkpoint()
        io.write_csv(output / "convergence.csv", Trace.HEADER, trace.rows)
        baselines = {name: {**notes, **_outcome(evaluation)}
                     for name, (notes, evaluation) in pending.items()}

        result = write_outputs(output, state, prepared, rejected, config, initial, final,
                               voxel, data_range, interrupted, baselines, pool)
    log.info("outputs written to %s in %.1f s total", output, time.perf_counter() - started)
    return result


def _outcome(evaluation):
    """The result of an evaluation that may have run in the helper pool; one interrupted there
    (Ctrl-C reaches the worker too) or lost with it is done again here."""
    if not isinstance(evaluation, Future):
        return evaluation
    try:
        return evaluation.result()
    except BaseException as error:     # noqa: B036 - KeyboardInterrupt from the worker included
        log.warning("a baseline evaluation in the helper process failed (%s); evaluating here",
                    type(error).__name__)
        function, arguments = evaluation.retry
        return function(*arguments)


def initial_state(prepared: list, config: BuildConfig):
    """The initial correspondence of prepared cases and the two objectives.

    The sphere maps are aligned across the population and sampled at ``config.points``; the
    objectives' Delta follow the mean voxel size. Returns (state, (fixed, integrated), voxel size,
    data range of the aligned shapes).
    """
    maps = align_parameterizations([case.map for case in prepared])
    grid_points, grid_triangles = sphere_grid(config.points)
    examples = [Example(case.name, [PartState(m.vertices, m.faces, m.sphere, grid_points,
                                              grid_triangles)])
                for case, m in zip(prepared, maps)]
    state = CorrespondenceState(examples, [(grid_points, grid_triangles)], scaling=config.scaling)
    voxel = float(np.mean([case.voxel_size for case in prepared]))
    data_range = float(np.max(np.ptp(state.aligned_shapes().reshape(-1, 3), axis=0)))
    return state, objectives(config, voxel, data_range), voxel, data_range


def objectives(config: BuildConfig, voxel: float, data_range: float) -> tuple:
    """(fixed-Delta objective eq. 13, full objective eq. 14) with Delta in units of ``voxel``."""
    return (Objective("fixed", data_range, delta=config.fixed_delta * voxel),
            Objective("integrated", data_range, delta_min=config.delta_range[0] * voxel,
                      delta_max=config.delta_range[1] * voxel))


def optimisation_settings(config: BuildConfig) -> OptimisationSettings:
    """The optimiser's settings from the build configuration."""
    return OptimisationSettings(strategy=config.strategy, sigma_g=config.sigma_g,
                                max_amplitude=config.max_amplitude, max_time=config.max_time,
                                fixed_fraction=config.fixed_fraction,
                                tolerance=config.tolerance, max_sweeps=config.max_sweeps,
                                warps=tuple(config.warps))


def evaluate_state(state: CorrespondenceState, config: BuildConfig, prepared: list | None = None,
                   model: ShapeModel | None = None, pool=None, background: bool = True):
    """Compactness, generalization and specificity of the state's aligned shapes (``model``: the
    model of those shapes, when already built). With ``prepared`` (the cases, in the state's
    order) and ``config.surface_samples`` > 0, also measured surface to surface.

    With a ``pool`` (see :func:`helper_pool`): ``background`` runs the whole evaluation there and
    returns its future (the state may change meanwhile: it gets copies); otherwise only a part
    runs there and the result is returned when all is done.
    """
    aligned = state.aligned_shapes()
    if model is None:
        model = ShapeModel.from_shapes(aligned, state.weights)
    surfaces = None
    if prepared is not None and config.surface_samples > 0:
        surfaces = [(state.to_model_frame(i, case.map.vertices), case.map.faces)
                    for i, case in enumerate(prepared)]
    arguments = (aligned, state.weights.copy(), model.variances, config.evaluation_modes,
                 config.specificity_samples, np.random.default_rng(config.seed),
                 state.triangles().copy(), surfaces, config.surface_samples)
    if pool is not None and background:
        future = pool.submit(evaluate, *arguments)
        future.retry = (evaluate, arguments)
        return future
    return evaluate(*arguments, pool=pool)


def cpd_state(state: CorrespondenceState, prepared: list, config: BuildConfig, progress=None
              ) -> tuple[CorrespondenceState, str]:
    """The CPD template correspondence of the same cases (the peer baseline), and its template.

    The template is the case whose initial correspondence is closest to the initial mean (the
    medoid); its points are registered onto every other case's surface by coherent point drift
    and projected onto it (:mod:`mdlshapemodel.registration`).
    """
    from .registration import cpd_correspondence

    aligned = state.aligned_shapes()
    distances = np.einsum("ikd,k->i", (aligned - aligned.mean(axis=0)) ** 2, state.weights)
    template = int(np.argmin(distances))
    points = state.examples[template].raw_points()
    log.info("CPD baseline: registering the template %s onto %d cases",
             state.examples[template].name, len(prepared) - 1)
    others = [i for i in range(len(prepared)) if i != template]
    registered = map_cases(cpd_correspondence,
                           [(points, prepared[i].map.vertices, prepared[i].map.faces)
                            for i in others], config.workers, progress, "CPD registered")
    shapes = {template: points, **dict(zip(others, registered))}
    examples = [FixedExample(case.name, shapes[i]) for i, case in enumerate(prepared)]
    return (CorrespondenceState(examples, state.grids, scaling=config.scaling),
            state.examples[template].name)


def save_checkpoint(path: Path, state: CorrespondenceState):
    """Sample positions on the sphere and poses of every example (enough to rebuild the state)."""
    arrays = {}
    for i, example in enumerate(state.examples):
        for j, part in enumerate(example.parts):
            arrays[f"positions_{i}_{j}"] = part.positions
        arrays[f"pose_{i}"] = np.concatenate([[example.pose.scale], example.pose.rotation.ravel(),
                                              example.pose.translation])
    arrays["names"] = np.array([e.name for e in state.examples])
    temporary = path.with_suffix(".tmp.npz")
    np.savez(temporary, **arrays)
    temporary.replace(path)


def write_outputs(output: Path, state: CorrespondenceState, prepared: list, rejected: list,
                  config: BuildConfig, initial: float, final: float, voxel: float,
                  data_range: float, interrupted: bool, baselines: dict | None = None,
                  pool=None) -> BuildResult:
    """model.h5, mean.vtp, correspondence/, aligned/, scores.csv, metrics.json, report.html."""
    from .report import write_report

    triangles = state.triangles()
    aligned = state.aligned_shapes()
    raw = state.raw_shapes()
    names = [e.name for e in state.examples]
    method = "cpd" if config.correspondence == "cpd" else config.strategy
    model = ShapeModel.from_shapes(aligned, state.weights, names=names, triangles=triangles,
                                   part_sizes=[len(p) for p, _ in state.grids],
                                   objective=final, strategy=method, voxel_size_mm=voxel,
                                   data_range_mm=data_range,
                                   config=json.dumps(config.to_dict()))
    model.parameters = np.concatenate([points for points, _ in state.grids])
    model.save(output / "model.h5")
    io.write_polydata(output / "mean.vtp", model.mean, triangles)
    outlier = score_outliers(model)
    cases = []
    for i, case in enumerate(prepared):
        # correspondence meshes overlay their input: mirrored cases are reflected back
        physical = mirror(raw[i], triangles)[0] if case.notes.get("mirrored") else raw[i]
        io.write_polydata(output / "correspondence" / f"{case.name}.vtp", physical, triangles)
        io.write_polydata(output / "aligned" / f"{case.name}.vtp", aligned[i], triangles)
        distances = surface_distances(case.map.vertices, case.map.faces, raw[i], triangles)
        quality = prepared[i].map.quality
        cases.append({"case": case.name, "file": case.path,
                      "surface_vertices": int(len(case.map.vertices)),
                      "mean_distance_mm": float(distances.mean()),
                      "max_distance_mm": float(distances.max()),
                      "mean_distance_voxels": float(distances.mean() / case.voxel_size),
                      "sphere_flips": quality["flipped_triangles"],
                      "sphere_mean_abs_log_area": quality["mean_abs_log_area_ratio"],
                      "sphere_p95_abs_log_area": quality["p95_abs_log_area_ratio"],
                      "sphere_seconds": quality["seconds"],
                      "kernels": int(sum(len(p.kernels) for p in state.examples[i].parts)),
                      "mahalanobis": float(outlier["distance"][i]),
                      "score_outlier": bool(outlier["outlier"][i]),
                      "smoothing_sigma": case.notes.get("smoothing_sigma", ""),
                      "repair": case.notes.get("repair", ""),
                      "mirrored": bool(case.notes.get("mirrored", False))})
    n_modes = model.n_modes
    io.write_csv(output / "scores.csv", ["case"] + [f"mode_{m + 1}" for m in range(n_modes)],
                 [[name] + [f"{v:.6g}" for v in row] for name, row in zip(names, model.scores)])
    io.write_csv(output / "cases.csv", list(cases[0].keys()),
                 [[c.get(k, "") for k in cases[0]] for c in cases])
    quality = evaluate_state(state, config, prepared, model, pool=pool, background=False)
    metrics = {"objective": {"initial": initial, "final": final,
                             "units": "nats (eq. 14, Delta averaged over delta_range)"},
               "strategy": method, "n_shapes": state.n_shapes, "n_points": state.n_points,
               "n_rejected": len(rejected), "voxel_size_mm": voxel, "data_range_mm": data_range,
               "interrupted": interrupted, "evaluations": state.evaluations,
               "variances": model.variances.tolist(), **quality,
               "score_outliers": {"modes": outlier["modes"], "threshold": outlier["threshold"],
                                  "cases": [n for n, o in zip(names, outlier["outlier"]) if o]},
               "surface_distance_mm": {
                   "mean": float(np.mean([c["mean_distance_mm"] for c in cases])),
                   "max": float(np.max([c["max_distance_mm"] for c in cases]))},
               "baselines": baselines or {}}
    (output / "metrics.json").write_text(json.dumps(metrics, indent=2))
    write_report(output, metrics, cases, rejected, model, aligned, names)
    return BuildResult(output, model, metrics, initial, final, cases, rejected, interrupted)


def score_outliers(model: ShapeModel, explained: float = 0.95, quantile: float = 0.99) -> dict:
    """Mahalanobis distance of each training case over the modes that explain ``explained`` of
    the variance, and whether its square exceeds the ``quantile`` of chi-square with that many
    degrees of freedom."""
    from scipy.stats import chi2

    cumulative = np.cumsum(model.variances) / max(model.variances.sum(), 1e-300)
    modes = int(min(np.searchsorted(cumulative, explained) + 1, model.n_modes))
    squared = np.sum(model.scores[:, :modes] ** 2 / model.variances[:modes], axis=1)
    threshold = float(np.sqrt(chi2.ppf(quantile, modes)))
    distance = np.sqrt(squared)
    return {"modes": modes, "threshold": threshold, "distance": distance,
            "outlier": distance > threshold}
