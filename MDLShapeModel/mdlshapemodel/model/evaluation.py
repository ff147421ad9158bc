"""Model quality: compactness, generalization and specificity with standard errors (IV-B).

Distances use the area measure: the squared distance of two corresponded shapes is
sum_k w_k |a_k - b_k|^2 (mm^2, the paper's |x - y|^2 with the weights of eq. 15-17), and the mean
point-to-point distance is sum_k w_k |a_k - b_k| (mm).

Everything is computed in model space: the n_s training shapes span an (n_s - 1)-dimensional
affine space, and the leave-one-out models and the specificity samples all live in it, so squared
distances are computed from (n_s - 1)-vectors. Only the mm point-to-point distances need the points.
:func:`evaluate` computes the :class:`ModelSpace` once for all its measures, with BLAS on one
thread, or takes it from the decomposition that made the model (:class:`PrincipalAxes`).

Beyond the paper, :func:`evaluate` also measures the same reconstructions and samples surface to
surface against the true training surfaces (:mod:`.surface_measures`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..correspondence import hotloops
from ..errors import ArgumentError
from ..parallel import ProcessPool, Task
from ..prepare.case import joined_mesh
from . import evaluation_kernels
from .shape_model import ShapeModel, kept_variances
from .space import (ModelSpace, PrincipalAxes, leave_one_out, model_space, principal_axes,
                    sample_scores, space_of, subspace_coordinates)
from .surface_measures import (joined_generalization, surface_generalization,
                               surface_specificity)

#: :func:`evaluate` measures surface generalization on at most this many points per side (exact
#: for the usual 2,562 correspondence points and surfaces of up to 5,000 vertices; larger true
#: surfaces are subsampled to bound the cost).
SURFACE_GENERALIZATION_POINTS = 5000

#: With a pool, :func:`evaluate` measures the surface generalization of this share of the
#: left-out cases (the last) in its own process, after the point measures, and the rest on the
#: pool after the surface specificity (when no surface is sampled). The share balances the two
#: processes: the pool's surface specificity and most of the surface generalization against
#: this process's files written meanwhile (in a build), point measures, jackknife and the rest
#: of the surface generalization, so that both finish at about the same time.
SURFACE_GENERALIZATION_HERE = 0.4


def _point_distances(difference: np.ndarray, to_points: np.ndarray, weights: np.ndarray
                     ) -> np.ndarray:
    """Area-weighted mean point-to-point distance of model-space differences (k, r) -> (k,)."""
    return hotloops.weighted_point_norms(difference @ to_points, weights)


def compactness(variances: np.ndarray, n_shapes: int, max_modes: int):
    """C(M) = sum_{m<=M} lambda_m and its standard error sum sqrt(2/n_s) lambda_m (eq. 24-25)."""
    variances = np.pad(np.asarray(variances, float), (0, max(0, max_modes - len(variances))))
    cumulative = np.cumsum(variances[:max_modes])
    return cumulative, np.sqrt(2.0 / n_shapes) * cumulative



def leave_out_cases(n_shapes: int, limit: int | None, rng: np.random.Generator):
    """The cases left out in turn to measure the generalization (eq. 20): None (every case) up
    to ``limit`` cases (None: no limit), beyond it a uniform random subset of ``limit`` of them,
    drawn from ``rng``, in increasing order.

    Each left-out case costs O(r n_p) (its residuals mapped back to the points, r the rank of the
    shapes, up to n_s - 1), so leaving out every case grows as n_s^2 n_p; a fixed number of them
    bounds it, with the subset's mean an unbiased estimate of the mean over all the cases
    (:func:`generalization` gives its standard errors).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> leave_out_cases(10, 10, rng) is None, len(leave_out_cases(11, 10, rng))
    (True, 10)
    """
    if limit is None or n_shapes <= limit:
        return None
    if limit < 2:
        raise ArgumentError(f"the generalization needs at least 2 left-out cases, not {limit}")
    return np.sort(rng.choice(n_shapes, size=limit, replace=False))


def generalization(shapes: np.ndarray, weights: np.ndarray, max_modes: int,
                   space: ModelSpace | None = None, cases: np.ndarray | None = None):
    """Leave-one-out reconstruction error G(M) for M = 1..max_modes (eq. 20-21).

    Returns a dict of arrays (max_modes,): ``squared`` and ``squared_se`` (mm^2), ``distance`` and
    ``distance_se`` (mean point-to-point, mm); and the errors of each left-out shape,
    ``squared_per_case`` and ``distance_per_case`` (k, max_modes), whose means over the shapes
    are ``squared`` and ``distance``. ``space``: the shapes' :func:`model_space`, when known.

    ``cases``: the k shapes left out in turn (indices, :func:`leave_out_cases`); default all of
    them (k = n_s). Each is reconstructed by the model of all the other n_s - 1. The standard
    errors are then eq. 21 over the k cases: the error of the mean as an estimate of the expected
    error, which includes that of the subset. The subset's own part, its error as an estimate of
    the mean over all n_s cases, is added as ``squared_subsample_se`` and
    ``distance_subsample_se``: sd / sqrt(k) sqrt(1 - k / n_s) (sampling without replacement;
    0 when every case is left out).
    """
    coordinates, to_points = space_of(shapes, weights, space)
    n_s = len(coordinates)
    order = np.arange(n_s) if cases is None else np.asarray(cases, dtype=np.int64)
    squared = np.zeros((len(order), max_modes))
    distance = np.zeros((len(order), max_modes))
    for row, (_, residuals, _) in enumerate(leave_one_out(coordinates, max_modes, order)):
        squared[row] = np.sum(residuals ** 2, axis=1)
        distance[row] = _point_distances(residuals, to_points, weights)
    result = _mean_and_error(squared, distance, len(order))
    result["squared_per_case"] = squared
    result["distance_per_case"] = distance
    if cases is not None:
        remaining = np.sqrt(max(1.0 - len(order) / n_s, 0.0) / len(order))
        result["squared_subsample_se"] = squared.std(axis=0, ddof=1) * remaining
        result["distance_subsample_se"] = distance.std(axis=0, ddof=1) * remaining
    return result



def _squared_per_case(coordinates: np.ndarray, max_modes: int, cases=None) -> np.ndarray:
    """The squared leave-one-out errors (k, max_modes) of eq. 20 of the ``cases`` (default all
    n_s), in model space."""
    order = np.arange(len(coordinates)) if cases is None else cases
    squared = np.zeros((len(order), max_modes))
    for row, (_, residuals, _) in enumerate(leave_one_out(coordinates, max_modes, order)):
        squared[row] = np.sum(residuals ** 2, axis=1)
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
                             groups: int = JACKKNIFE_GROUPS,
                             cases: np.ndarray | None = None) -> GeneralizationJackknife:
    """The leave-one-out errors (eq. 20) of the shapes of ``space``, and their mean with each
    group of cases left out of the population altogether (every other case's leave-one-out
    model then lacks that group too): one case per group up to ``groups`` cases, beyond them
    ``groups`` groups (case k in group k mod groups).

    ``cases``: a random subset of the shapes (:func:`leave_out_cases`) whose errors stand for
    all of them; ``per_case`` are theirs, and the groups are of the subset's k cases (the k-th
    of the subset in group k mod groups), whose errors are not recomputed without the group:
    in the population of more than :attr:`~mdlshapemodel.config.BuildConfig.generalization_cases`
    shapes that a subset is drawn from, a group moves the others' models by a share of the
    order of its size / n_s, and recomputing would cost groups x n_s^3.
    """
    n_s = len(space.coordinates)
    if n_s < 4:
        raise ArgumentError(f"the jackknife needs at least 4 cases, not {n_s}")
    if groups < 2:
        raise ArgumentError(f"the jackknife needs at least 2 groups, not {groups}")
    if cases is not None:
        per_case = _squared_per_case(space.coordinates, max_modes, cases)
        count = min(len(per_case), groups)
        group_of = np.arange(len(per_case)) % count
        left_out = np.array([per_case[group_of != g].mean(axis=0) for g in range(count)])
        return GeneralizationJackknife(per_case, left_out)
    count = min(n_s, groups)
    group_of = np.arange(n_s) % count
    left_out = np.array([
        _squared_per_case(subspace_coordinates(space, np.flatnonzero(group_of != g)),
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
        raise ArgumentError(f"two jackknifes of the same cases, groups and modes are needed (got "
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
    coordinates, to_points = space_of(shapes, weights, space)
    n_s, rank = coordinates.shape
    # the model-space coordinates are principal component scores: axis m has variance lambda_m
    sd = np.sqrt(np.sum(coordinates ** 2, axis=0) / n_s)
    squared = np.zeros((n_samples, max_modes))
    distance = np.zeros((n_samples, max_modes))
    nearest = np.zeros((n_samples, max_modes), dtype=np.int64)
    scores = sample_scores(rng, n_samples, sd, max_modes)
    train_sq = np.sum(coordinates ** 2, axis=1)
    kept = np.minimum(np.arange(1, max_modes + 1), rank)
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


def evaluate(shapes: np.ndarray, weights: np.ndarray, variances: np.ndarray | None,
             max_modes: int = 10, n_samples: int = 10_000, rng: np.random.Generator | None = None,
             triangles: np.ndarray | None = None, surfaces=None,
             surface_samples: int = 1000, pool=None, jackknife: bool = False,
             generalization_cases: int | None = None, meanwhile=None,
             axes: PrincipalAxes | None = None) -> dict:
    """Compactness, generalization and specificity for M = 1..max_modes, as JSON-ready lists.

    Parameters
    ----------
    shapes : ndarray (n_s, n_p, 3)
        Aligned, corresponded training shapes.
    weights : ndarray (n_p,)
        Area measure of the points.
    variances : ndarray or None
        Model variances lambda_m (for compactness); None: those of the model of the shapes
        (:func:`~.shape_model.kept_variances` of their decomposition, which the measures use
        anyway: no model needs to be built to be evaluated).
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
        Where to measure the surface measures meanwhile (e.g. a process on another core): the
        surface specificity, and the surface generalization of all but the last
        :data:`SURFACE_GENERALIZATION_HERE` of the cases, which this process measures after its
        own measures; the results are the same. If its worker process dies, that work is done
        here instead (:class:`~mdlshapemodel.parallel.Task`).
    jackknife : bool
        Also the :func:`generalization_jackknife` of the shapes, under ``jackknife`` (not
        JSON: for :func:`measure_differences` against another correspondence of the same
        cases), when there are at least 4 shapes.
    generalization_cases : int, optional
        Beyond this many shapes, the generalization (point and surface) leaves out only this
        many, a random subset (:func:`leave_out_cases`, drawn from a generator spawned from
        ``rng``, so the specificity samples are those of an unlimited evaluation); the result
        then says so: ``generalization_cases`` (how many), ``generalization_subsample_se`` and
        ``generalization_mm_subsample_se`` (:func:`generalization`). Default: no limit.
    meanwhile : callable, optional
        Called without arguments once the surface measures are on the ``pool``, before the
        measures of this process (e.g. writing files while the pool measures), with BLAS on
        the caller's threads (the measures here use one).
    axes : PrincipalAxes, optional
        The shapes' :func:`~.space.principal_axes` (e.g. those their model was made from,
        :meth:`~.shape_model.ShapeModel.from_shapes`): their model space is then not computed
        again.

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
        raise ArgumentError("surface measures need the triangles of the corresponded points")
    if axes is not None and (axes.mean.shape != np.shape(shapes)[1:]
                             or len(axes.space.coordinates) != n_s
                             or not np.array_equal(axes.mean, np.mean(shapes, axis=0))):
        raise ArgumentError("the principal axes given are not those of the shapes evaluated "
                            f"({len(axes.space.coordinates)} shapes of {len(axes.mean)} points "
                            f"for {n_s} of {len(shapes[0])}, or another mean)")
    rng = np.random.default_rng(0) if rng is None else rng
    # BLAS on one thread, as in a pool's worker: the surface generalization may have the other
    # core, where threaded BLAS costs many times what it gains, and the numbers are then those a
    # worker computes, whatever the number of cores
    with threadpool_limits(limits=1, user_api="blas") as limiter:
        def with_callers_threads():
            # the caller's work, with the caller's BLAS threads: its numbers are its own
            limiter.restore_original_limits()
            try:
                meanwhile()
            finally:
                threadpool_limits(limits=1, user_api="blas")

        return _evaluate(shapes, weights, variances, max_modes, n_samples, rng, triangles,
                         surfaces, surface_samples, pool, jackknife, generalization_cases,
                         None if meanwhile is None else with_callers_threads, axes)


