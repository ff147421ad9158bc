"""The compiled (numba) kernels on a first run: is numba's cache of them warm, and compiling them
ahead of a build.

The kernels are numba functions compiled on their first call and kept in numba's cache (beside
their modules in ``__pycache__``, or in ``NUMBA_CACHE_DIR``): once per installation, about a
minute of a first build (docs/benchmarks.md, "The demo"). Left to themselves they would compile
silently, in every worker process at once and then in the optimisation, whose time budget they
would spend. :func:`compile_ahead` instead says so in one line and compiles them in the calling
process, before a build starts its worker processes, by a build of three tiny generated label
maps (the code paths of a real build), so that the workers, the optimisation and the evaluation
load them from the cache. Two cores share the compilation: this process compiles the sphere
map's kernels first (:func:`compile_sphere_map`) while a second one compiles the remeshing's
(:func:`compile_remeshing`); the tiny build starts once those are in the cache (the remeshing
is its first step) and compiles the optimisation's, while the second process compiles the
evaluation's, the field replay's and the one of ``analyze --tfce`` (:func:`compile_beside`),
which the tiny build then loads.

Whether the cache is warm is read from a marker file written once that compilation has
succeeded, beside numba's cache and named after what numba's cache depends on: the kernels'
source files (path, modification time, size), numba's and Python's versions and the machine. The
check costs a few ``stat`` calls and imports nothing heavy.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import platform
import sys
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

from .config import BuildConfig
from .prepare import io

log = logging.getLogger("mdlshapemodel")

#: the modules of the package that hold numba functions cached on disk (``cache=True``)
KERNEL_MODULES = ("prepare/nearest.py", "prepare/remesh.py", "prepare/sphere_kernels.py",
                  "prepare/multilevel.py", "correspondence/hotloops.py",
                  "model/evaluation_kernels.py", "analysis/tfce.py")

#: what a build with a cold cache says before it compiles
COMPILING = "compiling numerical kernels (first run only, about half a minute of CPU)"

# the tiny build that compiles the kernels: one process, nothing cached but numba's, and the
# smallest settings that still run every stage (a sweep of the optimisation, the evaluation of
# specificity and of the surface distances)
_TINY_BUILD = dict(points=42, workers=1, baselines=[], cache_dir="", max_time=30.0,
                   evaluation_modes=1, specificity_samples=20, surface_samples=10)

_compiling = False   # set while compile_ahead's own build runs (it must not start another)


def _package() -> Path:
    return Path(__file__).resolve().parent


def marker_folder() -> Path:
    """Where the marker is kept: numba's own cache folder when ``NUMBA_CACHE_DIR`` names one,
    else the package's ``__pycache__`` where numba keeps the kernels when it can write there,
    else the user's cache folder (``$XDG_CACHE_HOME`` or ``~/.cache``)/mdlshapemodel."""
    configured = os.environ.get("NUMBA_CACHE_DIR")
    if configured:
        return Path(configured)
    beside = _package() / "__pycache__"
    if os.access(beside if beside.is_dir() else beside.parent, os.W_OK):
        return beside
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "mdlshapemodel"


def marker_path() -> Path:
    """The marker file of the kernels as they are now: its name changes with anything that makes
    numba compile them again (their sources, numba, Python, the machine)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        numba_version = version("numba")
    except PackageNotFoundError:
        numba_version = "unknown"
    facts = [numba_version, sys.version, getattr(sys, "abiflags", ""), platform.machine()]
    for name in KERNEL_MODULES:
        source = _package() / name
        stat = source.stat()
        facts.append(f"{source}:{stat.st_mtime_ns}:{stat.st_size}")
    digest = hashlib.sha256("\n".join(facts).encode()).hexdigest()[:16]
    return marker_folder() / f"mdlshapemodel-kernels-{digest}.txt"


def kernels_compiled() -> bool:
    """Whether numba's cache holds the kernels as they are now (their marker exists)."""
    return marker_path().is_file()


