"""Model quality: compactness, generalization and specificity with standard errors (IV-B).

Distances use the area measure: the squared distance of two corresponded shapes is
sum_k w_k |a_k - b_k|^2 (mm^2, the paper's |x - y|^2 with the weights of eq. 15-17), and the mean
point-to-point distance is sum_k w_k |a_k - b_k| (mm).

Everything is computed in model space: the n_s training shapes span an (n_s - 1)-dimensional
affine space, and the leave-one-out models and the specificity samples all live in it, so squared
distances are computed from (n_s - 1)-vectors. Only the mm point-to-point distances need the points.
:func:`evaluate` computes the :class:`ModelSpace` once for all its measures, with BLAS on one
thread.

Beyond the paper, :func:`surface_generalization` and :func:`surface_specificity` measure the same
reconstructions and samples surface to surface against the true training surfaces, which does not
depend on the correspondence being judged. The symmetric surface distance of a mesh X (the
corresponded connectivity) and a true surface S is the mean of (a) the mean distance from the points
of X to S and (b) the mean distance from the vertices of S to X; its area-weighted version weights
(a) by the area measure ``weights`` and (b) by the vertex areas of S. Point-to-triangle distances
are exact (:class:`MeshSearch`: the distances of
:class:`~mdlshapemodel.prepare.surface.SurfaceDistance`, each search started from the triangle
found nearest to the same point the last time).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..correspondence import hotloops
from ..parallel import Task
from ..prepare.nearest import TriangleGrid
from . import evaluation_kernels
from .shape_model import ShapeModel

#: :func:`evaluate` measures surface generalization on at most this many points per side (exact
#: for the usual 2,562 correspondence points and surfaces of up to 5,000 vertices; larger true
#: surfaces are subsampled to bound the cost).
SURFACE_GENERALIZATION_POINTS = 5000


#: A direction of the shapes whose variance is below this share of the largest one's is no mode:
#: it holds rounding (identical cases differ there in the last digits), so the model spaces here
#: and the leave-one-out models leave it out, as :meth:`ShapeModel.from_shapes` leaves it out of
#: a model (its ``relative_tolerance``). The measures of aligned shapes and of the model's own
#: reconstruction of them (``mdlshapemodel compare`` reads those) are then the same.
ROUNDING_VARIANCE = 1e-10


def _modes_kept(singular: np.ndarray) -> np.ndarray:
    """Which singular values of centred shapes are modes (variance above
    :data:`ROUNDING_VARIANCE` of the largest)."""
    largest = max(float(singular.max(initial=0.0)), 1e-300)
    return singular ** 2 > ROUNDING_VARIANCE * largest ** 2


@dataclass(frozen=True)
class ModelSpace:
    """The training shapes in model space.

    ``coordinates`` (n_s, r): the centred, area-weighted shapes in an orthonormal basis of their
    span (principal component scores: orthogonal columns, sums of squares descending);
    ``to_points`` (r, 3 n_p): the map from model-space differences back to point displacements.
    Every measure of :func:`evaluate` works from one :func:`model_space` of the shapes.
    """

    coordinates: np.ndarray
    to_points: np.ndarray


def model_space(shapes: np.ndarray, weights: np.ndarray) -> ModelSpace:
    """The :class:`ModelSpace` of aligned, corresponded shapes (n_s, n_p, 3) with area weights."""
    n_s, n_p, _ = shapes.shape
    root = np.sqrt(weights)
    z = ((shapes - shapes.mean(axis=0)) * root[None, :, None]).reshape(n_s, -1)
    u, singular, vt = np.linalg.svd(z, full_matrices=False)
    keep = _modes_kept(singular)
    return ModelSpace(u[:, keep] * singular[keep], vt[keep] / np.repeat(root, 3))


def _space(shapes: np.ndarray, weights: np.ndarray, space: ModelSpace | None):
    """(coordinates, to_points) of ``space``, or of the shapes' model space when it is None."""
    space = model_space(shapes, weights) if space is None else space
    return space.coordinates, space.to_points


def _displacements(difference: np.ndarray, to_points: np.ndarray) -> np.ndarray:
    """Point displacements (k, n_p, 3) of model-space differences (k, r)."""
    return (difference @ to_points).reshape(len(difference), -1, 3)


def _point_distances(difference: np.ndarray, to_points: np.ndarray, weights: np.ndarray
                     ) -> np.ndarray:
    """Area-weighted mean point-to-point distance of model-space differences (k, r) -> (k,)."""
    return hotloops.weighted_point_norms(difference @ to_points, weights)


def compactness(variances: np.ndarray, n_shapes: int, max_modes: int):
    """C(M) = sum_{m<=M} lambda_m and its standard error sum sqrt(2/n_s) lambda_m (eq. 24-25)."""
    variances = np.pad(np.asarray(variances, float), (0, max(0, max_modes - len(variances))))
    cumulative = np.cumsum(variances[:max_modes])
    return cumulative, np.sqrt(2.0 / n_shapes) * cumulative


