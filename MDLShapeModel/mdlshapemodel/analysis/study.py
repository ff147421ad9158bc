"""One analysis of a model's shapes: the per-point test, the global test, the discriminant and
classification of two groups, and how unusual each case is.

:func:`analyze_shapes` takes the corresponded shapes of a model's cases (for example
:func:`~.shapes.read_build`) and the design made of a subjects table
(:func:`~.table.subjects`), and returns an :class:`Analysis` of arrays; writing its files is the
job of :mod:`mdlshapemodel.analyze`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..config import AnalysisConfig, parse_contrast
from ..geometry import centroid_size
from ..model.outliers import Distances, modes_explaining, training_distances
from ..model.shape_model import ShapeModel
from ..progress import report
from .classification import Classification, classify
from .discriminant import Discriminant, discriminant, principal_scores
from .effects import (PREDICTED_AT, Interval, cohens_d, interval, partial_eta_squared,
                      predicted_offsets)
from .glm import PointTest, permutation_test
from .shapes import align, vertex_normals
from .table import Subjects, contrast_vector
from .tfce import Surface, surface_of


@dataclass
class GlobalTest:
    """The test of the effect on the first k principal scores together (permutation Hotelling's
    T^2 for one effect column, Pillai's trace for several)."""

    modes: int
    statistic: float
    p: float
    permutations: int


@dataclass
class SizeTest:
    """How much of the difference is size: the effect of each effect column on the cases'
    centroid size (the root area-weighted mean squared distance of the points from their
    centroid, mm, before any scaling), tested like a point.

    Attributes
    ----------
    sizes : ndarray (n_cases,)
        The used cases' centroid sizes (mm).
    effects : ndarray (r,)
        Each effect column's least-squares coefficient on them (mm; per unit of a covariate),
        adjusted for the nuisance.
    test : PointTest
        The design's test on the sizes (one "point").
    """

    sizes: np.ndarray
    effects: np.ndarray
    test: PointTest


@dataclass
class Unusual:
    """How unusual each of the model's cases is: Mahalanobis distance in the model space with its
    p-value (:mod:`~mdlshapemodel.model.outliers`) and, per point, how far the case lies from its
    reconstruction by the same k modes (mm)."""

    names: list
    distances: Distances
    departure: np.ndarray          # (n_s, n_p) mm


@dataclass
class SignedMap:
    """The signed test of one effect column along the normal, adjusted for the other effect
    columns and the nuisance (as MFSDA maps each covariate): Student's t of its coefficient
    (Welch's v with variance groups) per point, its permutation p-values and corrections.

    Attributes
    ----------
    name : str
        The effect column (a covariate, ``group=level`` or a level, ``change``).
    column : str
        Its table column.
    test : PointTest
        The test: ``test.t`` the signed statistic, ``test.p``, ``test.p_fwer``, ``test.q_fdr``
        (one-sided when ``test.tail`` says so).
    joint : bool
        Whether it is the analysis's per-point test itself (one effect column tested along the
        normal), not a test of its own.
    contrast : dict or None
        For a contrast of levels (``config.contrasts``), each level's coefficient.
    """

    name: str
    column: str
    test: PointTest
    joint: bool
    contrast: dict | None = None


@dataclass
class EffectSize:
    """How large one signed map's effect is along the normal, and how well it is known
    (:mod:`.effects`).

    Attributes
    ----------
    name : str
        The signed map's name (:attr:`SignedMap.name`).
    interval : Interval
        The per-point confidence interval at level 1 - alpha of the effect column's coefficient
        (or the contrast), with the nuisance.
    d : ndarray (p,) or None
        Cohen's d, for a column or contrast that compares two levels of a categorical column
        (or the mean change); else None.
    partial_eta2 : ndarray (p,)
        The column's partial eta^2 (adjusted for everything else in the model).
    """

    name: str
    interval: Interval
    d: np.ndarray | None
    partial_eta2: np.ndarray


@dataclass
class EffectShape:
    """A shape an effect describes, on the mean surface's triangles: a group's mean shape, or
    the shape predicted at a covariate's percentile with every other column at its mean.

    Attributes
    ----------
    name : str
        Its file's stem (``group=level``, ``age_p10``).
    column : str
        The table column.
    label : str
        What it is, in words.
    level : str or None
        The group level (a group's mean).
    offset : float or None
        The covariate's value minus its mean over the used cases (a predicted shape).
    percentile : float or None
        Which percentile of the covariate.
    points : ndarray (p, 3)
        The shape (aligned like the analysis's cases).
    displacement : ndarray (p, 3)
        The change it belongs to: for a group, the level's mean minus the reference level's
        mean (the reference's own: the second level's minus its); for a covariate, the
        prediction at the higher percentile minus that at the lower.
    normal_displacement : ndarray (p,)
        ``displacement`` along the mean surface's outward normals (negative: inward).
    """

    name: str
    column: str
    label: str
    level: str | None
    offset: float | None
    percentile: float | None
    points: np.ndarray
    displacement: np.ndarray
    normal_displacement: np.ndarray


@dataclass
class Analysis:
    """What :func:`analyze_shapes` found. Per-point arrays follow the model's points."""

    config: AnalysisConfig
    subjects: Subjects
    aligned: np.ndarray            # (n, p, 3) the used cases' shapes, aligned
    mean: np.ndarray               # (p, 3) their mean
    normals: np.ndarray            # (p, 3) its outward unit normals
    parts: np.ndarray              # (p,) the part index of each point
    points: PointTest              # the per-point test
    difference: np.ndarray         # (r, p, 3) effect vectors (mm; per unit of a covariate)
    normal_difference: np.ndarray  # (r, p) their components along the normals (negative: inward)
    global_test: GlobalTest
    signed: list                   # SignedMap per effect column (along the normal)
    discriminant: Discriminant | None
    classification: Classification | None
    unusual: Unusual
    scores: np.ndarray | None = None   # (n_cases, k) the principal scores of the global test
    size: SizeTest | None = None       # the effect on centroid size
    effect_sizes: list = field(default_factory=list)   # EffectSize per signed map
    shapes: list = field(default_factory=list)         # EffectShape per group level / percentile
    point_eta2: np.ndarray | None = None   # (p,) partial eta^2 of the per-point test

    def significant(self, correction: str = "fwer") -> np.ndarray:
        """Points significant at ``config.alpha`` after family-wise ("fwer") or FDR ("fdr")
        correction."""
        values = self.points.p_fwer if correction == "fwer" else self.points.q_fdr
        return values <= self.config.alpha


def unusual_cases(model: ShapeModel) -> Unusual:
    """Distances of the model's training cases (p-values against their empirical null, and
    against a training case's own reference distribution under normality) and each case's
    departure from its reconstruction by the same modes."""
    n = len(model.scores)
    k = modes_explaining(model.variances, n_cases=n)
    distances = training_distances(model.scores, model.variances, k)
    full = model.instance(model.scores)
    reconstructed = model.instance(model.scores[:, :k])
    return Unusual(list(model.names), distances, np.linalg.norm(full - reconstructed, axis=2))


def analyze_shapes(model: ShapeModel, shapes: np.ndarray, subjects: Subjects,
                   config: AnalysisConfig | None = None, progress=None) -> Analysis:
    """Test the subjects' effect on the shapes of a model's cases.

    Parameters
    ----------
    model : ShapeModel
        The model (its area weights, triangles or segments, parts, training scores).
    shapes : ndarray (n_s, n_p, 3)
        Every model case's corresponded points in the model's frame, in the model's order
        (unaligned: they are aligned here as ``config.size`` says).
    subjects : Subjects
        Which cases are used and the design (:func:`~.table.subjects`).
    config : AnalysisConfig
    progress : callable, optional
        The library's progress protocol; the permutations report as they go.

    Returns
    -------
    Analysis

    Examples
    --------
    ::

        built = read_build("out")
        design = subjects("subjects.csv", built.model.names, group="diagnosis")
        found = analyze_shapes(built.model, built.shapes, design)
        found.significant("fwer").sum(), found.global_test.p
    """
    config = (config or AnalysisConfig()).validate()
    planar = model.of_curves
    used = np.asarray(shapes, dtype=np.float64)[subjects.indices]
    report(progress, 0.0, "aligning the shapes")
    if config.parts == "each" and len(model.part_sizes) > 1:
        aligned = np.empty_like(used)
        for rows in model.part_slices():
            aligned[:, rows] = align(used[:, rows], model.weights[rows], config.size,
                                     planar, config.superimposition)
    else:
        aligned = align(used, model.weights, config.size, planar, config.superimposition)
    mean = aligned.mean(axis=0)
    normals = vertex_normals(mean, model.triangles, model.part_of_triangles())
    offsets = aligned - mean
    if config.displacement == "normal":
        data = np.einsum("npd,pd->np", offsets, normals)
    else:
        data = offsets[..., :2] if planar else offsets
    surface = surface_of(mean, model.triangles) if config.tfce else None
    points = point_test(data, subjects, config, progress, surface=surface)
    along = data if config.displacement == "normal" else np.einsum("npd,pd->np", offsets,
                                                                    normals)
    report(progress, None, "the signed map of each effect")
    signed = signed_maps(along, subjects, config, points, surface=surface)
    effect_sizes = effects_of(along, subjects, config)
    point_eta2 = None
    if effect_sizes:
        point_eta2 = partial_eta_squared(design_rows(data, subjects), subjects.interest,
                                         subjects.nuisance, not subjects.mean_change_tested)
    difference = _effects(offsets, subjects)
    normal_difference = np.einsum("rpd,pd->rp", difference, normals)
    r = subjects.interest.shape[1]
    z = int(not subjects.mean_change_tested) + subjects.nuisance.shape[1]
    _, _, scores = principal_scores(aligned, model.weights,
                                    max_modes=len(subjects.interest) - z - r - 1)
    report(progress, None, "the effect on size")
    unit = model.weights / model.weights.sum()
    sizes = np.array([centroid_size(x, unit) for x in used])
    size = SizeTest(sizes, _effects(sizes[:, None, None], subjects)[:, 0, 0],
                    point_test(sizes[:, None], subjects, config))
    report(progress, None, "the global test")
    # the global test is pooled: per-group covariances of k scores need more than k cases in
    # every group
    overall = point_test(scores[:, None, :], subjects, config, pooled=True)
    global_test = GlobalTest(scores.shape[1], float(overall.statistic[0]), float(overall.p[0]),
                             config.permutations)
    found_discriminant = found_classification = None
    # the discriminant and the classification describe a tested group, not one adjusted for,
    # of independent cases or of subjects each in one group (whole subjects held out and
    # permuted)
    repeated = subjects.repeated
    if (subjects.groups is not None and subjects.group in subjects.tested
            and (repeated is None or repeated.design == "blocks")):
        if len(subjects.levels) == 2:
            second = np.array([g == subjects.levels[1] for g in subjects.groups])
            found_discriminant = discriminant(aligned, model.weights, second)
        report(progress, None, "the classification")
        found_classification = classify(
            aligned, model.weights, subjects.groups, classification_nuisance(subjects),
            config.folds, config.repeats, config.classification_permutations, config.seed,
            levels=subjects.levels, blocks=None if repeated is None else repeated.blocks,
            progress=progress)
    parts = np.concatenate([np.full(s.stop - s.start, j)
                            for j, s in enumerate(model.part_slices())])
    return Analysis(config, subjects, aligned, mean, normals, parts, points, difference,
                    normal_difference, global_test, signed, found_discriminant,
                    found_classification, unusual_cases(model), scores, size, effect_sizes,
                    effect_shapes(aligned, normals, difference, subjects), point_eta2)


def classification_nuisance(subjects: Subjects) -> np.ndarray:
    """The columns the classification regresses out in each training fold: the nuisance and
    the other tested columns (not the group's own, nor an interaction with it)."""
    other = [k for k, column in enumerate(subjects.interest_columns)
             if subjects.group not in column.split(":")]
    return np.hstack([subjects.nuisance, subjects.interest[:, other]])


def design_rows(per_case: np.ndarray, subjects: Subjects) -> np.ndarray:
    """Per-case values (n_cases, ...) as the design's rows: with two times per subject each
    subject's change (its later case's values minus its baseline case's), else the cases."""
    per_case = np.asarray(per_case)
    repeated = subjects.repeated
    if repeated is None or repeated.design != "change":
        return per_case
    return per_case[repeated.pairs[:, 1]] - per_case[repeated.pairs[:, 0]]


def signed_maps(normal: np.ndarray, subjects: Subjects, config: AnalysisConfig,
                joint: PointTest | None = None, progress=None,
                surface: Surface | None = None) -> list:
    """A signed test along the normal per effect column, each adjusted for the other effect
    columns and the nuisance (with ``config.tail``, one-sided).

    Parameters
    ----------
    normal : ndarray (n_cases, p)
        The used cases' displacements along the mean's normals.
    subjects : Subjects
    config : AnalysisConfig
    joint : PointTest, optional
        The analysis's per-point test: when it is already the signed test of the only effect
        column (one column, the normal displacement), it is the map.
    surface : Surface, optional
        The mean surface's mesh: each map also enhanced by TFCE (:mod:`.tfce`).

    Returns
    -------
    list of SignedMap
    """
    names, columns = subjects.interest_names, subjects.interest_columns
    r = len(names)
    contrasts = contrasts_of(subjects, config)
    if joint is not None and joint.t is not None:
        maps = [SignedMap(names[0], columns[0], joint, True)]
    else:
        maps = [SignedMap(name, column, point_test(normal, _single(subjects, np.eye(r)[j]),
                                                   config, progress, surface=surface), False)
                for j, (name, column) in enumerate(zip(names, columns))]
    for text, coefficients, column, vector in contrasts:
        maps.append(SignedMap(text, column, point_test(normal, _single(subjects, vector), config,
                                                       progress, surface=surface), False,
                              coefficients))
    return maps


def contrasts_of(subjects: Subjects, config: AnalysisConfig) -> list:
    """Each of ``config.contrasts`` as (text, coefficients per level, the tested column, its
    vector over the effect columns); InputError when one names levels that are not tested
    (:func:`~.table.contrast_vector`)."""
    found = []
    for text in config.contrasts:
        coefficients = parse_contrast(text)
        found.append((text, coefficients, *contrast_vector(subjects, text, coefficients)))
    return found


def _single(subjects: Subjects, vector: np.ndarray) -> Subjects:
    """The design reparameterised so that one effect column carries c'b (Smith et al. 2007;
    Winkler et al. 2014): X c / (c'c) tested, X Q adjusted for (Q an orthonormal basis of the
    coefficients orthogonal to c), the model's span unchanged."""
    interest = subjects.interest
    basis = np.linalg.svd(np.eye(len(vector)) - np.outer(vector, vector) / (vector @ vector))[0]
    complement = basis[:, :len(vector) - 1]
    return replace(subjects, interest=interest @ vector[:, None] / (vector @ vector),
                   nuisance=np.hstack([subjects.nuisance, interest @ complement]))


def point_test(per_case: np.ndarray, subjects: Subjects, config: AnalysisConfig,
               progress=None, pooled: bool = False, surface: Surface | None = None
               ) -> PointTest:
    """The per-point test of a design on per-case data, resampled as the design allows.

    Independent cases: permutations (sign flips and permutations within the groups with
    variance groups). Two times per subject: the test on each subject's change
    (:func:`design_rows`); of the mean change (nothing else tested) with no intercept,
    by sign flips (Winkler et al. 2014, independent and symmetric errors). More times: the
    effect of time with each subject adjusted for, permuted within subjects (exchangeability
    blocks). Subjects without times: the subjects' columns on all their cases, whole subjects
    permuted (the pooled statistic).

    Parameters
    ----------
    per_case : ndarray (n_cases, p) or (n_cases, p, q)
        The data of the used cases, in :attr:`~.table.Subjects.cases` order.
    subjects : Subjects
    config : AnalysisConfig
        Permutations, seed, variance, family-wise correction and tail (one-sided only where
        there is one effect column and one number per point).
    pooled : bool
        Use the pooled statistic whatever ``config.variance`` says (the global test).
    surface : Surface, optional
        The points' mesh: the map also enhanced by TFCE and tested by its maximum.

    Returns
    -------
    PointTest
    """
    data = design_rows(per_case, subjects)
    single = subjects.interest.shape[1] == 1 and (data.ndim == 2 or data.shape[2] == 1)
    repeated = subjects.repeated
    return permutation_test(
        data, subjects.interest, subjects.nuisance, config.permutations, config.seed, progress,
        variance_groups=(subjects.groups if config.variance_groups() and not pooled else None),
        family_wise=config.family_wise, intercept=not subjects.mean_change_tested,
        flips=subjects.mean_change_tested,
        blocks=repeated.blocks if repeated is not None else None,
        whole_blocks=repeated is not None and repeated.design == "blocks",
        tail=config.tail if single and not pooled else "both", surface=surface)


def _effects(offsets: np.ndarray, subjects: Subjects) -> np.ndarray:
    """The effect columns' least-squares coefficients on the point coordinates (r, p, 3),
    adjusted for the nuisance (for the mean change: the mean change at the nuisance's mean)."""
    rows = design_rows(offsets, subjects)
    n, p, d = rows.shape
    columns = [subjects.nuisance, subjects.interest]
    if not subjects.mean_change_tested:
        columns.insert(0, np.ones((n, 1)))
    coefficients, *_ = np.linalg.lstsq(np.hstack(columns), rows.reshape(n, -1), rcond=None)
    r = subjects.interest.shape[1]
    return coefficients[-r:].reshape(r, p, d)


def effects_of(normal: np.ndarray, subjects: Subjects, config: AnalysisConfig) -> list:
    """The :class:`EffectSize` of each signed map (in :func:`signed_maps`' order): the
    confidence interval at level 1 - ``config.alpha`` (Welch-Satterthwaite with variance groups,
    else Student's), Cohen's d and partial eta^2. None for a design that exchanges whole
    subjects (its cases are not independent): an empty list.

    Parameters
    ----------
    normal : ndarray (n_cases, p)
        The used cases' displacements along the mean's normals.
    subjects : Subjects
    config : AnalysisConfig
    """
    repeated = subjects.repeated
    if repeated is not None and repeated.design == "blocks":
        return []
    data = design_rows(normal, subjects)
    names = subjects.interest_names
    r = len(names)
    intercept = not subjects.mean_change_tested
    codes = None
    if config.variance_groups():
        codes = np.array([subjects.levels.index(g) for g in subjects.groups])
    vectors = [(name, np.eye(r)[j], _compared(subjects, j))
               for j, name in enumerate(names)]
    vectors += [(text, vector, _contrasted(subjects, coefficients, column))
                for text, coefficients, column, vector in contrasts_of(subjects, config)]
    found = []
    for name, vector, compared in vectors:
        single = _single(subjects, vector)
        bounds = interval(data, subjects.interest, vector, subjects.nuisance, intercept, codes,
                          1.0 - config.alpha)
        d = None if compared is False else cohens_d(bounds, compared)
        found.append(EffectSize(name, bounds, d, partial_eta_squared(
            data, single.interest, single.nuisance, intercept)))
    return found


def _compared(subjects: Subjects, column: int):
    """Which variance groups effect column ``column`` compares, for Cohen's d: (reference,
    level) codes for a level of the group; None (the pooled SD) for a level of another
    categorical column or the mean change; False for a covariate or an interaction (no d)."""
    source = subjects.interest_columns[column]
    if subjects.mean_change_tested:
        return None
    if ":" in source or source not in subjects.levels_of:
        return False
    if source != subjects.group:
        return None
    first = subjects.interest_columns.index(source)
    return (0, 1 + column - first)


def _contrasted(subjects: Subjects, coefficients: dict, column: str):
    """Which variance groups a contrast compares, for Cohen's d, as :func:`_compared`: a
    difference of two levels (coefficients +1 and -1) of the group, their codes (the level
    subtracted first); of another categorical column, None (the pooled SD); any other
    combination, False (no d)."""
    if sorted(coefficients.values()) != [-1.0, 1.0]:
        return False
    if column != subjects.group:
        return None
    return tuple(subjects.levels.index(level)
                 for level in sorted(coefficients, key=coefficients.get))


def effect_shapes(aligned: np.ndarray, normals: np.ndarray, difference: np.ndarray,
                  subjects: Subjects) -> list:
    """The shapes the tested effects describe (:class:`EffectShape`), for independent cases:
    each level's mean shape of a tested group, and the shapes predicted at a tested covariate's
    percentiles (:data:`~.effects.PREDICTED_AT`) with every other column at its mean. None for
    repeated measures (an empty list).

    Parameters
    ----------
    aligned : ndarray (n_cases, p, 3)
        The used cases, superimposed as the analysis does.
    normals : ndarray (p, 3)
        The mean surface's outward normals.
    difference : ndarray (r, p, 3)
        The effect columns' coefficients on the coordinates (:attr:`Analysis.difference`).
    subjects : Subjects
    """
    if subjects.repeated is not None:
        return []
    shapes = []
    if subjects.group is not None and subjects.group in subjects.tested:
        groups = np.array(subjects.groups)
        means = [aligned[groups == level].mean(axis=0) for level in subjects.levels]
        for k, (level, mean) in enumerate(zip(subjects.levels, means)):
            other = means[1] if k == 0 else mean
            change = other - means[0]
            shapes.append(EffectShape(
                f"{subjects.group}={level}", subjects.group,
                f"mean shape of {subjects.group} {level} ({int(np.sum(groups == level))} cases)",
                level, None, None, mean, change, np.einsum("pd,pd->p", change, normals)))
    centre = aligned.mean(axis=0)
    for j, source in enumerate(subjects.interest_columns):
        if ":" in source or source in subjects.levels_of:
            continue
        offsets = predicted_offsets(subjects.interest[:, j])
        change = (offsets[-1] - offsets[0]) * difference[j]
        normal = np.einsum("pd,pd->p", change, normals)
        for percentile, offset in zip(PREDICTED_AT, offsets):
            shapes.append(EffectShape(
                f"{source}_p{percentile:g}", source,
                f"predicted at the {percentile:g}th percentile of {source}", None,
                float(offset), percentile, centre + offset * difference[j], change, normal))
    return shapes
