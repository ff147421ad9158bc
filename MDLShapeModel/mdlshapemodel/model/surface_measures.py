"""Generalization and specificity measured surface to surface (beyond the paper's IV-B).

:func:`surface_generalization` and :func:`surface_specificity` measure the reconstructions and
samples of :func:`.evaluation.generalization` and :func:`.evaluation.specificity` against the true
training surfaces, which does not depend on the correspondence being judged. The symmetric surface
distance of a mesh X (the corresponded connectivity) and a true surface S is the mean of (a) the
mean distance from the points of X to S and (b) the mean distance from the vertices of S to X; its
area-weighted version weights (a) by the area measure ``weights`` and (b) by the vertex areas of
S. Point-to-triangle distances are exact (:class:`MeshSearch`: the distances of
:class:`~mdlshapemodel.prepare.surface.SurfaceDistance`, each search started from the triangle
found nearest to the same point the last time); large surfaces may be sampled
(:class:`RandomPoints`, :class:`StratifiedPoints`).
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from ..errors import ArgumentError
from ..prepare.nearest import TriangleGrid
from . import evaluation_kernels
from .space import ModelSpace, displacements, leave_one_out, sample_scores, space_of


#: Points without a guessed triangle are searched on the grid from scratch until this many have
#: been, since the mesh last moved; from then on they start from the triangle whose centroid is
#: nearest (a k-d tree of the centroids, which costs about as much to build as this many grid
#: searches).
CENTROID_TREE_POINTS = 500
#: True surfaces the surface specificity keeps built, each with its search structures: the
#: nearest cases of its samples recur, and building one again costs little beside measuring
#: on it, so the bound keeps the memory from growing with n_s.
SPECIFICITY_SURFACES_KEPT = 256


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
            raise ArgumentError(f"need at least one triangle, got faces of shape {self.faces.shape}")
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


class _TrueSurfaces:
    """The true surfaces of the n_s shapes, each :class:`_TrueSurface` (with its search
    structures) built when first asked for, and kept until released, or, past ``kept`` of them,
    until it is the one least recently asked for: a measure holds those of the cases it
    compares, not of the whole population. A surface built again is the same, so is what is
    measured on it."""

    def __init__(self, surfaces, n_s: int, kept: int | None = None):
        if len(surfaces) != n_s:
            raise ArgumentError(f"need one true surface per shape: {len(surfaces)} surfaces, "
                                f"{n_s} shapes")
        self.surfaces, self.built, self.kept = surfaces, OrderedDict(), kept

    def __getitem__(self, i: int) -> _TrueSurface:
        if i in self.built:
            self.built.move_to_end(i)
        else:
            self.built[i] = _TrueSurface(*self.surfaces[i])
            if self.kept is not None and len(self.built) > self.kept:
                self.built.popitem(last=False)
        return self.built[i]

    def release(self, i: int):
        self.built.pop(i, None)


def _mean_se(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean over axis 0 and its standard error sd / sqrt(n - 1) (eq. 21, 23)."""
    scale = 1.0 / np.sqrt(max(len(values) - 1, 1))
    return values.mean(axis=0), values.std(axis=0, ddof=1) * scale


def surface_generalization(shapes: np.ndarray, weights: np.ndarray, triangles: np.ndarray,
                           surfaces, max_modes: int, max_points: int | None = None,
                           rng: np.random.Generator | None = None,
                           space: ModelSpace | None = None, cases=None) -> dict:
    """Leave-one-out generalization measured surface to surface against the true surfaces.

    For each training shape i and M = 1..max_modes, the reconstruction x_i'(M) of
    :func:`.evaluation.generalization` (the model built without shape i, M modes) is turned back
    into points and meshed with ``triangles``; it is compared with the TRUE surface i by the
    symmetric surface distance: the mean of (a) the mean distance from the reconstruction's points
    to surface i and (b) the mean distance from surface i's vertices to the reconstruction mesh.
    Distances are exact point-to-triangle distances (:class:`MeshSearch`; with each further mode,
    every point's search starts from the triangle found nearest with the previous one).

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
        The shapes' :func:`.space.model_space`, when known.
    cases : ndarray of int, optional
        The k shapes left out in turn (:func:`.evaluation.leave_out_cases`); default all
        (k = n_s), and the per-case values below then have k rows, in this order.

    Returns
    -------
    dict of ndarray
        ``distance``, ``distance_se`` (max_modes,): mean over the shapes of the symmetric surface
        distance (mm), SE = sd / sqrt(n_s - 1) (eq. 21). ``weighted``, ``weighted_se``: the same
        with area weights (the point weights for (a), the true surface's vertex areas for (b)).
        ``distance_per_case``, ``weighted_per_case`` (n_s, max_modes): each shape's values.
        ``to_surface_per_case``, ``from_surface_per_case`` (n_s, max_modes): the area-weighted
        directional means (a) and (b); (a) is at most :func:`.evaluation.generalization`'s
        ``distance_per_case`` whenever the corresponded points lie on the true surfaces.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    shapes = np.asarray(shapes, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    coordinates, to_points = space_of(shapes, weights, space)
    n_s, n_p = len(coordinates), shapes.shape[1]
    true = _TrueSurfaces(surfaces, n_s)
    order = np.arange(n_s) if cases is None else np.asarray(cases, dtype=np.int64)
    points_sampler = _sampler(shapes[0], max_points, stratified=False)
    values = np.zeros((4, len(order), max_modes))
    mesh = None
    for row, (i, residuals, used) in enumerate(leave_one_out(coordinates, max_modes, order)):
        rebuilt = shapes[i] - displacements(residuals, to_points)
        # the reconstructions with more modes move little: each search starts where the last
        # one for the same point or vertex ended, the first from shape i's mesh
        on_true = np.full(n_p, -1, dtype=np.int64)
        on_mesh = _faces_near(shapes[i], triangles, true[i].vertices)
        true_sampler = _sampler(true[i].vertices, max_points, stratified=False)
        for m in range(max_modes):
            if m > 0 and used[m] == used[m - 1]:        # the same reconstruction as with m modes
                values[:, row, m] = values[:, row, m - 1]
                continue
            if mesh is None:
                mesh = MeshSearch(rebuilt[m], triangles)
            else:
                mesh.move(rebuilt[m])
            values[:, row, m] = _symmetric(rebuilt[m], weights, mesh, true[i], points_sampler,
                                           true_sampler, rng, on_true, on_mesh)
        true.release(i)                 # one case's search structures at a time
    return _generalization_of(values)


#: The per-case values of :func:`surface_generalization`, in the order of its ``values`` rows.
_PER_CASE = ("distance_per_case", "weighted_per_case", "to_surface_per_case",
             "from_surface_per_case")


def _generalization_of(values: np.ndarray) -> dict:
    """:func:`surface_generalization`'s result from its per-case values (4, k, max_modes)."""
    distance, distance_se = _mean_se(values[0])
    weighted, weighted_se = _mean_se(values[1])
    return {"distance": distance, "distance_se": distance_se,
            "weighted": weighted, "weighted_se": weighted_se,
            **{name: values[row] for row, name in enumerate(_PER_CASE)}}


