"""Cases given more than once: found by their files' bytes before anything is prepared, and by
their shapes in the initial correspondence.

A case given twice is not a second observation of the population. Its copy makes the model's
smallest mode one of almost no variance (a Mahalanobis distance divides by it), and every
leave-one-out model holds the left-out case's copy, so generalization looks better than it is.
A build therefore names such cases and stops, unless ``BuildConfig.allow_duplicates``:

- :func:`identical_files`: the cases' files have the same SHA-256 (checked before preparing);
- :func:`same_shapes`: the corresponded shapes of two cases, each moved to its centroid, are
  closer than :data:`~mdlshapemodel.config.DUPLICATE_DISTANCE` of the shape's size (a copy in
  another format, moved, or with a few voxels changed).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import DUPLICATE_DISTANCE
from . import io


@dataclass(frozen=True)
class Duplicates:
    """Cases that are one case given several times: their files (or names, when a case has no
    file) and why they are taken for one."""

    files: tuple       # of str, in input order
    why: str           # "identical files", "the same shape (RMS distance ...)"

    def line(self) -> str:
        """"a.nii.gz and b.nii.gz are identical files"."""
        shown = [io.printable(f) for f in self.files]
        listed = (" and ".join(shown) if len(shown) == 2
                  else ", ".join(shown[:-1]) + " and " + shown[-1])
        return f"{listed} are {self.why}"


def refusal(duplicates: list) -> str:
    """The one-line message of a build refused for ``duplicates`` (:class:`Duplicates`): every
    group named, and how to go on."""
    return ("the same case is given more than once: " + "; ".join(d.line() for d in duplicates)
            + ". A repeated case adds a mode of no variance to the model and leaves its "
              "measures too good: remove all but one of each, or give --allow-duplicates to "
              "model them as they are")


def _groups(pairs, count: int) -> list:
    """The connected groups (sorted index lists, of two or more) of ``pairs`` of 0..count-1."""
    parent = list(range(count))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in pairs:
        parent[root(i)] = root(j)
    members = {}
    for i in range(count):
        members.setdefault(root(i), []).append(i)
    return sorted((m for m in members.values() if len(m) > 1), key=lambda m: m[0])


def identical_files(cases) -> list:
    """The groups of cases (:class:`~.parts.CaseInput`) whose files are byte for byte the same
    (SHA-256 of every file of the case, in part order). A case listed twice under the same
    path, one already rejected (``problem``) and a file that cannot be read are left to the
    checks that name those."""
    digests, files, seen = [], [], set()
    for case in cases:
        paths = tuple(dict.fromkeys(str(part.path) for part in case.parts))
        resolved = tuple(str(Path(p).resolve()) for p in paths)
        if case.problem or not paths or resolved in seen:
            continue
        seen.add(resolved)
        try:
            digests.append(tuple(io.file_digest(p) for p in paths))
        except OSError:
            continue
        files.append(paths[0])
    index = {}
    pairs = []
    for i, digest in enumerate(digests):
        if digest in index:
            pairs.append((index[digest], i))
        else:
            index[digest] = i
    return [Duplicates(tuple(files[i] for i in group), "identical files")
            for group in _groups(pairs, len(files))]


def same_shapes(shapes: np.ndarray, weights: np.ndarray, files,
                within: float = DUPLICATE_DISTANCE) -> list:
    """The groups of cases whose corresponded shapes, each moved to its centroid, are closer than
    ``within`` of the shape's size.

    Only translation is taken out, not rotation or size: a copy moved elsewhere (another origin)
    is the same shape, but two shapes that a rotation makes congruent (a case and its mirror
    image turned over, as in synthetic populations) are not; nor are a left and a mirrored
    right side of one subject, scanned in their own poses.

    Parameters
    ----------
    shapes : ndarray (n_s, n_p, 3)
        The corresponded points of the cases in their own coordinates (e.g. of the initial
        correspondence, ``CorrespondenceState.raw_shapes``).
    weights : ndarray (n_p,)
        The area weights of the points (sum 1).
    files : sequence of str
        What names each case in a message (its file).
    within : float
        Two shapes are one when sqrt(sum_k w_k |a_k - b_k|^2), each centred on its weighted
        centroid, is below ``within`` times the size: the root mean over the cases of
        sum_k w_k |x_k - c|^2 about their centroids c.

    Returns
    -------
    list of Duplicates
        Connected groups of such pairs, each with its largest distance in mm and as a share
        of the size.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> shapes = rng.normal(size=(4, 50, 3))
    >>> shapes[3] = shapes[1] + [10.0, 0.0, 0.0]             # a moved copy
    >>> [d.files for d in same_shapes(shapes, np.full(50, 1 / 50), "abcd")]
    [('b', 'd')]
    """
    weights = np.asarray(weights, dtype=np.float64)
    shapes = np.asarray(shapes, dtype=np.float64)
    centroids = np.einsum("k,ikd->id", weights, shapes)
    root = np.sqrt(weights)[:, None]
    # the weighted shapes about their centroids, one row each (sum of squares: the RMS distance)
    z = np.empty((len(shapes), shapes.shape[1] * 3))
    for i, shape in enumerate(shapes):
        z[i] = ((shape - centroids[i]) * root).ravel()
    size = float(np.sqrt(np.mean(np.einsum("ij,ij->i", z, z))))
    if len(shapes) < 2 or not size > 0:
        return []
    close = close_pairs(z, within * size)
    found = []
    for group in _groups(close, len(shapes)):
        centred = {i: shapes[i] - centroids[i] for i in group}
        farthest = max(float(np.sqrt(weights @ np.sum((centred[i] - centred[j]) ** 2, axis=1)))
                       for a, i in enumerate(group) for j in group[a + 1:])
        found.append(Duplicates(tuple(str(files[i]) for i in group),
                                f"the same shape (RMS distance {farthest:.2g} mm, "
                                f"{100 * farthest / size:.2g} % of its size)"))
    return found


# the directions :func:`close_pairs` projects the rows on, at most, and the rows they are taken from
PROJECTED_DIRECTIONS = 16
DIRECTION_ROWS = 256


def close_pairs(rows: np.ndarray, radius: float) -> np.ndarray:
    """The pairs (i, j), i < j, of ``rows`` (n, d) whose Euclidean distance is below ``radius``,
    as an (m, 2) array in lexicographic order, without the n x n distances.

    The rows are projected on a few orthonormal directions (the leading principal directions of
    the first :data:`DIRECTION_ROWS` rows): a projection never lengthens a difference, so every
    close pair is among the pairs whose projections lie within ``radius`` (found with a k-d
    tree), and only those are measured in full. The cost grows as n log n with few such pairs
    (n^2 when most rows are close to each other).

    Examples
    --------
    >>> rows = np.random.default_rng(0).normal(size=(500, 40))
    >>> rows[7] = rows[300] + 1e-3
    >>> close_pairs(rows, 0.1).tolist()
    [[7, 300]]
    """
    from scipy.spatial import cKDTree

    rows = np.asarray(rows, dtype=np.float64)
    sample = rows[:DIRECTION_ROWS] - rows[:DIRECTION_ROWS].mean(axis=0)
    # the sample's leading principal directions, from the eigenvectors of its small Gram
    # matrix, made exactly orthonormal (a projection on them cannot lengthen a difference)
    vectors = np.linalg.eigh(sample @ sample.T)[1][:, ::-1][:, :PROJECTED_DIRECTIONS]
    directions = np.linalg.qr(sample.T @ vectors)[0].T
    # the bound with room for the projection's rounding, so that no close pair is missed
    reach = radius * (1.0 + 1e-9) + 1e-9 * float(np.sqrt(np.max(np.einsum("ij,ij->i", rows,
                                                                         rows), initial=0.0)))
    candidates = cKDTree(rows @ directions.T).query_pairs(reach, output_type="ndarray")
    candidates = candidates[np.lexsort((candidates[:, 1], candidates[:, 0]))]
    keep = np.zeros(len(candidates), dtype=bool)
    for start in range(0, len(candidates), 4096):     # the differences a block at a time
        pairs = candidates[start:start + 4096]
        difference = rows[pairs[:, 0]] - rows[pairs[:, 1]]
        keep[start:start + 4096] = np.einsum("ij,ij->i", difference, difference) < radius ** 2
    return candidates[keep].reshape(-1, 2)
