"""Closed 2-D curves: their geometry, checks, and the arc-length parameterization on the circle.

A curve is an array (n, 2) float64 of ordered points in physical coordinates (mm), the polygon
through them closed by the segment from the last point back to the first. A *clean* curve is
counter-clockwise (positive signed area), has no two consecutive points equal, the closing point
not repeated, at least :data:`MIN_POINTS` points, is finite, encloses an area, and is simple
(:func:`check_curve`, with which the readers of :mod:`.curve_io` end); a curve that is not
raises :class:`~mdlshapemodel.errors.InputError` with a one-line reason (callers add the file
name).

The 2-D counterpart of a sphere map is the arc-length parameterization on the unit circle
(:func:`curve_map`, docs/method.md section 1): t = 2 pi s / L, s the arc length from the curve's
origin, L its length. :func:`align_curve_origins` moves the origins of a population so that
equal parameters start as nearly corresponding points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import MAX_COORDINATE
from ..errors import InputError

#: the fewest points of a usable curve
MIN_POINTS = 8


# ------------------------------------------------------------------------------------------------
# Geometry of closed polygons


def signed_area(points: np.ndarray) -> float:
    """Signed area of the closed polygon (shoelace formula): positive when counter-clockwise."""
    x, y = points[:, 0], points[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def segment_lengths(points: np.ndarray) -> np.ndarray:
    """Length of each segment k -> k + 1 of the closed polygon (the last one closes it)."""
    return np.linalg.norm(np.roll(points, -1, axis=0) - points, axis=1)


def segment_vertex_lengths(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Half the summed length of the segments around each vertex: eq. 17 in 2-D.

    Parameters
    ----------
    points : ndarray (n, d)
        Vertex positions (e.g. the mean shape's samples, d = 3 with z = 0).
    segments : ndarray (m, 2)
        Vertex indices of each segment.

    Returns
    -------
    ndarray (n,)
        w_k before normalisation; sums to the polygon's length.
    """
    length = np.linalg.norm(points[segments[:, 1]] - points[segments[:, 0]], axis=-1)
    result = np.zeros(len(points))
    for k in range(2):
        np.add.at(result, segments[:, k], 0.5 * length)
    return result