def joined_generalization(parts: list) -> dict:
    """The :func:`surface_generalization` of the cases of ``parts`` together: each part that
    function's result for some of the cases (its ``cases``), the parts in the order of the cases.

    Each case's values depend on that case alone (the distances are exact whatever the searches
    start from; sampled points, with ``max_points``, are drawn in the order of the cases, so
    only without sampling), so the cases may be measured in separate runs, e.g. in two
    processes, and joined: the result is that of one run over them all, bit for bit.
    """
    if not parts:
        raise ArgumentError("no surface generalization to join")
    return _generalization_of(np.concatenate(
        [np.stack([part[name] for name in _PER_CASE]) for part in parts], axis=1))


def surface_specificity(shapes: np.ndarray, weights: np.ndarray, triangles: np.ndarray, surfaces,
                        max_modes: int, n_samples: int = 1000,
                        rng: np.random.Generator | None = None, candidates: int = 3,
                        max_points: int | None = 64, space: ModelSpace | None = None) -> dict:
    """Specificity measured surface to surface: model samples against the true training surfaces.

    Samples are drawn as :func:`.evaluation.specificity` draws them: scores b_m ~ N(0, lambda_m) on
    the first M modes, from one (n_samples, n_s - 1) array of standard normals taken first from
    ``rng`` (so a generator in the same state gives the same samples as the first n_samples of
    :func:`.evaluation.specificity`). Each sample, meshed with ``triangles``, is compared with the
    nearest training SURFACE by the symmetric surface distance of :func:`surface_generalization`.

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
        Default: ``numpy.random.default_rng(0)``, as :func:`.evaluation.specificity`.
    candidates : int
        Training shapes, nearest in model space, compared surface to surface with each sample.
    max_points : int or None
        Strata, i.e. points per side of each measured distance (see above); None: all points,
        exact.
    space : ModelSpace, optional
        The shapes' :func:`.space.model_space`, when known.

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
    coordinates, to_points = space_of(shapes, weights, space)
    n_s, rank = coordinates.shape
    # exactly as specificity(): axis m of the model-space coordinates has variance lambda_m
    sd = np.sqrt(np.sum(coordinates ** 2, axis=0) / n_s)
    scores = sample_scores(rng, n_samples, sd, max_modes)
    true = _TrueSurfaces(surfaces, n_s, SPECIFICITY_SURFACES_KEPT)
    candidates = int(min(max(candidates, 1), n_s))
    mean = shapes.mean(axis=0)
    points_sampler = _sampler(mean, max_points, stratified=True)
    # built with the true surfaces, for the candidates only
    true_samplers = {}
    train_sq = np.sum(coordinates ** 2, axis=1)
    distance = np.zeros((n_samples, max_modes))
    weighted = np.zeros((n_samples, max_modes))
    nearest = np.zeros((n_samples, max_modes), dtype=np.int64)
    # per true surface, the triangles last found nearest (see _symmetric); on the samples' mesh
    # first those of the training shape's own mesh, which the samples it is a candidate for are near
    on_true = [None] * n_s
    on_mesh = [None] * n_s
    mesh = None
    for m in range(1, max_modes + 1):
        kept = min(m, rank)
        if m > 1 and kept == min(m - 1, rank):         # the same samples as with m - 1 modes
            distance[:, m - 1], weighted[:, m - 1] = distance[:, m - 2], weighted[:, m - 2]
            nearest[:, m - 1] = nearest[:, m - 2]
            continue
        sample = np.zeros((n_samples, rank))
        sample[:, :kept] = scores[:, :kept]
        d2 = (np.sum(sample ** 2, axis=1)[:, None] - 2 * sample @ coordinates.T
              + train_sq[None, :])
        order = np.argsort(d2, axis=1, kind="stable")[:, :candidates]
        samples = mean + displacements(sample[:, :kept], to_points[:kept])
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
                    true_samplers[candidate] = _sampler(true[candidate].vertices, max_points,
                                                        stratified=True)
                    on_true[candidate] = np.full(len(mean), -1, dtype=np.int64)
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
