"""Freed memory handed back to the operating system at a build's large frees.

The C library's allocator keeps memory that a program frees for its later allocations; with glibc
(Linux), blocks up to tens of MB (NumPy arrays among them, once a larger one has been freed) come
from its heaps, and a free block there stays resident until a block after it is freed too. A
build frees much at a few points, in blocks of a few hundred KB among blocks still in use: the
initial correspondence's temporaries (the aligned sphere maps, the first grid's samples), the
point locators once the correspondence is final (:meth:`~.correspondence.state.
CorrespondenceState.release_sampling`), the evaluations' arrays. Without help, the process's
resident memory grows with those frees as if they were still held. :func:`release_freed_memory`
asks glibc to return the free pages (``malloc_trim``) where the process has glibc; elsewhere
(macOS, Windows, musl) it does nothing. It moves no data: what a build computes is the same.

It is called where a stage ends and what it freed is not needed again, never inside a loop whose
next pass reuses the memory (the optimisation's rounds): pages handed back there are only faulted
in again, and zeroed, by the next round, which costs CPU time and lowers no peak.
"""

from __future__ import annotations

import ctypes
import sys

__all__ = ["release_freed_memory"]


def _malloc_trim():
    """glibc's ``malloc_trim`` of this process, or None where there is none."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        trim = ctypes.CDLL(None).malloc_trim     # the C library the process runs with
    except (OSError, AttributeError):            # no such symbol: not glibc
        return None
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


_TRIM = _malloc_trim()


def release_freed_memory() -> bool:
    """Return the C library's free memory to the operating system (glibc's ``malloc_trim(0)``:
    the free pages of every heap, not only the top); whether any was returned (False where the
    C library has no such call)."""
    return bool(_TRIM(0)) if _TRIM is not None else False
