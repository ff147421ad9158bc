"""Prepared cases whose surfaces and sphere maps lie in a file mapped into memory, not held in it.

A build keeps its prepared cases from the preprocessing to the outputs, yet from the initial
correspondence to the end of the optimisation nothing reads their surfaces or sphere maps: the
correspondence state holds its own reordered copies. :func:`mapped_cases` writes each part's
vertices, triangles and sphere map into one file and gives back the same cases with read-only
views of the file, mapped. A mapping's pages take memory only once read, and
:func:`~mdlshapemodel.memory.release_freed_memory` hands back those read (the kernel reads them
again from the file, or its cache of it, when they are next touched). The arrays hold the bytes
written: a build gives the same results with the mapped cases as with the arrays held.

A process of the same machine (a build's helper, which evaluates the baselines) reads the meshes it
asks for from the file, one case at a time (:meth:`MeshFile.meshes`), instead of receiving a copy
of them all.
"""

from __future__ import annotations

import logging
import mmap
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import InternalError
from ..memory import watch_mapping
from .sphere import SphereMap

__all__ = ["CasesInFile", "MappedCases", "MeshFile", "StoredArray", "StoredPart",
           "mapped_cases"]

log = logging.getLogger("mdlshapemodel")

#: every array starts at a multiple of this many bytes of the file (aligned for any dtype)
ALIGNMENT = 64


@dataclass(frozen=True)
class StoredArray:
    """Where one array lies in a :class:`MeshFile`: its first byte, dtype and shape."""

    offset: int
    dtype: str
    shape: tuple

    @property
    def count(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))


@dataclass(frozen=True)
class StoredPart:
    """Where one part's sphere map lies in a :class:`MeshFile`."""

    vertices: StoredArray
    faces: StoredArray
    sphere: StoredArray


@dataclass(frozen=True)
class MeshFile:
    """A file of prepared cases' sphere maps: ``parts[i][j]`` is the :class:`StoredPart` of case
    i's part j."""

    path: str
    parts: tuple

    def __len__(self) -> int:
        return len(self.parts)

    def meshes(self, i: int) -> list:
        """Case i's (vertices, triangles) of each part, read from the file: new arrays, no
        mapping kept (what :meth:`~mdlshapemodel.prepare.case.PreparedCase.meshes` gives of the
        mapped case)."""
        with open(self.path, "rb") as file:
            return [(self._read(file, part.vertices), self._read(file, part.faces))
                    for part in self.parts[i]]

    def _read(self, file, stored: StoredArray) -> np.ndarray:
        file.seek(stored.offset)
        array = np.fromfile(file, dtype=stored.dtype, count=stored.count)
        if array.size != stored.count:      # the file is the build's own: never a user's input
            raise InternalError(f"{self.path} ends before the array at byte {stored.offset}")
        return array.reshape(stored.shape)


class MappedCases(list):
    """A list of prepared cases whose sphere maps' arrays are read-only views of ``file``, mapped
    (:func:`mapped_cases`). Slices and copies are plain lists of the same cases."""

    def __init__(self, cases: list, file: MeshFile, mapping: mmap.mmap):
        super().__init__(cases)
        self.file = file
        self._mapping = mapping       # kept open while the list lives (its arrays view it)


def _write(file, array: np.ndarray, offset: int) -> tuple[StoredArray, int]:
    padding = -offset % ALIGNMENT
    file.write(b"\0" * padding)
    offset += padding
    array = np.ascontiguousarray(array)
    array.tofile(file)
    return StoredArray(offset, array.dtype.str, tuple(array.shape)), offset + array.nbytes


def mapped_cases(prepared: list, path) -> list:
    """The prepared cases with their sphere maps' vertices, faces and sphere points held in the
    file ``path`` (written anew, replacing any file there) and mapped read-only.

    Parameters
    ----------
    prepared : list of PreparedCase
        Cases of surfaces (sphere maps); a list with 2-D curves, or an empty one, is returned as
        it is (their maps are small).
    path : str or Path
        The file to write; the caller removes it once the cases are no longer used.

    Returns
    -------
    MappedCases, or ``prepared`` itself
        The same cases in the same order, their maps' arrays read-only views of the mapped file
        (equal to the arrays given, bit for bit). Where the file cannot be written (e.g. the
        disk is full) the log says so and ``prepared`` is returned: the build holds the arrays.

    Examples
    --------
    ::

        from mdlshapemodel.prepare.mapped import mapped_cases
        cases = mapped_cases(prepared, output / "surfaces.tmp")
        cases[0].map.vertices        # read from the file when touched
    """
    if not prepared or any(case.is_curve for case in prepared):
        return prepared
    path = Path(path)
    temporary = path.with_name(path.name + f".{os.getpid()}.part")
    where, offset = [], 0
    try:
        with open(temporary, "wb") as file:
            for case in prepared:
                parts = []
                for part in case.parts:
                    vertices, offset = _write(file, part.map.vertices, offset)
                    faces, offset = _write(file, part.map.faces, offset)
                    sphere, offset = _write(file, part.map.sphere, offset)
                    parts.append(StoredPart(vertices, faces, sphere))
                where.append(tuple(parts))
        temporary.replace(path)
        with open(path, "rb") as file:
            mapping = mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ)
    except OSError as error:
        temporary.unlink(missing_ok=True)
        log.warning("could not write %s (%s): the prepared surfaces stay in memory", path, error)
        return prepared
    watch_mapping(mapping)

    def view(stored: StoredArray) -> np.ndarray:
        return np.frombuffer(mapping, dtype=stored.dtype, count=stored.count,
                             offset=stored.offset).reshape(stored.shape)

    cases = []
    for case, parts in zip(prepared, where):
        mapped = [replace(part, map=SphereMap(view(stored.vertices), view(stored.faces),
                                              view(stored.sphere), part.map.quality))
                  for part, stored in zip(case.parts, parts)]
        cases.append(replace(case, parts=mapped))
    return MappedCases(cases, MeshFile(str(path), tuple(where)), mapping)


class CasesInFile:
    """:func:`mapped_cases` for the length of a ``with`` block, whose end removes the file (the
    mapping stays readable while its arrays are referenced). The list given is not kept: its
    arrays go once the caller's name for it does (a ``with ... as`` of the same name).

    Examples
    --------
    ::

        with CasesInFile(prepared, output / "prepared-surfaces.tmp") as prepared:
            ...                          # the optimisation, the outputs
    """

    def __init__(self, prepared: list, path):
        self.path = Path(path)
        self.cases = mapped_cases(prepared, self.path)

    def __enter__(self) -> list:
        return self.cases

    def __exit__(self, *raised) -> None:
        self.path.unlink(missing_ok=True)