def _orientation(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Twice the signed area of triangles (a, b, c), rowwise: > 0 when counter-clockwise."""
    return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - \
           (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])


def _segments_meet(p1, p2, q1, q2) -> np.ndarray:
    """Whether closed segments p1p2 and q1q2 share a point, rowwise (touching counts)."""
    d1, d2 = _orientation(q1, q2, p1), _orientation(q1, q2, p2)
    d3, d4 = _orientation(p1, p2, q1), _orientation(p1, p2, q2)
    straddle = (d1 * d2 <= 0) & (d3 * d4 <= 0)
    collinear = (d1 == 0) & (d2 == 0)
    # collinear segments meet only when their extents overlap along both axes
    overlap = np.ones(len(p1), dtype=bool)
    for axis in range(2):
        overlap &= (np.maximum(np.minimum(p1[:, axis], p2[:, axis]),
                               np.minimum(q1[:, axis], q2[:, axis]))
                    <= np.minimum(np.maximum(p1[:, axis], p2[:, axis]),
                                  np.maximum(q1[:, axis], q2[:, axis])))
    return np.where(collinear, overlap, straddle)


def find_crossing(points: np.ndarray) -> tuple[int, int, tuple[float, float]] | None:
    """Segments i < j (segment k joins point k to k + 1) where the closed polygon touches or
    crosses itself, and a point where they meet; None when the polygon is simple.

    Segments are binned in a uniform grid of cells about the median segment length (coarser
    when long segments would cover more than 16 n cells); only segments sharing a cell are
    tested, so the cost is about O(n) for evenly spaced points (10^4 points: milliseconds). Two consecutive segments cross when the second folds back onto
    the first (a spike).
    """
    n = len(points)
    start, end = points, np.roll(points, -1, axis=0)
    # spikes: consecutive segments that are collinear and point in opposite directions
    a, b = end - start, np.roll(end - start, -1, axis=0)
    spike = (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0] == 0) & (np.einsum("ij,ij->i", a, b) < 0)
    if np.any(spike):
        k = int(np.flatnonzero(spike)[0])
        i, j = sorted((k, (k + 1) % n))
        return i, j, (float(end[k, 0]), float(end[k, 1]))
    lower, upper = np.minimum(start, end), np.maximum(start, end)
    cell = max(float(np.median(np.linalg.norm(a, axis=1))), 1e-300)
    origin = lower.min(axis=0)
    while True:
        first = np.floor((lower - origin) / cell).astype(np.int64)
        last = np.floor((upper - origin) / cell).astype(np.int64)
        span = last - first + 1
        counts = span[:, 0] * span[:, 1]
        # a few long segments among many short ones would cover too many cells: coarser cells
        if counts.sum() <= 16 * n:
            break
        cell *= 2.0
    segment = np.repeat(np.arange(n), counts)
    offset = np.arange(len(segment)) - np.repeat(np.cumsum(counts) - counts, counts)
    cx = first[segment, 0] + offset % span[segment, 0]
    cy = first[segment, 1] + offset // span[segment, 0]
    key = cx * (int(last[:, 1].max()) + 2) + cy
    order = np.lexsort((segment, key))
    key, segment = key[order], segment[order]
    for gap in range(1, len(key)):
        same = np.flatnonzero(key[gap:] == key[:-gap])
        if len(same) == 0:
            break
        i, j = segment[same], segment[same + gap]
        apart = (np.abs(i - j) > 1) & (np.abs(i - j) != n - 1)   # neighbours share a vertex
        i, j = i[apart], j[apart]
        meet = _segments_meet(start[i], end[i], start[j], end[j])
        if np.any(meet):
            k = int(np.flatnonzero(meet)[0])
            i, j = int(i[k]), int(j[k])
            return min(i, j), max(i, j), _meeting_point(start[i], end[i], start[j], end[j])
    return None


def remove_small_loops(points: np.ndarray, max_fraction: float = 0.01
                       ) -> tuple[np.ndarray, int]:
    """Cut out the small loops of a closed polygon: where it crosses itself and the shorter of
    the two arcs between the crossing is under ``max_fraction`` of its length, that arc is
    replaced by the crossing point (traced outlines often have sub-pixel twists). Returns the
    polygon and the number of loops cut; raises :class:`InputError` at the first larger crossing.
    """
    cut = 0
    while True:
        found = find_crossing(points)
        if found is None:
            return points, cut
        i, j, (x, y) = found
        if j - i == 1 or (i == 0 and j == len(points) - 1):   # a spike: drop its tip
            points = np.delete(points, j if j - i == 1 else 0, axis=0)
            cut += 1
            continue
        lengths = segment_lengths(points)
        inner = float(lengths[i + 1:j].sum())         # the arc from point i + 1 to point j
        if min(inner, float(lengths.sum()) - inner) > max_fraction * float(lengths.sum()):
            raise InputError(f"the curve crosses itself near ({x:.4g}, {y:.4g})")
        crossing = np.array([[x, y]])
        if inner <= lengths.sum() - inner:
            points = np.concatenate([points[:i + 1], crossing, points[j + 1:]])
        else:
            points = np.concatenate([crossing, points[i + 1:j + 1]])
        points = points[np.any(points != np.roll(points, 1, axis=0), axis=1)]
        cut += 1


def _meeting_point(p1, p2, q1, q2) -> tuple[float, float]:
    """Where segments p1p2 and q1q2 meet (an end point of one when they are parallel)."""
    r, s = p2 - p1, q2 - q1
    denominator = r[0] * s[1] - r[1] * s[0]
    if denominator == 0:
        point = q1 if np.all(np.minimum(p1, p2) <= q1) and np.all(q1 <= np.maximum(p1, p2)) else p1
    else:
        t = ((q1 - p1)[0] * s[1] - (q1 - p1)[1] * s[0]) / denominator
        point = p1 + t * r
    return float(point[0]), float(point[1])


def check_curve(points, max_loop: float = 0.01, notes: list | None = None) -> np.ndarray:
    """A clean closed curve from ordered points, or :class:`InputError` saying why not.

    Consecutive equal points and a closing point equal to the first are dropped; the order is
    reversed if needed to make the curve counter-clockwise (the first point kept first); loops
    shorter than ``max_loop`` of the length are cut out (:func:`remove_small_loops`) and, when
    ``notes`` is a list, said there (a repair note for the case's record).

    Raises
    ------
    InputError
        Non-finite or out-of-range coordinates, fewer than :data:`MIN_POINTS` points, zero length
        or area, or a curve that crosses or touches itself beyond a small loop (the message names
        a point where).

    Examples
    --------
    >>> check_curve([(0, 0), (0, 1), (1, 1), (1, 0)])
    Traceback (most recent call last):
    ...
    mdlshapemodel.errors.InputError: the curve has 4 points; a curve needs at least 8
    """
    points = np.array(points, dtype=np.float64).reshape(-1, 2)
    if not np.all(np.isfinite(points)):
        raise InputError("the curve has non-finite (NaN or infinite) coordinates")
    largest = float(np.abs(points).max()) if points.size else 0.0
    if largest > MAX_COORDINATE:
        raise InputError(f"the curve has a coordinate of {largest:.3g} mm, beyond "
                         f"{MAX_COORDINATE:.0e} (MAX_COORDINATE)")
    keep = np.ones(len(points), dtype=bool)
    keep[1:] = np.any(points[1:] != points[:-1], axis=1)
    points = points[keep]
    if len(points) > 1 and np.all(points[-1] == points[0]):
        points = points[:-1]
    if len(points) < MIN_POINTS:
        raise InputError(f"the curve has {len(points)} points; a curve needs at least "
                         f"{MIN_POINTS}")
    length = float(segment_lengths(points).sum())
    area = signed_area(points)
    if not length > 0:
        raise InputError("the curve has zero length")
    if abs(area) <= 1e-12 * length * length:
        raise InputError("the curve encloses no area (its points are collinear)")
    if area < 0:
        points = np.concatenate([points[:1], points[:0:-1]])
    points, cut = remove_small_loops(points, max_loop)
    if cut and notes is not None:
        notes.append(f"{cut} small loop{'s' if cut > 1 else ''} cut where the curve crossed "
                     "itself")
    if len(points) < MIN_POINTS:
        raise InputError(f"the curve has {len(points)} points; a curve needs at least "
                         f"{MIN_POINTS}")
    return points



# ------------------------------------------------------------------------------------------------
# The arc-length parameterization on the circle


@dataclass
class CurveMap:
    """A closed curve and its arc-length parameterization on the unit circle.

    Attributes
    ----------
    points : ndarray (n, 2)
        The clean curve (counter-clockwise), points[0] its origin.
    parameter : ndarray (n,)
        t_k = 2 pi s_k / L in [0, 2 pi), s_k the arc length from points[0]; t[0] = 0.
    length : float
        L, the curve's length.
    """

    points: np.ndarray
    parameter: np.ndarray
    length: float


def curve_map(points) -> CurveMap:
    """The arc-length parameterization of a clean closed curve (section III-A in 2-D).

    S(t) is the point at arc length L t / (2 pi) from the origin points[0], linear between the
    points; a homeomorphism of the circle onto the curve, with |dS/dt| = L / (2 pi).
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    lengths = segment_lengths(points)
    length = float(lengths.sum())
    parameter = np.concatenate([[0.0], np.cumsum(lengths[:-1])]) * (2.0 * np.pi / length)
    return CurveMap(points, parameter, length)


def resample_curve(points, count: int, start: float = 0.0) -> np.ndarray:
    """``count`` points equally spaced in arc length along a closed curve, the first at the
    fraction ``start`` of its length from points[0] (e.g. to take a corresponded population out
    of correspondence)."""
    mapped = curve_map(points)
    targets = (2.0 * np.pi * (start + np.arange(count) / count)) % (2.0 * np.pi)
    return point_at(mapped, targets)


def point_at(mapped: CurveMap, parameters: np.ndarray) -> np.ndarray:
    """S(t) (m, 2) at parameters t (any real numbers: taken modulo 2 pi)."""
    t = np.mod(np.asarray(parameters, dtype=np.float64), 2.0 * np.pi)
    knots = np.append(mapped.parameter, 2.0 * np.pi)
    closed = np.vstack([mapped.points, mapped.points[:1]])
    return np.stack([np.interp(t, knots, closed[:, d]) for d in range(2)], axis=1)


def shift_origin(mapped: CurveMap, shift: float) -> CurveMap:
    """The same curve with its origin moved to parameter ``shift``: a point inserted there
    (unless one is there already) and the points rolled so that it comes first."""
    shift = float(np.mod(shift, 2.0 * np.pi))
    index = int(np.searchsorted(mapped.parameter, shift, side="right"))
    if mapped.parameter[index - 1] == shift:
        points = np.roll(mapped.points, -(index - 1), axis=0)
    else:
        origin = point_at(mapped, np.array([shift]))
        points = np.vstack([origin, mapped.points[index:], mapped.points[:index]])
    return curve_map(points)


def _correlation_shift(reference: np.ndarray, samples: np.ndarray) -> float:
    """The cyclic shift (in samples, fractional) of ``samples`` that best matches ``reference``
    after a similarity transform: both are complex, centred, equally spaced in arc length; the
    best rotation and scale for shift m give residual |r|^2 - |c_m|^2 / |x|^2 with
    c_m = sum_k conj(x_{k+m}) r_k, a cyclic cross-correlation (FFT)."""
    count = len(reference)
    c = np.fft.ifft(np.fft.fft(reference) * np.conj(np.fft.fft(samples)))
    # c[m] = sum_k r_k conj(x_{k-m}): the shift that rolls x onto r is -m
    power = np.abs(c)
    m = int(np.argmax(power))
    left, centre, right = power[(m - 1) % count], power[m], power[(m + 1) % count]
    curvature = left - 2.0 * centre + right
    fraction = 0.5 * (left - right) / curvature if curvature < 0 else 0.0
    return m + fraction


def align_curve_origins(maps: list, samples: int = 512, rounds: int = 2) -> list:
    """Move each curve's origin so that equal arc-length parameters start in correspondence.

    Each curve is sampled at ``samples`` points equally spaced in arc length; the origin shift
    that best matches the reference after the best rotation and scale (a proper similarity:
    curves are all counter-clockwise, so no reflection is needed) is found for all shifts at once
    by a cross-correlation (:func:`_correlation_shift`), refined to a fraction of a sample. The
    reference is the first curve, then (``rounds`` > 1) the mean of the aligned samples.

    Why not leave the origins to the optimiser: a curve's origin error is a rigid rotation of
    its parameter circle, which costs the optimiser many kernel steps to undo (every kernel
    fixes two points of the circle) and can trap it in a local minimum half a shape away; the
    correlation finds the globally best shift in O(n log n). Principal axes (the sphere's
    first-order alignment) are ambiguous for near-round or symmetric shapes; the correlation
    uses the whole outline.

    Returns new :class:`CurveMap` objects (the inputs are unchanged).
    """
    sampled = []
    for mapped in maps:
        z = point_at(mapped, 2.0 * np.pi * np.arange(samples) / samples)
        z = z[:, 0] + 1j * z[:, 1]
        sampled.append(z - z.mean())
    shifts = np.zeros(len(maps))
    reference = sampled[0]
    for _ in range(rounds):
        aligned = []
        for k, z in enumerate(sampled):
            shifts[k] = _correlation_shift(reference, z)
            rolled = _roll_fraction(z, shifts[k])
            # the best similarity onto the reference: rolled * <rolled, reference> / |rolled|^2
            aligned.append(rolled * (np.vdot(rolled, reference) / np.vdot(rolled, rolled)))
        reference = np.mean(aligned, axis=0)
    return [shift_origin(mapped, -2.0 * np.pi * shift / samples)
            for mapped, shift in zip(maps, shifts)]


def _roll_fraction(z: np.ndarray, shift: float) -> np.ndarray:
    """z rolled by a fractional number of samples (linear interpolation): result[k] = z[k - shift]."""
    count = len(z)
    position = (np.arange(count) - shift) % count
    low = np.floor(position).astype(np.int64)
    fraction = position - low
    return (1.0 - fraction) * z[low % count] + fraction * z[(low + 1) % count]


def point_curve_distances(points: np.ndarray, curve_points: np.ndarray, segments: np.ndarray,
                          chunk: int = 4096) -> np.ndarray:
    """Distance from each point (n, 2 or 3) to the nearest of the segments (m, 2) joining
    ``curve_points``: the 2-D counterpart of :func:`.surface.point_surface_distances`."""
    points = np.asarray(points, dtype=np.float64)
    a = np.asarray(curve_points, dtype=np.float64)[segments[:, 0]]
    edge = np.asarray(curve_points, dtype=np.float64)[segments[:, 1]] - a
    squared = np.maximum(np.einsum("md,md->m", edge, edge), 1e-300)
    result = np.empty(len(points))
    for start in range(0, len(points), chunk):
        offset = points[start:start + chunk, None, :] - a[None]
        t = np.clip(np.einsum("nmd,md->nm", offset, edge) / squared, 0.0, 1.0)
        nearest = offset - t[..., None] * edge[None]
        result[start:start + chunk] = np.sqrt(np.einsum("nmd,nmd->nm", nearest, nearest)
                                              .min(axis=1))
    return result