def _evaluate(shapes, weights, variances, max_modes, n_samples, rng, triangles, surfaces,
              surface_samples, pool, jackknife, generalization_cases, meanwhile, axes) -> dict:
    import copy

    n_s = len(shapes)
    surface_rng = copy.deepcopy(rng)            # the surface samples repeat the first point samples
    # a spawned generator leaves rng's own stream as it is
    cases = leave_out_cases(n_s, generalization_cases, rng.spawn(1)[0])
    # one model space for every measure, wherever it runs (and the model's variances with it)
    axes = principal_axes(shapes, weights) if axes is None else axes
    space = axes.space
    if variances is None:
        variances = kept_variances(axes.singular, n_s)
    pool_part, here = None, None
    if surfaces is not None:
        # the longest measures, started first: on the pool when there is one, in one piece of
        # work (the surface specificity, then the surface generalization of the first cases);
        # the last cases' surface generalization is measured here once this process's own
        # measures are done
        first, here = _generalization_shares(shapes, surfaces, cases, pool)
        pool_part = Task(pool, _surface_measures, shapes, weights, triangles, surfaces,
                         max_modes, surface_samples, surface_rng, space, first,
                         what="the surface measures")
    if meanwhile is not None:
        meanwhile()
    c, c_se = compactness(variances, n_s, max_modes)
    g = generalization(shapes, weights, max_modes, space, cases)
    s = specificity(shapes, weights, max_modes, n_samples, rng, space=space)
    as_list = {"modes": list(range(1, max_modes + 1)),
               "compactness": c.tolist(), "compactness_se": c_se.tolist()}
    for name, result in (("generalization", g), ("specificity", s)):
        as_list[name] = result["squared"].tolist()
        as_list[name + "_se"] = result["squared_se"].tolist()
        as_list[name + "_mm"] = result["distance"].tolist()
        as_list[name + "_mm_se"] = result["distance_se"].tolist()
    as_list["specificity_samples"] = int(n_samples)
    if cases is not None:
        as_list["generalization_cases"] = len(cases)
        as_list["generalization_subsample_se"] = g["squared_subsample_se"].tolist()
        as_list["generalization_mm_subsample_se"] = g["distance_subsample_se"].tolist()
    if jackknife and n_s >= 4:
        as_list["jackknife"] = generalization_jackknife(space, max_modes, cases=cases)
    if surfaces is not None:
        s_surface, g_surface = pool_part.result()
        if len(here):
            g_surface = joined_generalization([g_surface, surface_generalization(
                shapes, weights, triangles, surfaces, max_modes, SURFACE_GENERALIZATION_POINTS,
                None, space, here)])
        for name, result in (("generalization", g_surface), ("specificity", s_surface)):
            as_list[name + "_surface_mm"] = result["distance"].tolist()
            as_list[name + "_surface_mm_se"] = result["distance_se"].tolist()
        as_list["specificity_surface_samples"] = int(surface_samples)
    return as_list