def _leave_one_out(coordinates: np.ndarray, max_modes: int):
    """For each shape i: (i, residuals (max_modes, r), modes used (max_modes,)).

    ``residuals[M - 1]`` is x_i - x_i'(M) in model space: x_i minus its reconstruction by the model
    built without it, with M modes (at most the n_s - 2 that model has).

    The coordinates are principal component scores (centred, orthogonal columns with sums of
    squares d_j), so the scatter of the other shapes about their mean is a diagonal matrix less a
    rank-one term, diag(d) - rho x_i x_i^T with rho = n_s / (n_s - 1). Its leading eigenpairs
    come from the secular equation (:func:`_downdated_modes`), O(n_s max_modes) per shape instead
    of an O(n_s^3) decomposition; where that is ill-conditioned (repeated d_j), the others'
    decomposition is computed directly.
    """
    n_s, r = coordinates.shape
    scatter = np.sum(coordinates ** 2, axis=0)
    # the model without shape i has at most n_s - 2 modes: null directions would otherwise
    # hold the part of shape i that the others do not span
    wanted = min(max_modes, max(n_s - 2, 0), r)
    rho = n_s / (n_s - 1.0)
    for i in range(n_s):
        offset = coordinates[i] * rho          # x_i minus the others' mean
        directions = _downdated_modes(scatter, coordinates[i], rho, wanted)
        if directions is None:
            directions, rank = _modes_of_others(coordinates, i)
        else:
            rank = wanted
        residuals = []
        for m in range(1, max_modes + 1):
            kept = directions[:min(m, rank)]
            residuals.append(offset - (offset @ kept.T) @ kept)
        used = np.minimum(np.arange(1, max_modes + 1), rank)
        yield i, np.array(residuals), used


def _modes_of_others(coordinates: np.ndarray, i: int) -> tuple[np.ndarray, int]:
    """The principal directions (rows) of every shape but i, and their number (the rank)."""
    others = np.delete(coordinates, i, axis=0)
    _, singular, directions = np.linalg.svd(others - others.mean(axis=0), full_matrices=False)
    rank = int(np.sum(_modes_kept(singular)))
    return directions, rank


def _downdated_modes(d: np.ndarray, v: np.ndarray, rho: float, count: int):
    """The ``count`` leading unit eigenvectors (rows) of diag(d) - rho v v^T, for d descending
    and positive, or None when the secular equation is ill-conditioned here.

    Each leading eigenvalue lies strictly between consecutive d (interlacing); it is the root of
    1 - rho sum_j v_j^2 / (d_j - lambda) in (d_{k+1}, d_k), found by bisection to the last bit,
    and its eigenvector is (diag(d) - lambda)^-1 v, normalised. Components of v that vanish, or
    d that repeat, would need deflation: then None.
    """
    r = len(d)
    if count == 0:
        return np.zeros((0, r))
    if count >= r or np.any(np.diff(d) >= 0.0):
        return None
    scale = float(np.sqrt(np.sum(v * v)))
    gaps = d[:-1] - d[1:]
    if scale == 0.0 or np.any(np.abs(v[:count + 1]) < 1e-8 * scale) or np.any(
            gaps[:count] < 1e-8 * d[0]):
        return None
    low, high = d[1:count + 1].copy(), d[:count].copy()
    for _ in range(200):
        middle = 0.5 * (low + high)
        if np.all((middle <= low) | (middle >= high)):
            break
        value = 1.0 - rho * np.sum(v * v / (d[None, :] - middle[:, None]), axis=1)
        # the secular function falls from +inf to -inf across the interval
        low = np.where(value > 0.0, middle, low)
        high = np.where(value > 0.0, high, middle)
    roots = 0.5 * (low + high)
    vectors = v[None, :] / (d[None, :] - roots[:, None])
    return vectors / np.linalg.norm(vectors, axis=1, keepdims=True)


def generalization(shapes: np.ndarray, weights: np.ndarray, max_modes: int,
                   space: ModelSpace | None = None):
    """Leave-one-out reconstruction error G(M) for M = 1..max_modes (eq. 20-21).

    Returns a dict of arrays (max_modes,): ``squared`` and ``squared_se`` (mm^2), ``distance`` and
    ``distance_se`` (mean point-to-point, mm); and the errors of each left-out shape,
    ``squared_per_case`` and ``distance_per_case`` (n_s, max_modes), whose means over the shapes
    are ``squared`` and ``distance``. ``space``: the shapes' :func:`model_space`, when known.
    """
    coordinates, to_points = _space(shapes, weights, space)
    n_s = len(coordinates)
    squared = np.zeros((n_s, max_modes))
    distance = np.zeros((n_s, max_modes))
    for i, residuals, _ in _leave_one_out(coordinates, max_modes):
        squared[i] = np.sum(residuals ** 2, axis=1)
        distance[i] = _point_distances(residuals, to_points, weights)
    result = _mean_and_error(squared, distance, n_s)
    result["squared_per_case"] = squared
    result["distance_per_case"] = distance
    return result


def subspace(space: ModelSpace, keep) -> ModelSpace:
    """The :class:`ModelSpace` of the shapes ``keep`` (indices) alone, from that of all of them.

    Their coordinates are centred on their own mean and turned to their principal axes; the turn
    is orthogonal, so every measure comes out as from :func:`model_space` of those shapes, in
    O(n_s r^2) instead of a decomposition of the shapes.
    """
    coordinates = space.coordinates[np.asarray(keep)]
    coordinates = coordinates - coordinates.mean(axis=0)
    u, singular, vt = np.linalg.svd(coordinates, full_matrices=False)
    nonzero = _modes_kept(singular)
    return ModelSpace(u[:, nonzero] * singular[nonzero], vt[nonzero] @ space.to_points)


def _squared_per_case(coordinates: np.ndarray, max_modes: int) -> np.ndarray:
    """The squared leave-one-out errors (n_s, max_modes) of eq. 20, in model space."""
    squared = np.zeros((len(coordinates), max_modes))
    for i, residuals, _ in _leave_one_out(coordinates, max_modes):
        squared[i] = np.sum(residuals ** 2, axis=1)
    return squared


#: The jackknife of :func:`generalization_jackknife` leaves out one case at a time up to this
#: many cases, and beyond it one of this many groups at a time (case k in group k mod groups): its
#: cost grows as n_s^2 per group, so a population of 1000 costs 50 recomputations, not 1000.
JACKKNIFE_GROUPS = 50