def tiny_population(folder) -> list[Path]:
    """Three small label maps (ellipsoids of different thickness, 1 mm voxels) in ``folder``."""
    import SimpleITK as sitk

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    z, y, x = np.indices((16, 18, 26), dtype=np.float64)
    paths = []
    for k, thickness in enumerate((4.0, 5.0, 6.0)):
        inside = ((x - 12.5) / 10.0) ** 2 + ((y - 8.5) / 6.0) ** 2 + ((z - 7.5) / thickness) ** 2
        image = sitk.GetImageFromArray((inside <= 1.0).astype(np.uint8))
        image.SetSpacing((1.0, 1.0, 1.0))
        path = folder / f"tiny_{k + 1}.nii.gz"
        sitk.WriteImage(image, str(path))
        paths.append(path)
    return paths


@contextlib.contextmanager
def _silent():
    """No log record of the package's logger passes in the block."""
    def drop(record):
        return False

    log.addFilter(drop)
    try:
        yield
    finally:
        log.removeFilter(drop)


def ellipsoid(subdivisions: int, axes) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangle mesh of the ellipsoid of semi-axes ``axes`` (an icosphere scaled):
    vertices (n, 3) float64 and counter-clockwise faces (m, 3) int64."""
    from .correspondence.sampling import icosphere

    vertices, faces = icosphere(subdivisions)
    return (np.ascontiguousarray(vertices * np.asarray(axes, dtype=np.float64)),
            np.ascontiguousarray(faces, dtype=np.int64))


def compile_sphere_map() -> None:
    """Compile the sphere map's kernels (:func:`~.prepare.sphere.sphere_map`: the distortion's
    minimiser, the largest of all, and the area balance) into numba's cache by mapping a small
    generated ellipsoid. :func:`compile_ahead` calls it before its tiny build, while
    :func:`compile_remeshing` runs in a second process."""
    from .prepare.sphere import sphere_map

    sphere_map(*ellipsoid(2, (12.0, 7.0, 5.0)))


def compile_remeshing() -> None:
    """Compile the remeshing's kernels (:func:`~.prepare.surface.remesh`) into numba's cache by
    remeshing a small generated ellipsoid (edges of 0.5-2 mm: splits, collapses, flips).
    :func:`compile_ahead` runs it in a second process while it compiles the sphere map's
    kernels, and starts its tiny build, whose first step is the remeshing, once it is done."""
    from .prepare.surface import remesh

    remesh(*ellipsoid(3, (12.0, 7.0, 5.0)), 1.2)


def compile_beside() -> None:
    """Compile into numba's cache the kernels of the model's evaluation with its surface
    measures (:func:`~.model.evaluation.evaluate`), of a field warp's replay
    (:func:`~.correspondence.fields.apply_field`) and of TFCE (:func:`~.analysis.tfce.enhance`),
    by calling them on small generated ellipsoids: arrays of the types a build and ``analyze``
    pass.

    :func:`compile_ahead` runs it in a second process after :func:`compile_remeshing`, while its
    tiny build compiles the optimisation's kernels: the tiny build reaches the evaluation's
    last (the replay's and TFCE's never), and loads them from the cache when this process has
    compiled them by then."""
    from .analysis.tfce import enhance, surface_of
    from .correspondence.fields import apply_field
    from .model.evaluation import evaluate

    surfaces = [ellipsoid(2, (12.0 + k, 7.0, 5.0 - 0.5 * k)) for k in range(4)]
    shapes = np.stack([ellipsoid(1, (12.0 + k, 7.0, 5.0 - 0.5 * k))[0] for k in range(4)])
    triangles = ellipsoid(1, (1.0, 1.0, 1.0))[1]
    centred = shapes - shapes.mean(axis=0)
    variances = np.linalg.svd(centred.reshape(len(shapes), -1), compute_uv=False) ** 2 / 4
    evaluate(shapes, np.ones(shapes.shape[1]), variances, max_modes=2, n_samples=20,
             triangles=triangles, surfaces=surfaces, surface_samples=10)
    apply_field(1, surfaces[0][0] / 12.0, np.full((42, 3), 1e-3))
    surface = surface_of(*surfaces[0])
    enhance(np.linspace(0.0, 3.0, 2 * surface.n_points).reshape(2, -1), surface)


def _start_beside():
    """:func:`compile_remeshing` then :func:`compile_beside` submitted to a pool of one worker
    process (the pool, their two futures), or None where no process can be started
    (:func:`compile_ahead` then runs them in its own process)."""
    from .parallel import ProcessPool

    pool = ProcessPool(1)
    try:
        return pool, pool.submit(compile_remeshing), pool.submit(compile_beside)
    except Exception as error:  # noqa: BLE001 - the tiny build compiles them instead
        pool.shutdown(wait=False)
        log.info("could not start a second process to compile kernels (%s: %s)",
                 type(error).__name__, error)
        return None


def _wait_for(future, what: str) -> None:
    """Wait for one compilation of :func:`_start_beside`'s process; its error is a warning
    (those kernels compile where they are first used)."""
    try:
        future.result()
    except Exception as error:  # noqa: BLE001 - the user's build goes on without it
        log.warning("compiling %s kernels ahead failed (%s: %s); they compile where they are "
                    "first used", what, type(error).__name__, error)


def _finish_beside(beside, interrupted: bool) -> None:
    """Wait for :func:`_start_beside`'s process (not after an interruption: it then ends with
    this process) and shut its pool down."""
    if beside is None:
        return
    pool, _, rest = beside
    if interrupted:
        pool.shutdown(wait=False, cancel_futures=True)
        return
    try:
        _wait_for(rest, "the evaluation's, field replay's and TFCE's")
    finally:
        pool.shutdown(wait=True)


def compile_ahead(build: Callable, second_process: bool = True) -> bool:
    """Compile the kernels into numba's cache unless it holds them: say so (:data:`COMPILING`,
    an info line), start :func:`compile_remeshing` and then :func:`compile_beside` in a second
    process, :func:`compile_sphere_map` here, wait for the remeshing's, run
    ``build(inputs, output, config)`` (:func:`~.build.build_model`) on :func:`tiny_population`
    into a temporary folder, silently, wait for the second process, then write the marker.
    Returns whether it compiled.
    Inside that build, and when the cache is warm, it does nothing. Without ``second_process``
    (a caller that must start no process: one worker, a script's unguarded top-level code),
    :func:`compile_beside` runs here after the tiny build. An error of the tiny build
    or of the second process is logged as a warning and the caller's work goes on (their kernels
    then compile where they are first called); an interruption propagates, the marker unwritten.
    """
    global _compiling
    if _compiling or kernels_compiled():
        return False
    log.info("%s", COMPILING)
    _compiling = True
    beside, interrupted = (_start_beside() if second_process else None), True
    try:
        with tempfile.TemporaryDirectory(prefix="mdlshapemodel-kernels-") as folder:
            with _silent():
                compile_sphere_map()
            if beside is not None:   # the tiny build's first step: loaded, not compiled again
                _wait_for(beside[1], "the remeshing's")
            with _silent():
                build(tiny_population(Path(folder) / "inputs"), Path(folder) / "model",
                      BuildConfig(**_TINY_BUILD))
                if beside is None:
                    compile_beside()
        interrupted = False
    except Exception as error:  # noqa: BLE001 - the user's build goes on without it
        interrupted = False
        log.warning("compiling the numerical kernels ahead failed (%s: %s); they compile where "
                    "they are first used", type(error).__name__, error)
        return False
    finally:
        _compiling = False
        _finish_beside(beside, interrupted)
    marker = marker_path()
    try:
        marker.parent.mkdir(parents=True, exist_ok=True)
        io.write_text(marker, "numba's cache holds mdlshapemodel's compiled kernels for the "
                              "sources, numba, Python and machine that name this file\n")
    except OSError as error:
        log.info("could not write %s (%s): the next run compiles ahead again", marker, error)
    return True
