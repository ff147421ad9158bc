"""The compiled (numba) kernels on a first run: is numba's cache of them warm, and compiling them
ahead of a build.

The kernels are numba functions compiled on their first call and kept in numba's cache (beside
their modules in ``__pycache__``, or in ``NUMBA_CACHE_DIR``): once per installation, about a
minute of a first build (docs/benchmarks.md, "The demo"). Left to themselves they would compile
silently, in every worker process at once and then in the optimisation, whose time budget they
would spend. :func:`compile_ahead` instead says so in one line and compiles them in the calling
process, before a build starts its worker processes, by a build of three tiny generated label
maps (the code paths of a real build), so that the workers, the optimisation and the evaluation
load them from the cache.

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
                  "model/evaluation_kernels.py")

#: what a build with a cold cache says before it compiles
COMPILING = "compiling numerical kernels (first run only, about a minute)"

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


def compile_ahead(build: Callable) -> bool:
    """Compile the kernels into numba's cache unless it holds them: say so (:data:`COMPILING`,
    an info line), run ``build(inputs, output, config)`` (:func:`~.build.build_model`) on
    :func:`tiny_population` into a temporary folder, silently, then write the marker. Returns
    whether it compiled. Inside that build, and when the cache is warm, it does nothing. An
    error of the tiny build is logged as a warning and the caller's work goes on (its kernels
    then compile where they are first called); an interruption propagates, the marker unwritten.
    """
    global _compiling
    if _compiling or kernels_compiled():
        return False
    log.info("%s", COMPILING)
    _compiling = True
    try:
        with tempfile.TemporaryDirectory(prefix="mdlshapemodel-kernels-") as folder, _silent():
            build(tiny_population(Path(folder) / "inputs"), Path(folder) / "model",
                  BuildConfig(**_TINY_BUILD))
    except Exception as error:  # noqa: BLE001 - the user's build goes on without it
        log.warning("compiling the numerical kernels ahead failed (%s: %s); they compile where "
                    "they are first used", type(error).__name__, error)
        return False
    finally:
        _compiling = False
    marker = marker_path()
    try:
        marker.parent.mkdir(parents=True, exist_ok=True)
        io.write_text(marker, "numba's cache holds mdlshapemodel's compiled kernels for the "
                              "sources, numba, Python and machine that name this file\n")
    except OSError as error:
        log.info("could not write %s (%s): the next run compiles ahead again", marker, error)
    return True
