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

Where a stage ends, what it freed is not needed again and is handed back at once. Inside a loop
whose next pass reuses what this one freed (the optimisation's rounds, after each checkpoint),
the pages handed back are faulted in again, and zeroed, by the next pass: there a release is
asked for with ``at_most_every`` (:data:`LOOP_RELEASE_SECONDS`), so that short passes, whose
refaulting would be a large share of their time, release rarely, and long ones (a large
population's rounds) still bound what the allocator keeps.

Files mapped into memory read-only (:func:`watch_mapping`: a build's prepared surfaces, see
:mod:`~mdlshapemodel.prepare.mapped`) hold as resident the pages that were read. A release hands
those back too (``madvise(MADV_DONTNEED)``); a later read maps them again from the file, or from
the kernel's cache of it, with the same bytes.
"""

from __future__ import annotations

import ctypes
import mmap
import sys
import time
import weakref

__all__ = ["LOOP_RELEASE_SECONDS", "release_freed_memory", "watch_mapping"]

#: the least time between two releases asked for inside a loop (``at_most_every``): a release
#: there costs about as much as faulting in again the pages it hands back, so at most one a
#: minute keeps that a small share of any loop whose passes reuse their memory
LOOP_RELEASE_SECONDS = 60.0


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
_LAST = None         # time.monotonic() of this process's last release
_MAPPINGS = []       # weak references to the read-only file mappings whose pages a release drops


def watch_mapping(mapping: mmap.mmap) -> None:
    """Have every later :func:`release_freed_memory` of this process hand back the pages of
    ``mapping`` (a read-only mapping of a file) that were read, for as long as it is open.

    Examples
    --------
    >>> import mmap, tempfile
    >>> from mdlshapemodel.memory import release_freed_memory, watch_mapping
    >>> with tempfile.TemporaryFile() as file:
    ...     _ = file.write(bytes(8192)); file.flush()
    ...     mapping = mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ)
    ...     watch_mapping(mapping)
    ...     first = mapping[0]             # its first page is now resident
    ...     released = release_freed_memory()
    ...     mapping.close()
    """
    _MAPPINGS[:] = [ref for ref in _MAPPINGS if ref() is not None]
    _MAPPINGS.append(weakref.ref(mapping))


def _drop_mapped_pages() -> bool:
    """Hand back the read pages of the watched mappings; whether there were any to drop."""
    dropped = False
    if not hasattr(mmap, "MADV_DONTNEED"):       # not Linux, BSD or macOS
        return False
    for ref in _MAPPINGS:
        mapping = ref()
        if mapping is not None and not mapping.closed:
            mapping.madvise(mmap.MADV_DONTNEED)
            dropped = True
    return dropped


def release_freed_memory(at_most_every: float | None = None) -> bool:
    """Return the C library's free memory to the operating system (glibc's ``malloc_trim(0)``:
    the free pages of every heap, not only the top), and the read pages of the watched file
    mappings (:func:`watch_mapping`).

    Parameters
    ----------
    at_most_every : float, optional
        Seconds: do nothing if the last release of this process was more recent (for calls
        inside a loop, :data:`LOOP_RELEASE_SECONDS`). None: release now.

    Returns
    -------
    bool
        Whether any memory was returned (False where the C library has no such call and no
        mapping is watched, or the release was skipped).

    Examples
    --------
    >>> from mdlshapemodel.memory import release_freed_memory
    >>> released = release_freed_memory()     # after a stage's large frees
    """
    global _LAST
    now = time.monotonic()
    if at_most_every is not None and _LAST is not None and now - _LAST < at_most_every:
        return False
    _LAST = now
    dropped = _drop_mapped_pages()
    trimmed = _TRIM is not None and bool(_TRIM(0))
    return trimmed or dropped