def _surface_measures(shapes, weights, triangles, surfaces, max_modes, surface_samples, rng,
                      space, cases) -> tuple[dict, dict]:
    """The surface specificity (:func:`surface_specificity`, its samples from ``rng``) and the
    surface generalization of the left-out ``cases``, as :func:`evaluate` measures them."""
    return (surface_specificity(shapes, weights, triangles, surfaces, max_modes, surface_samples,
                                rng, space=space),
            surface_generalization(shapes, weights, triangles, surfaces, max_modes,
                                   SURFACE_GENERALIZATION_POINTS, None, space, cases))


def _generalization_shares(shapes: np.ndarray, surfaces, cases, pool) -> tuple:
    """The left-out cases (``cases``, None: all) whose surface generalization the ``pool``
    measures, and those measured here (the last :data:`SURFACE_GENERALIZATION_HERE` of them):
    none here without a pool, or when a surface is sampled (its points are drawn in the order
    of the cases, so the measure is then one run over them all)."""
    order = np.arange(len(shapes)) if cases is None else np.asarray(cases, dtype=np.int64)
    if pool is None or shapes.shape[1] > SURFACE_GENERALIZATION_POINTS or any(
            len(surfaces[i][0]) > SURFACE_GENERALIZATION_POINTS for i in order):
        return order, order[:0]
    split = len(order) - int(round(SURFACE_GENERALIZATION_HERE * len(order)))
    return order[:split], order[split:]