@dataclass(frozen=True)
class GeneralizationJackknife:
    """The squared leave-one-out errors of one correspondence's cases, ``per_case`` (n_s, M),
    and their mean with each of the jackknife's groups of cases left out of the population,
    ``left_out`` (groups, M). Two of the same cases and groups give
    :func:`generalization_difference`."""

    per_case: np.ndarray
    left_out: np.ndarray


def generalization_jackknife(space: ModelSpace, max_modes: int,
                             groups: int = JACKKNIFE_GROUPS) -> GeneralizationJackknife:
    """The leave-one-out errors (eq. 20) of the shapes of ``space``, and their mean with each
    group of cases left out of the population altogether (every other case's leave-one-out
    model then lacks that group too): one case per group up to ``groups`` cases, beyond them
    ``groups`` groups (case k in group k mod groups)."""
    n_s = len(space.coordinates)
    if n_s < 4:
        raise ValueError(f"the jackknife needs at least 4 cases, not {n_s}")
    if groups < 2:
        raise ValueError(f"the jackknife needs at least 2 groups, not {groups}")
    count = min(n_s, groups)
    group_of = np.arange(n_s) % count
    left_out = np.array([
        _squared_per_case(subspace(space, np.flatnonzero(group_of != g)).coordinates,
                          max_modes).mean(axis=0) for g in range(count)])
    return GeneralizationJackknife(_squared_per_case(space.coordinates, max_modes), left_out)


def generalization_difference(a: GeneralizationJackknife, b: GeneralizationJackknife) -> dict:
    """G_b(M) - G_a(M) of two correspondences of the same cases (rows in the same order, the
    same groups), and its jackknife standard error over the cases.

    The difference is the mean of the per-case differences of the squared leave-one-out errors
    (eq. 20-21). Their spread understates its error: each case's error depends on the model of
    all the others, so the per-case differences are not independent. The jackknife recomputes
    the difference with each group of cases left out of both populations
    (:func:`generalization_jackknife`): with D_(g) those g values,
    SE^2 = (g - 1)/g sum_g (D_(g) - mean D_(.))^2 (g = n_s: one case per group).

    Returns a dict of arrays (M,): ``difference``, ``se`` (jackknife), and ``paired_se``
    (sd of the per-case differences / sqrt(n_s - 1), the error eq. 21 would give them).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> shapes = rng.normal(size=(8, 20, 3))
    >>> noisier = shapes + rng.normal(scale=0.5, size=shapes.shape)
    >>> weights = np.full(20, 1 / 20)
    >>> result = generalization_difference(
    ...     generalization_jackknife(model_space(shapes, weights), 2),
    ...     generalization_jackknife(model_space(noisier, weights), 2))
    >>> bool(np.all(result["difference"] > 0))
    True
    """
    if a.per_case.shape != b.per_case.shape or a.left_out.shape != b.left_out.shape:
        raise ValueError(f"two jackknifes of the same cases, groups and modes are needed (got "
                         f"{a.per_case.shape}, {a.left_out.shape} and {b.per_case.shape}, "
                         f"{b.left_out.shape})")
    per_case = b.per_case - a.per_case
    left_out = b.left_out - a.left_out
    count, n_s = len(left_out), len(per_case)
    spread = np.sum((left_out - left_out.mean(axis=0)) ** 2, axis=0)
    return {"difference": per_case.mean(axis=0),
            "se": np.sqrt((count - 1.0) / count * spread),
            "paired_se": per_case.std(axis=0, ddof=1) / np.sqrt(n_s - 1.0)}


#: The measures :func:`measure_differences` compares (lower is better for each, IV-B).
COMPARED_MEASURES = ("compactness", "generalization", "specificity")

#: Two models differ in a measure where their difference exceeds this many standard errors of
#: the difference (the paper's criterion for its error bars, IV-B).
SIGNIFICANT_SE = 2.0


def verdict(difference: float, se: float) -> str:
    """"better", "worse" or "same": a model's measure minus a reference's, ``difference``, with
    its standard error ``se``. Lower is better for every measure (a compact model has little
    variance, IV-B); within :data:`SIGNIFICANT_SE` standard errors the two are the same.

    The one rule of ``mdlshapemodel compare`` and of the report's baseline verdicts.

    Examples
    --------
    >>> verdict(-0.5, 0.2), verdict(0.5, 0.2), verdict(0.3, 0.2)
    ('better', 'worse', 'same')
    """
    if not abs(difference) > SIGNIFICANT_SE * se:
        return "same"
    return "better" if difference < 0 else "worse"


def measure_differences(reference: dict, other: dict,
                        reference_jackknife: GeneralizationJackknife | None = None,
                        other_jackknife: GeneralizationJackknife | None = None) -> dict:
    """The measures of ``other`` minus those of ``reference``, two :func:`evaluate` results of
    the same cases (in the same order) with the same modes, and their standard errors.

    Generalization is paired: :func:`generalization_difference` of the two models'
    :func:`generalization_jackknife` (left out when either is None: fewer than 4 cases).
    Compactness has no per-case values and the specificities are of samples of two different
    models, so theirs are sqrt(SE_a^2 + SE_b^2).

    Returns
    -------
    dict
        measure -> ``difference``, ``se`` and ``verdict`` (:func:`verdict`, of ``other``) per M,
        ``significant`` (the verdict is not "same") and ``paired`` (the jackknife's SE).
    """
    result = {}
    for measure in COMPARED_MEASURES:
        paired = measure == "generalization"
        if paired:
            if reference_jackknife is None or other_jackknife is None:
                continue
            found = generalization_difference(reference_jackknife, other_jackknife)
            difference, se = found["difference"], found["se"]
        else:
            difference = np.asarray(other[measure]) - np.asarray(reference[measure])
            se = np.hypot(np.asarray(other[measure + "_se"]),
                          np.asarray(reference[measure + "_se"]))
        verdicts = [verdict(d, s) for d, s in zip(difference, se)]
        result[measure] = {"difference": np.asarray(difference).tolist(),
                           "se": np.asarray(se).tolist(), "paired": paired,
                           "significant": [v != "same" for v in verdicts], "verdict": verdicts}
    return result


