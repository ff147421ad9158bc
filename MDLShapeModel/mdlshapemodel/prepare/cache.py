"""The preprocessing cache: a prepared case stored under a hash of its file and settings.

A rebuild with other optimisation settings starts at the optimisation. Entries are keyed by the
file's bytes, the preprocessing settings, the versions of the preprocessing algorithm and of the
package; unreadable entries are recomputed; entries are written to a temporary name and renamed,
so a killed build never leaves half an entry.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from ..config import BuildConfig
from ..version import __version__
from . import io
from .case import PreparedCase, PreparedPart, Rejection, is_mirrored, prepare_case
from .sphere import SphereMap

log = logging.getLogger("mdlshapemodel")

# The layout of an entry (the preparation facts as named fields): raise it when what an entry
# stores changes, so that entries of another layout are not read.
CACHE_FORMAT = 2
# Version of the preprocessing algorithm (reading and checking files, surface extraction,
# remeshing, the sphere map): raise it whenever a change alters the surfaces, the maps or the
# verdict on an input, so that entries made by another algorithm are not reused. Both numbers are
# part of every entry's key (:func:`cache_key`).
PREPROCESSING_VERSION = 7
PREPROCESSING_FIELDS = ("labels", "voxel_size", "surface_method", "smoothing_factor", "decimation",
                        "smoothing_sigma", "max_smoothing_sigma", "edge_length",
                        "target_vertices")


def default_cache_dir() -> Path:
    """``$MDLSHAPEMODEL_CACHE``, else ``$XDG_CACHE_HOME/mdlshapemodel``, else ``~/.cache/...``."""
    if os.environ.get("MDLSHAPEMODEL_CACHE"):
        return Path(os.environ["MDLSHAPEMODEL_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "mdlshapemodel"


def cache_dir_of(config: BuildConfig) -> str | None:
    """The cache folder of a build: ``config.cache_dir``, the default place when None, no cache
    when ''."""
    if config.cache_dir == "":
        return None
    return config.cache_dir or str(default_cache_dir())


def cache_key(path: str, config: BuildConfig) -> str:
    """Hash of the file's bytes, the preprocessing settings, algorithm and package versions."""
    digest = hashlib.sha256(io.file_digest(path).encode())
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
        facts = json.loads(str(data["facts"]))
        mapped = SphereMap(data["vertices"], data["faces"], data["sphere"], quality)
        labels = facts.get("labels")          # None: the entry does not say
        part = PreparedPart("", path, mapped, facts["repair"], facts["smoothing_sigma"],
                            None if labels is None else tuple(labels))
        return PreparedCase(name, [part], float(data["voxel_size"]), facts["mirrored"])


def _store_cached(file: Path, result):
    file.parent.mkdir(parents=True, exist_ok=True)
    temporary = file.with_name(file.name + f".{os.getpid()}.tmp.npz")
    if isinstance(result, Rejection):
        np.savez(temporary, reason=np.array(result.reason))
    else:
        np.savez(temporary, vertices=result.map.vertices, faces=result.map.faces,
                 sphere=result.map.sphere, quality=np.array(json.dumps(result.map.quality)),
                 facts=np.array(json.dumps(result.record())), voxel_size=result.voxel_size)
    temporary.replace(file)


def prepare_case_cached(path: str, config: BuildConfig, cache_dir: str | None):
    """:func:`~mdlshapemodel.prepare.case.prepare_case`, reusing the stored result of an identical
    file and settings.

    Returns (result, whether it came from the cache). Unreadable cache entries are recomputed.
    """
    if cache_dir is None or not Path(path).is_file():
        return prepare_case(path, config), False
    name = io.case_name(path)
    file = Path(cache_dir) / f"{cache_key(path, config)}.npz"
    if file.exists():
        try:
            return _load_cached(file, name, str(path)), True
        except (OSError, EOFError, ValueError, KeyError, TypeError, zipfile.BadZipFile,
                zlib.error):
            pass   # a damaged entry, or one holding objects (never unpickled): made anew
    result = prepare_case(path, config)
    if isinstance(result, PreparedCase) and result.is_curve:
        return result, False            # 2-D curves take milliseconds: not stored
    try:
        _store_cached(file, result)
    except OSError as error:
        log.warning("could not write the preprocessing cache %s: %s", file, error)
    return result, False