class ModelFrameSurfaces(Sequence):
    """The true surfaces of prepared cases in the model frame of a correspondence ``state`` as
    it is when this is made
    (:meth:`~mdlshapemodel.correspondence.state.CorrespondenceState.model_frame`),
    case i moved there when asked for: a list of them all would hold n_s more meshes through
    the evaluation, which measures one case at a time (:mod:`.surface_measures`). It holds the
    prepared cases' own meshes and the poses, not copies of the meshes; so does its pickle (for
    a pool's process), and neither follows the state as it changes afterwards.

    With ``from_file`` and cases whose maps lie in a file (:func:`~.prepare.mapped.mapped_cases`),
    it holds where they lie instead, and reads case i's meshes from the file when asked: so does
    its pickle, for a process of the same machine (a :class:`~.parallel.ProcessPool`'s), which
    then receives no copy of every mesh."""

    def __init__(self, state, prepared: list, from_file: bool = False):
        self.frame = state.model_frame()
        self.file = getattr(prepared, "file", None) if from_file else None
        self.meshes = None if self.file is not None else [case.meshes() for case in prepared]

    def __len__(self) -> int:
        return len(self.file if self.meshes is None else self.meshes)

    def __getitem__(self, i: int):
        meshes = self.file.meshes(i) if self.meshes is None else self.meshes[i]
        # (one part: its triangles as they are, not joined into a new array)
        vertices, faces = meshes[0] if len(meshes) == 1 else joined_mesh(meshes)
        return self.frame.to_model_frame(i, vertices), faces