def specificity(shapes: np.ndarray, weights: np.ndarray, max_modes: int, n_samples: int = 10_000,
                rng: np.random.Generator | None = None, chunk: int = 256,
                space: ModelSpace | None = None):
    """Specificity S(M): distance of model samples to their nearest training shape (eq. 22-23).

    Samples have scores b_m ~ N(0, lambda_m) on the first M modes (lambda_m the model variances,
    divisor n_s). Returns the same dict as :func:`generalization`.

    The nearest training shape is found in model space, ``chunk`` samples at a time (squared
    distances |a|^2 - 2 a.b + |b|^2 with one matrix product), and the squared distance to it
    recomputed from the difference; the point-to-point distances (mm) are then measured for every
    M in one pass per sample over its points (:func:`~.evaluation_kernels.sample_distances`).
    ``space``: the shapes' :func:`model_space`, when known.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    coordinates, to_points = _space(shapes, weights, space)
    n_s, rank = coordinates.shape
    # the model-space coordinates are principal component scores: axis m has variance lambda_m
    sd = np.sqrt(np.sum(coordinates ** 2, axis=0) / n_s)
    squared = np.zeros((n_samples, max_modes))
    distance = np.zeros((n_samples, max_modes))
    nearest = np.zeros((n_samples, max_modes), dtype=np.int64)
    normal = rng.standard_normal((n_samples, rank))
    train_sq = np.sum(coordinates ** 2, axis=1)
    kept = np.minimum(np.arange(1, max_modes + 1), rank)
    scores = normal[:, :kept[-1]] * sd[:kept[-1]]
    for m in range(1, max_modes + 1):
        used = kept[m - 1]
        for start in range(0, n_samples, chunk):
            stop = min(start + chunk, n_samples)
            sample = np.ascontiguousarray(scores[start:stop, :used])
            d2 = (np.sum(sample ** 2, axis=1)[:, None] - 2 * sample @ coordinates[:, :used].T
                  + train_sq[None, :])
            nearest[start:stop, m - 1] = np.argmin(d2, axis=1)
            offset = -coordinates[nearest[start:stop, m - 1]]
            offset[:, :used] += sample
            squared[start:stop, m - 1] = np.sum(offset ** 2, axis=1)
    # the training shapes' point displacements from the mean, once: a sample's distances then
    # cost O(M n_p), not O(n_s n_p)
    train_points = coordinates @ to_points
    evaluation_kernels.sample_distances(scores, np.ascontiguousarray(to_points[:kept[-1]]),
                                        train_points, nearest, kept, weights, distance)
    return _mean_and_error(squared, distance, n_samples)


def _mean_and_error(squared: np.ndarray, distance: np.ndarray, n: int) -> dict:
    scale = 1.0 / np.sqrt(max(n - 1, 1))
    return {"squared": squared.mean(axis=0), "squared_se": squared.std(axis=0, ddof=1) * scale,
            "distance": distance.mean(axis=0), "distance_se": distance.std(axis=0, ddof=1) * scale}


#: Points without a guessed triangle are searched on the grid from scratch until this many have
#: been, since the mesh last moved; from then on they start from the triangle whose centroid is
#: nearest (a k-d tree of the centroids, which costs about as much to build as this many grid
#: searches).
CENTROID_TREE_POINTS = 500


class MeshSearch:
    """Exact squared distances from points to a triangle mesh, each point's search started from a
    guessed nearest triangle (:func:`~.evaluation_kernels.closest_from`).

    The distances are those of :class:`~mdlshapemodel.prepare.surface.SurfaceDistance` (the same
    point-to-triangle arithmetic, the exact minimum), bit for bit; the guesses only decide how
    much of the mesh is searched. The evaluation asks about points and meshes that move a little
    between two questions, so the triangle found for a point the last time is a good guess.

    Parameters
    ----------
    vertices : ndarray (n, 3)
    faces : ndarray (m, 3)
        Triangles, m >= 1.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or len(self.faces) == 0:
            raise ValueError(f"need at least one triangle, got faces of shape {self.faces.shape}")
        self.grid = TriangleGrid(vertices, self.faces)
        self._moved()

    def move(self, vertices: np.ndarray):
        """New vertex positions (the same triangles)."""
        self.grid.move(vertices)
        self._moved()

    def _moved(self):
        self.boxes, self._extent = evaluation_kernels.triangle_boxes(self.grid.vertices,
                                                                     self.faces)
        self._centroids = None
        self._unguessed = 0           # points asked about without a guess since the last move

    def squared(self, points: np.ndarray, guess: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Squared distances (k,) of ``points`` (k, 3) and a nearest triangle of each (k,),
        from the guessed triangles ``guess`` (k,), -1 where there is none."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        guess = np.array(guess, dtype=np.int64)
        unknown = np.flatnonzero(guess < 0)
        self._unguessed += len(unknown)
        if len(unknown) and self._unguessed >= CENTROID_TREE_POINTS:
            if self._centroids is None:
                from scipy.spatial import cKDTree

                self._centroids = cKDTree(self.grid.vertices[self.faces].mean(axis=1))
            guess[unknown] = self._centroids.query(points[unknown])[1]
        elif len(unknown):
            _, squared, faces = self.grid.closest(points[unknown])
            if len(unknown) == len(points):
                return squared, faces
            guess[unknown] = faces
        grid = self.grid
        return evaluation_kernels.closest_from(points, guess, grid.vertices, self.faces,
                                               self.boxes, grid.origin, grid.cell, grid.shape,
                                               grid.start, grid.triangles, self._extent)


class _TrueSurface:
    """A true training surface: its search, vertices and vertex areas (eq. 17 on its mesh)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        from ..prepare.surface import triangle_vertex_areas

        self.vertices = np.asarray(vertices, dtype=np.float64)
        faces = np.asarray(faces, dtype=np.int64)
        self.search = MeshSearch(self.vertices, faces)
        self.areas = triangle_vertex_areas(self.vertices, faces)


class _AllPoints:
    """Sampler of the points entering a mean: all of them."""

    def draw(self, rng: np.random.Generator):
        """(indices, stratum fractions or None for equal shares)."""
        return slice(None), None


class RandomPoints:
    """Sampler: a uniform random subset of ``size`` of ``n`` points, fresh at each draw."""

    def __init__(self, n: int, size: int):
        self.n, self.size = n, size

    def draw(self, rng: np.random.Generator):
        return np.sort(rng.choice(self.n, size=self.size, replace=False)), None


class StratifiedPoints:
    """Sampler: one random point from each of ``size`` spatial strata, fresh at each draw.

    The strata are the Voronoi cells of ``size`` farthest-point-sampled points. Each stratum enters
    a mean with the fraction of the points it holds, so the estimate of a mean over all points is
    unbiased; for a distance field that varies smoothly over the surface its variance is far below
    that of a uniform random subset of the same size.
    """

    def __init__(self, points: np.ndarray, size: int):
        from scipy.spatial import cKDTree

        points = np.ascontiguousarray(points, dtype=np.float64)
        centres = evaluation_kernels.farthest_points(points, size)
        _, label = cKDTree(points[centres]).query(points)
        counts = np.bincount(label, minlength=size)
        self.order = np.argsort(label, kind="stable")
        self.start = (np.cumsum(counts) - counts)[counts > 0]
        self.counts = counts[counts > 0]
        self.fraction = self.counts / len(points)

    def draw(self, rng: np.random.Generator):
        offset = (rng.random(len(self.counts)) * self.counts).astype(np.int64)
        return self.order[self.start + offset], self.fraction


def _sampler(points: np.ndarray, max_points: int | None, stratified: bool):
    if max_points is None or max_points >= len(points):
        return _AllPoints()
    return StratifiedPoints(points, max_points) if stratified else RandomPoints(len(points), max_points)


def weighted_means(values: np.ndarray, fraction: np.ndarray | None, weights: np.ndarray):
    """(plain, weighted) mean of the values of sampled points: their estimates of the means of all
    points, ``fraction`` the share of the points each sampled point stands for (None: equal)."""
    if fraction is None:
        fraction = np.full(len(values), 1.0 / len(values))
    share = fraction * weights
    total = share.sum()
    plain = float(fraction @ values / fraction.sum())
    return plain, (float(share @ values / total) if total > 0 else plain)


def _symmetric(points: np.ndarray, weights: np.ndarray, mesh: MeshSearch, true: _TrueSurface,
               points_sampler, true_sampler, rng: np.random.Generator, on_true: np.ndarray,
               on_mesh: np.ndarray):
    """Plain and area-weighted symmetric distance of a mesh and a true surface, and directions.

    ``on_true`` (n_p,) and ``on_mesh`` (n_v,) hold the triangle of the true surface last found
    nearest to each point of the mesh, and the triangle of the mesh last found nearest to each
    vertex of the true surface (-1: none yet): the searches start there, and they are updated.

    Returns (plain, weighted, to_surface, from_surface): the last two are the area-weighted means
    of (a) points -> true surface and (b) true vertices -> mesh.
    """
    a_index, a_fraction = points_sampler.draw(rng)
    b_index, b_fraction = true_sampler.draw(rng)
    a_squared, on_true[a_index] = true.search.squared(points[a_index], on_true[a_index])
    b_squared, on_mesh[b_index] = mesh.squared(true.vertices[b_index], on_mesh[b_index])
    a_plain, to_surface = weighted_means(np.sqrt(a_squared), a_fraction, weights[a_index])
    b_plain, from_surface = weighted_means(np.sqrt(b_squared), b_fraction, true.areas[b_index])
    return 0.5 * (a_plain + b_plain), 0.5 * (to_surface + from_surface), to_surface, from_surface


def _faces_near(shape: np.ndarray, triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
    """For each of ``points`` (k, 3), a triangle of the corresponded mesh (``shape``,
    ``triangles``) at the mesh's point nearest to it: where a search on a mesh of the same
    triangles and of a shape near ``shape`` starts (:meth:`MeshSearch.squared`)."""
    from scipy.spatial import cKDTree

    incident = np.empty(len(shape), dtype=np.int64)
    incident[triangles.ravel()] = np.repeat(np.arange(len(triangles)), 3)
    return incident[cKDTree(shape).query(points)[1]]


def _true_surfaces(surfaces, n_s: int) -> list:
    if len(surfaces) != n_s:
        raise ValueError(f"need one true surface per shape: {len(surfaces)} surfaces, {n_s} shapes")
    return [_TrueSurface(vertices, faces) for vertices, faces in surfaces]


def _mean_se(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean over axis 0 and its standard error sd / sqrt(n - 1) (eq. 21, 23)."""
    scale = 1.0 / np.sqrt(max(len(values) - 1, 1))
    return values.mean(axis=0), values.std(axis=0, ddof=1) * scale


def surface_generalization(shapes: np.ndarray, weights: np.ndarray, triangles: np.ndarray,
                           surfaces, max_modes: int, max_points: int | None = None,
                           rng: np.random.Generator | None = None,
                           space: ModelSpace | None = None) -> dict:
    """Leave-one-out generalization measured surface to surface against the true surfaces.

    For each training shape i and M = 1..max_modes, the reconstruction x_i'(M) of
    :func:`generalization` (the model built without shape i, M modes) is turned back into points
    and meshed with ``triangles``; it is compared with the TRUE surface i by the symmetric surface
    distance: the mean of (a) the mean distance from the reconstruction's points to surface i and
    (b) the mean distance from surface i's vertices to the reconstruction mesh. Distances are
    exact point-to-triangle distances (:class:`MeshSearch`; with each further mode, every point's
    search starts from the triangle found nearest with the previous one).

    Parameters
    ----------
    shapes : ndarray (n_s, n_p, 3)
        Aligned, corresponded training shapes (the model frame).
    weights : ndarray (n_p,)
        Area measure of the points (eq. 15-17), positive; weights (a) in the area-weighted version.
    triangles : ndarray (m, 3)
        Connectivity of the corresponded points.
    surfaces : sequence of n_s (vertices (n_v, 3), faces (n_f, 3))
        The true training surfaces, already in the frame of ``shapes[i]``.
    max_modes : int
        Largest number of modes M.
    max_points : int, optional
        Use at most this many points on each side of each comparison (a fresh uniform random
        subset, drawn from ``rng``): an unbiased Monte Carlo estimate that bounds the cost for very
        large surfaces. Default: all points (exact).
    rng : numpy.random.Generator, optional
        Only used with ``max_points`` (default: ``numpy.random.default_rng(0)``).
    space : ModelSpace, optional
        The shapes' :func:`model_space`, when known.

    Returns
    -------
    dict of ndarray
        ``distance``, ``distance_se`` (max_modes,): mean over the shapes of the symmetric surface
        distance (mm), SE = sd / sqrt(n_s - 1) (eq. 21). ``weighted``, ``weighted_se``: the same
        with area weights (the point weights for (a), the true surface's vertex areas for (b)).
        ``distance_per_case``, ``weighted_per_case`` (n_s, max_modes): each shape's values.
        ``to_surface_per_case``, ``from_surface_per_case`` (n_s, max_modes): the area-weighted
        directional means (a) and (b); (a) is at most :func:`generalization`'s
        ``distance_per_case`` whenever the corresponded points lie on the true surfaces.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    shapes = np.asarray(shapes, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    coordinates, to_points = _space(shapes, weights, space)
    n_s, n_p = len(coordinates), shapes.shape[1]
    true = _true_surfaces(surfaces, n_s)
    points_sampler = _sampler(shapes[0], max_points, stratified=False)
    true_samplers = [_sampler(t.vertices, max_points, stratified=False) for t in true]
    values = np.zeros((4, n_s, max_modes))
    mesh = None
    for i, residuals, used in _leave_one_out(coordinates, max_modes):
        rebuilt = shapes[i] - _displacements(residuals, to_points)
        # the reconstructions with more modes move little: each search starts where the last
        # one for the same point or vertex ended, the first from shape i's mesh
        on_true = np.full(n_p, -1, dtype=np.int64)
        on_mesh = _faces_near(shapes[i], triangles, true[i].vertices)
        for m in range(max_modes):
            if m > 0 and used[m] == used[m - 1]:        # the same reconstruction as with m modes
                values[:, i, m] = values[:, i, m - 1]
                continue
            if mesh is None:
                mesh = MeshSearch(rebuilt[m], triangles)
            else:
                mesh.move(rebuilt[m])
            values[:, i, m] = _symmetric(rebuilt[m], weights, mesh, true[i], points_sampler,
                                         true_samplers[i], rng, on_true, on_mesh)
    distance, distance_se = _mean_se(values[0])
    weighted, weighted_se = _mean_se(values[1])
    return {"distance": distance, "distance_se": distance_se,
            "weighted": weighted, "weighted_se": weighted_se,
            "distance_per_case": values[0], "weighted_per_case": values[1],
            "to_surface_per_case": values[2], "from_surface_per_case": values[3]}


def surface_specificity(shapes: np.ndarray, weights: np.ndarray, triangles: np.ndarray, surfaces,
                        max_modes: int, n_samples: int = 1000,
                        rng: np.random.Generator | None = None, candidates: int = 3,
                        max_points: int | None = 64, space: ModelSpace | None = None) -> dict:
    """Specificity measured surface to surface: model samples against the true training surfaces.

    Samples are drawn as :func:`specificity` draws them: scores b_m ~ N(0, lambda_m) on the first
    M modes, from one (n_samples, n_s - 1) array of standard normals taken first from ``rng`` (so a
    generator in the same state gives the same samples as the first n_samples of
    :func:`specificity`). Each sample, meshed with ``triangles``, is compared with the nearest
    training SURFACE by the symmetric surface distance of :func:`surface_generalization`.

    To stay cheap, only the ``candidates`` training shapes nearest to the sample in model space
    (area-weighted squared distance of corresponded points) are compared surface to surface; the
    one at the smallest (plain) symmetric surface distance is the sample's nearest training
    surface, and both the plain and the area-weighted distance to it are reported. A training
    surface that is nearer as a surface but not among the ``candidates`` nearest shapes is missed;
    ``candidates=n_s`` compares all of them.

    Distances are exact point-to-triangle distances, but with ``max_points`` (default) each
    directional mean is estimated by stratified sampling: the points (the sample's, indexed as the
    mean shape's, for (a); the true surface's vertices for (b)) are divided once into
    ``max_points`` compact spatial strata (Voronoi cells of farthest-point samples), and each
    comparison draws one fresh random point per stratum, weighted by the stratum's share of the
    points. Each candidate's estimate is unbiased; its noise averages out over the samples and is
    part of the standard error. The minimum over the candidates of such estimates is biased low:
    on 40 shapes of 2,562 points (true surfaces of 2,562 vertices) by about 0.5% with 64 strata
    (2% with 64 uniformly random points), with about 3% rms noise per sample.
    ``max_points=None`` uses all points: exact symmetric distances and their exact minimum. The
    search for a point's closest triangle starts from the one found for the same point (of the
    sample's mesh, or of the true surface) the last time it was asked about on the same true
    surface (:class:`MeshSearch`).

    Parameters
    ----------
    shapes, weights, triangles, surfaces, max_modes
        As for :func:`surface_generalization`.
    n_samples : int
        Samples N per number of modes (the point measure uses 10,000; surface distances cost
        milliseconds each).
    rng : numpy.random.Generator, optional
        Default: ``numpy.random.default_rng(0)``, as :func:`specificity`.
    candidates : int
        Training shapes, nearest in model space, compared surface to surface with each sample.
    max_points : int or None
        Strata, i.e. points per side of each measured distance (see above); None: all points,
        exact.
    space : ModelSpace, optional
        The shapes' :func:`model_space`, when known.

    Returns
    -------
    dict
        ``distance``, ``distance_se``, ``weighted``, ``weighted_se`` (max_modes,): mean over the
        samples of the symmetric surface distance to the nearest training surface (mm), plain and
        area-weighted, SE = sd / sqrt(N - 1) (eq. 23). ``nearest`` (n_samples, max_modes): index
        of that training surface for each sample; ``distance_per_sample`` and
        ``weighted_per_sample`` (n_samples, max_modes): each sample's distances.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    shapes = np.asarray(shapes, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    coordinates, to_points = _space(shapes, weights, space)
    n_s, rank = coordinates.shape
    # exactly as specificity(): axis m of the model-space coordinates has variance lambda_m
    sd = np.sqrt(np.sum(coordinates ** 2, axis=0) / n_s)
    normal = rng.standard_normal((n_samples, rank))
    true = _true_surfaces(surfaces, n_s)
    candidates = int(min(max(candidates, 1), n_s))
    mean = shapes.mean(axis=0)
    points_sampler = _sampler(mean, max_points, stratified=True)
    true_samplers = [_sampler(t.vertices, max_points, stratified=True) for t in true]
    train_sq = np.sum(coordinates ** 2, axis=1)
    distance = np.zeros((n_samples, max_modes))
    weighted = np.zeros((n_samples, max_modes))
    nearest = np.zeros((n_samples, max_modes), dtype=np.int64)
    # per true surface, the triangles last found nearest (see _symmetric); on the samples' mesh
    # first those of the training shape's own mesh, which the samples it is a candidate for are near
    on_true = [np.full(len(mean), -1, dtype=np.int64) for _ in true]
    on_mesh = [None] * n_s
    mesh = None
    for m in range(1, max_modes + 1):
        kept = min(m, rank)
        if m > 1 and kept == min(m - 1, rank):         # the same samples as with m - 1 modes
            distance[:, m - 1], weighted[:, m - 1] = distance[:, m - 2], weighted[:, m - 2]
            nearest[:, m - 1] = nearest[:, m - 2]
            continue
        sample = np.zeros((n_samples, rank))
        sample[:, :kept] = normal[:, :kept] * sd[:kept]
        d2 = (np.sum(sample ** 2, axis=1)[:, None] - 2 * sample @ coordinates.T
              + train_sq[None, :])
        order = np.argsort(d2, axis=1, kind="stable")[:, :candidates]
        samples = mean + _displacements(sample[:, :kept], to_points[:kept])
        for s in range(n_samples):
            points = samples[s]
            if mesh is None:
                mesh = MeshSearch(points, triangles)
            else:
                mesh.move(points)
            best, j = None, -1
            for candidate in order[s]:
                if on_mesh[candidate] is None:
                    on_mesh[candidate] = _faces_near(shapes[candidate], triangles,
                                                     true[candidate].vertices)
                values = _symmetric(points, weights, mesh, true[candidate], points_sampler,
                                    true_samplers[candidate], rng, on_true[candidate],
                                    on_mesh[candidate])
                if best is None or values[0] < best[0]:
                    best, j = values, candidate
            distance[s, m - 1], weighted[s, m - 1], nearest[s, m - 1] = best[0], best[1], j
    distance_mean, distance_se = _mean_se(distance)
    weighted_mean, weighted_se = _mean_se(weighted)
    return {"distance": distance_mean, "distance_se": distance_se,
            "weighted": weighted_mean, "weighted_se": weighted_se, "nearest": nearest,
            "distance_per_sample": distance, "weighted_per_sample": weighted}


def evaluate(shapes: np.ndarray, weights: np.ndarray, variances: np.ndarray, max_modes: int = 10,
             n_samples: int = 10_000, rng: np.random.Generator | None = None,
             triangles: np.ndarray | None = None, surfaces=None,
             surface_samples: int = 1000, pool=None, jackknife: bool = False) -> dict:
    """Compactness, generalization and specificity for M = 1..max_modes, as JSON-ready lists.

    Parameters
    ----------
    shapes : ndarray (n_s, n_p, 3)
        Aligned, corresponded training shapes.
    weights : ndarray (n_p,)
        Area measure of the points.
    variances : ndarray
        Model variances lambda_m (for compactness).
    max_modes : int
        Largest M (at most n_s - 1).
    n_samples : int
        Specificity samples per M (point measures).
    rng : numpy.random.Generator, optional
        Specificity sampling (default: ``numpy.random.default_rng(0)``).
    triangles : ndarray (m, 3), optional
        Connectivity of the corresponded points; needed with ``surfaces``.
    surfaces : sequence of n_s (vertices, faces), optional
        True training surfaces in the frame of ``shapes``. When given, the measures are also
        taken surface to surface (:func:`surface_generalization` on at most
        ``SURFACE_GENERALIZATION_POINTS`` points per side, :func:`surface_specificity` with its
        defaults and ``surface_samples`` samples: the first ``surface_samples`` samples of the
        point specificity), adding ``generalization_surface_mm``, ``generalization_surface_mm_se``,
        ``specificity_surface_mm``, ``specificity_surface_mm_se`` and
        ``specificity_surface_samples``.
    surface_samples : int
        Specificity samples per M measured surface to surface.
    pool : concurrent.futures.Executor, optional
        Where to measure the surface generalization meanwhile (e.g. a process on another core);
        the results are the same. If its worker process dies, it is measured here instead
        (:class:`~mdlshapemodel.parallel.Task`).
    jackknife : bool
        Also the :func:`generalization_jackknife` of the shapes, under ``jackknife`` (not
        JSON: for :func:`measure_differences` against another correspondence of the same
        cases), when there are at least 4 shapes.

    Returns
    -------
    dict
        ``modes``, ``compactness``, ``generalization``, ``specificity`` (mm^2), their ``_mm``
        (point-to-point) versions, each with ``_se``, ``specificity_samples``, the surface
        measures above when ``surfaces`` is given, and ``jackknife`` when asked for.
    """
    from threadpoolctl import threadpool_limits

    n_s = len(shapes)
    max_modes = max(1, min(max_modes, n_s - 1))
    if surfaces is not None and triangles is None:
        raise ValueError("surface measures need the triangles of the corresponded points")
    rng = np.random.default_rng(0) if rng is None else rng
    # BLAS on one thread, as in a pool's worker: the surface generalization may have the other
    # core, where threaded BLAS costs many times what it gains, and the numbers are then those a
    # worker computes, whatever the number of cores
    with threadpool_limits(limits=1, user_api="blas"):
        return _evaluate(shapes, weights, variances, max_modes, n_samples, rng, triangles,
                         surfaces, surface_samples, pool, jackknife)


def _evaluate(shapes, weights, variances, max_modes, n_samples, rng, triangles, surfaces,
              surface_samples, pool, jackknife) -> dict:
    import copy

    n_s = len(shapes)
    surface_rng = copy.deepcopy(rng)            # the surface samples repeat the first point samples
    # one model space for every measure, wherever it runs
    space = model_space(shapes, weights)
    g_surface = None
    if surfaces is not None:
        # the longest part: started first, elsewhere when there is a pool
        arguments = (shapes, weights, triangles, surfaces, max_modes,
                     SURFACE_GENERALIZATION_POINTS, None, space)
        g_surface = Task(pool, surface_generalization, *arguments,
                         what="the surface generalization")
    c, c_se = compactness(variances, n_s, max_modes)
    g = generalization(shapes, weights, max_modes, space)
    s = specificity(shapes, weights, max_modes, n_samples, rng, space=space)
    as_list = {"modes": list(range(1, max_modes + 1)),
               "compactness": c.tolist(), "compactness_se": c_se.tolist()}
    for name, result in (("generalization", g), ("specificity", s)):
        as_list[name] = result["squared"].tolist()
        as_list[name + "_se"] = result["squared_se"].tolist()
        as_list[name + "_mm"] = result["distance"].tolist()
        as_list[name + "_mm_se"] = result["distance_se"].tolist()
    as_list["specificity_samples"] = int(n_samples)
    if surfaces is not None:
        s_surface = surface_specificity(shapes, weights, triangles, surfaces, max_modes,
                                        surface_samples, surface_rng, space=space)
        for name, result in (("generalization", g_surface.result()),
                             ("specificity", s_surface)):
            as_list[name + "_surface_mm"] = result["distance"].tolist()
            as_list[name + "_surface_mm_se"] = result["distance_se"].tolist()
        as_list["specificity_surface_samples"] = int(surface_samples)
    if jackknife and n_s >= 4:
        as_list["jackknife"] = generalization_jackknife(space, max_modes)
    return as_list


def evaluate_state(state, config, prepared: list | None = None,
                   model: ShapeModel | None = None, pool=None, background: bool = True,
                   jackknife: bool = False):
    """Compactness, generalization and specificity of the state's aligned shapes (``model``: the
    model of those shapes, when already built). With ``prepared`` (the cases, in the state's
    order) and ``config.surface_samples`` > 0, also measured surface to surface; with
    ``jackknife``, also the generalization's jackknife (:func:`evaluate`), to tell another
    correspondence of the same cases apart from this one (:func:`measure_differences`).

    With a ``pool`` (any ``concurrent.futures.Executor``): ``background`` runs the whole evaluation there and
    returns its :class:`~mdlshapemodel.parallel.Task` (the state may change meanwhile: it gets
    copies; if the worker process dies, ``result()`` evaluates here); otherwise only a part runs
    there and the result is returned when all is done.
    """
    aligned = state.aligned_shapes()
    if model is None:
        model = ShapeModel.from_shapes(aligned, state.weights)
    surfaces = None
    # (curves: the measures between the sample points only)
    if prepared is not None and config.surface_samples > 0 and not prepared[0].is_curve:
        surfaces = [(state.to_model_frame(i, vertices), faces)
                    for i, (vertices, faces) in enumerate(case.surface() for case in prepared)]
    arguments = (aligned, state.weights.copy(), model.variances, config.evaluation_modes,
                 config.specificity_samples, np.random.default_rng(config.seed),
                 state.triangles().copy(), surfaces, config.surface_samples)
    if pool is not None and background:
        return Task(pool, evaluate, *arguments, None, jackknife, what="an evaluation")
    return evaluate(*arguments, pool=pool, jackknife=jackknife)