def evaluate_state(state, config, prepared: list | None = None,
                   model: ShapeModel | None = None, pool=None, background: bool = True,
                   jackknife: bool = False, meanwhile=None, axes: PrincipalAxes | None = None):
    """Compactness, generalization and specificity of the state's aligned shapes (``model``: the
    model of those shapes, when already built, for its variances; none is built otherwise;
    ``axes``: the :func:`~.space.principal_axes` it was made from, which the measures then
    share instead of decomposing the shapes again). With ``prepared`` (the cases, in the state's
    order) and ``config.surface_samples`` > 0, also measured surface to surface; with
    ``jackknife``, also the generalization's jackknife (:func:`evaluate`), to tell another
    correspondence of the same cases apart from this one (:func:`measure_differences`).

    With a ``pool`` (any ``concurrent.futures.Executor``): ``background`` runs the whole evaluation there and
    returns its :class:`~mdlshapemodel.parallel.Task` (the state may change meanwhile: it gets
    copies; if the worker process dies, ``result()`` evaluates here); otherwise only a part runs
    there and the result is returned when all is done; ``meanwhile`` (a callable) is then
    called while the pool measures (:func:`evaluate`).
    """
    aligned = state.aligned_shapes()
    surfaces = None
    # (curves: the measures between the sample points only)
    if prepared is not None and config.surface_samples > 0 and not prepared[0].is_curve:
        # (the state may change meanwhile); a process of this machine reads the meshes' file
        surfaces = ModelFrameSurfaces(state, prepared, from_file=isinstance(pool, ProcessPool))
    arguments = (aligned, state.weights.copy(), None if model is None else model.variances,
                 config.evaluation_modes,
                 config.specificity_samples, np.random.default_rng(config.seed),
                 state.triangles().copy(), surfaces, config.surface_samples)
    if pool is not None and background:
        return Task(pool, evaluate, *arguments, None, jackknife, config.generalization_cases,
                    None, axes, what="an evaluation")
    return evaluate(*arguments, pool=pool, jackknife=jackknife,
                    generalization_cases=config.generalization_cases, meanwhile=meanwhile,
                    axes=axes)
