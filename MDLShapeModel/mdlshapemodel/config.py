"""One configuration object for every knob, with the paper's defaults (Table I).

The command line, the VTK filters and the Slicer panel all fill a :class:`BuildConfig`; ``validate``
names the field at fault. This module is a leaf: it imports nothing heavier than the standard
library, so a panel that only fills a configuration loads neither VTK, numba nor the optimiser.
"""

from __future__ import annotations

import math
import os
import re
import typing
from dataclasses import asdict, dataclass, field, fields

from .errors import ConfigError

# Names of the optimisation strategies (section III-D; ``fast`` is ours, ``none`` keeps the initial
# correspondence). The functions are registered under these names in
# ``mdlshapemodel.correspondence.strategies``; a test checks that both lists agree.
STRATEGIES = ("none", "one-at-a-time", "one-at-a-time-pose", "multiresolution", "multiscale",
              "fast")
# Warp kinds a one-at-a-time step can draw: the symmetric theta kernel (III-A), the Appendix's
# asymmetric theta transformation and shear/twist, and a global rotation of the parameter sphere.
WARPS = ("symmetric", "asymmetric", "shear", "rotation")
WARP_STRATEGIES = ("one-at-a-time", "one-at-a-time-pose")
CORRESPONDENCES = ("mdl", "cpd")
BASELINES = ("none", "cpd")
PLACEMENTS = ("sphere", "surface")
# The precision of the fast strategy's quasi-Newton curvature pairs (``--curvature-pairs``;
# correspondence/strategies/quasi_newton.py): "auto" keeps them in single precision in rounds of
# at least SINGLE_PRECISION_PAIRS_FROM variables, in double below.
CURVATURE_PAIRS = ("auto", "double", "single")
# A round's ten pairs of two vectors in double precision take 160 bytes per variable: 640 MB at
# this many variables (about 2,000 surfaces at the finest field level, 1,930 coefficients each).
# Below it a build keeps exact double-precision pairs; above it the pairs are the largest
# holder of a round's memory, and single precision halves them.
SINGLE_PRECISION_PAIRS_FROM = 4_000_000
# A build of at least this many cases ends its helper process once the baselines are evaluated
# (build.py): the idle process holds 0.2-0.3 GB, which matters beside a build of several GB; a
# smaller build keeps it, and saves the second or two a fresh one takes to start for the
# model's evaluation.
HELPER_RESTS_FROM = 1000
SURFACE_METHODS = ("gaussian", "slicer")


@dataclass
class OptimisationSettings:
    """The optimiser's knobs (filled from the build configuration by
    :meth:`BuildConfig.optimisation_settings`)."""

    strategy: str = "one-at-a-time-pose"
    sigma_g: float = 1.0 / 32.0
    max_amplitude: float = 1.0
    max_time: float = 600.0
    fixed_fraction: float = 0.7
    tolerance: float = 0.001
    patience: int = 3
    max_sweeps: int = 10_000
    pose_evaluations: int = 80
    # threads for the per-example loops of an evaluation (the fast strategy's field sampling and
    # its chain rule); the result does not depend on it (``BuildConfig.workers``)
    threads: int = 1
    # the fast strategy: coarse-to-fine passes over its field levels at most; another pass only
    # while the last one gained more than ``tolerance`` of the phase's gain. A second pass lets
    # the coarse levels move again after the fine ones have, which brings the correspondence
    # closer to a population's known truth (docs/benchmarks.md)
    field_passes: int = 2
    # the fast strategy: quasi-Newton iterations per round at most. Each round ends with a rebuild
    # (area weights of the new mean, the next fields centred where the points are then): shorter
    # rounds reach lower G and S in fewer evaluations (benchmarks/fast_variants.py, iterationsN)
    round_iterations: int = 15
    # the fast strategy's coarse grid (correspondence/coarse.py): both objectives on this many
    # sample points per part (an icosphere: 10 * 4**k + 2), and the maps then carried over to
    # the build's own points; 0, or a build with no more points than this, optimises on the
    # build's points. There the fixed-Delta phase makes ``coarse_passes`` passes over the field
    # levels and the full objective's phase one (further passes lower eq. 14 but not G or S:
    # benchmarks/fast_variants.py, integrated1)
    coarse_points: int = 642
    coarse_passes: int = 3
    # the fast strategy: the precision of the quasi-Newton curvature pairs (CURVATURE_PAIRS)
    curvature_pairs: str = "auto"
    # the simplex strategies (III-D1, III-D2)
    omega_1: float = 0.25          # multiresolution: width of the level-0 kernels (Table I)
    max_levels: int = 4            # multiresolution: levels per phase (12, 30, 120, 480 kernels)
    simplex_step: float = 0.25     # initial simplex edge, as a fraction of each kernel's A_max
    simplex_evaluations: int = 0   # evaluations per simplex run; 0: 200 x its parameters
    # trace a row whenever a trial inside a step beats the best F so far (not only after each
    # example / iteration): convergence curves at the resolution of single evaluations
    trace_improvements: bool = False
    # the one-at-a-time strategies: warp kinds drawn (uniformly) per step
    warps: tuple = ("symmetric",)
    max_angle: float = math.pi / 4  # largest rotation, and peak shear/twist angle, of one step
    shear_sigma: float = 0.25      # shear/twist band widths c: positive half of N(0, this)


# Unless set, the largest blur of a mask whose surface is not genus 0 is the larger of this and
# the first blur: ``BuildConfig.max_smoothing_sigma``, voxels.
MAX_SMOOTHING_SIGMA = 2.0


# Unless set (``BuildConfig.points``), the sample points of each part: on the sphere for a
# surface (an icosphere of 2562 vertices), on the circle for a 2-D curve (128).
SURFACE_POINTS = 2562
CURVE_POINTS = 128

# ``--placement``: where a surface's sample points lie (correspondence/placement.py): evenly over
# the population's mean surface, so that the landmarks' distance from the corresponded surface
# falls where sphere maps squeeze the anatomy (docs/benchmarks.md)
PLACEMENT = "surface"

# ``--landmark-weight``: lambda of the landmark guides' term (correspondence/guides.py), nats per
# squared voxel of distance between a landmark and its corresponded point, halved
LANDMARK_WEIGHT = 10.0

# ``--check-landmarks``: with at most this many labels guiding, each is left out of the guides
# in a fold of its own (one optimisation per label); with more, the labels are dealt in turn
# (in sorted order) to this many folds, so that the check costs at most this many optimisations
LANDMARK_CHECK_FOLDS = 6

# ``--smoothness``: w of the prior on smooth correspondence of surfaces
# (correspondence/smoothness.py); 0: none. The default is the weight that brings the benchmark
# populations' correspondence closest to their known truth and expert landmarks while the
# hippocampi's generalization and specificity (modes 1-10) stay within 5 % of those of the model
# without the prior (docs/benchmarks.md). 2-D curves have no prior.
SMOOTHNESS = 0.01

# ``--smoothness`` where landmarks guide the correspondence: the guides hold the correspondence
# at the experts' places and the prior makes it a smooth deformation between them. The default
# is the weight past which doubling it brings held-out expert landmarks less than 5 % closer
# (docs/benchmarks.md, "Landmarks as guides").
GUIDED_SMOOTHNESS = 0.04

# Unless set, the surfaces mapped to the sphere have about this many vertices per sample point,
# and at least MIN_SURFACE_VERTICES: ``BuildConfig.target_vertices``. A surface many times finer
# than the sampling grid buys nothing and costs time.
SURFACE_VERTICES_PER_POINT = 2
MIN_SURFACE_VERTICES = 5000

# The largest inputs: a file whose header claims more is rejected, with its size, before anything
# is allocated for it (a header of a few bytes can claim 10^15 voxels). The bounds are what
# preparing one input may take of MEMORY_BUDGET, at the peak memory measured per voxel of a label
# map (17 bytes for 8-bit labels, 22 for 32-bit, 33 for 64-bit floats: the mask, its components
# and the blur are images of the same size) and per point of a mesh (1.6 kB: cleaning, topology
# and remeshing). One input is prepared per worker process (--workers).
MEMORY_BUDGET = 16 * 2**30
PREPARATION_BYTES_PER_VOXEL = 36
PREPARATION_BYTES_PER_MESH_POINT = 1600
MAX_VOXELS = MEMORY_BUDGET // PREPARATION_BYTES_PER_VOXEL               # 477,218,588
MAX_MESH_POINTS = MEMORY_BUDGET // PREPARATION_BYTES_PER_MESH_POINT     # 10,737,418
# Without --label, an image of more distinct non-zero values than this is not a label map but an
# intensity image (a CT's or an MR's hundreds to thousands of grey values): its non-zero voxels
# would make the image's box the object. An 8-bit label map holds at most 255 labels.
MAX_LABEL_VALUES = 255

# Two cases are one case given twice (refused unless ``BuildConfig.allow_duplicates``) when their
# files are identical, or when their shapes in the initial correspondence, each moved to its
# centroid, are closer than this share of the shape's size: the area-weighted RMS distance of
# their corresponded points over the RMS distance of the points from their centroid. A copy
# re-saved, converted or moved lies at about 0, one with a voxel changed below it; different
# subjects lie 30 times further apart or more, and the closest of 60 synthetic subjects of the
# demo (two shape parameters) 5 times (docs/inputs.md, "A case given twice").
DUPLICATE_DISTANCE = 0.001

# The largest coordinate (mm) of an input: a mesh's points, a label map's corners. 1,000 km is no
# anatomy; beyond about 1e154 squared distances overflow (a point at 1e308 broke the k-d tree).
MAX_COORDINATE = 1e9


def target_vertices_for(points: int) -> int:
    """The vertices of the surfaces that are mapped to the sphere, unless set: the larger of
    :data:`MIN_SURFACE_VERTICES` and :data:`SURFACE_VERTICES_PER_POINT` per sample point."""
    return max(MIN_SURFACE_VERTICES, SURFACE_VERTICES_PER_POINT * points)


def max_smoothing_for(smoothing_sigma: float) -> float:
    """The largest blur of a mask whose surface is not genus 0, unless set: the larger of
    :data:`MAX_SMOOTHING_SIGMA` and the first blur (voxels)."""
    return max(MAX_SMOOTHING_SIGMA, smoothing_sigma)


def parse_items(text: str, kind: type = str, item: str = "value", choices=None,
                nonempty: bool = False) -> list:
    """The items of a list setting written as text, separated by commas or spaces (``"1, 2"``),
    each converted to ``kind`` and checked against ``choices``. The one parser of list settings
    for every face (the command line's list options, the Slicer panel's text fields).

    Raises :class:`ConfigError` with a one-line message (``"unknown warp kind 'twirl'; choose
    from ..."``, ``"labels must be integers, got 'a'"``).

    Examples
    --------
    >>> parse_items("1, 2", int, "label")
    [1, 2]
    """
    kind_name = {int: "integers", float: "numbers"}.get(kind, "values")
    try:
        values = [kind(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise ConfigError(f"{item}s must be {kind_name}, got {text!r}") from None
    unknown = [v for v in values if choices is not None and v not in choices]
    if unknown or (nonempty and not values):
        problem = f"unknown {item} {unknown[0]!r}" if unknown else f"no {item} given"
        suffix = f"; choose from {', '.join(choices)}" if choices is not None else ""
        raise ConfigError(problem + suffix)
    return values


@dataclass(frozen=True)
class PartSpec:
    """One part of a multi-part object (``BuildConfig.parts``): its name and the labels whose
    union it is (empty: the build's ``labels``, e.g. a part given by its own files)."""

    name: str
    labels: tuple = ()


def parse_part(text: str) -> PartSpec:
    """A part written as ``NAME=LABELS`` (``head=1``, ``tail=2,3``) or ``NAME`` alone (the build's
    labels, for parts that have files of their own). Names are letters, digits, ``_`` and ``-``
    (they become folder names of the outputs).

    Raises :class:`ConfigError` with a one-line message.

    Examples
    --------
    >>> parse_part("tail=2, 3")
    PartSpec(name='tail', labels=(2, 3))
    """
    name, _, labels = str(text).partition("=")
    name = name.strip()
    if not name or not all(c.isalnum() or c in "_-" for c in name) or name.startswith("-"):
        raise ConfigError(f"part {text!r}: a part is NAME=LABELS, its name of letters, digits, "
                          "'_' and '-' (e.g. head=1)")
    try:
        values = parse_items(labels, int, "label") if labels.strip() else []
    except ConfigError as error:
        raise ConfigError(f"part {text!r}: {error}") from None
    if any(v <= 0 for v in values):
        raise ConfigError(f"part {text!r}: label values must be positive integers")
    return PartSpec(name, tuple(values))


def split_parts(text: str) -> list:
    """The parts of ``parts`` written as one text, ``"head=1; tail=2, 3"`` (separated by ';',
    or by commas or spaces before the next ``NAME=``), each checked by :func:`parse_part`.

    Examples
    --------
    >>> split_parts("head=1, tail=2,3")
    ['head=1', 'tail=2,3']
    """
    items = [item.strip() for item in
             re.split(r";|[,\s]+(?=[A-Za-z0-9_][A-Za-z0-9_-]*\s*=)", text) if item.strip()]
    for item in items:
        parse_part(item)
    return items


def field_items(name: str, text: str) -> list:
    """The value of :class:`BuildConfig`'s list field ``name`` written as text (see
    :func:`parse_items`, or :func:`split_parts` for ``parts``; its item kind, noun and choices
    are the field's). A bad item raises :class:`ConfigError` naming it, its ``setting``
    ``name``."""
    try:
        if name == "parts":
            return split_parts(text)
        f = next(f for f in fields(BuildConfig) if f.name == name)
        (kind,) = typing.get_args(typing.get_type_hints(BuildConfig)[name])
        metadata = f.metadata
        return parse_items(text, kind, metadata.get("item", "value"), metadata.get("choices"),
                           metadata.get("nonempty", False))
    except ConfigError as error:
        raise ConfigError(str(error), setting=name) from None


def rule(choices: tuple | None = None, item: str | None = None, nonempty: bool = False) -> dict:
    """The metadata of a :class:`BuildConfig` field whose values are checked by rule, read by
    every face that parses the setting from text (:func:`field_items`, the command line).

    Parameters
    ----------
    choices : tuple, optional
        The allowed values (of each item, for a list field).
    item : str, optional
        List fields: what one item is, for messages ("unknown warp kind ...").
    nonempty : bool
        List fields: at least one item.
    """
    metadata = {"choices": choices, "item": item, "nonempty": nonempty or None}
    return {key: value for key, value in metadata.items() if value is not None}


@dataclass
class BuildConfig:
    """Settings of a model build. Lengths marked *voxels* are in voxels of the source images.

    Each field's type, default and check (:meth:`validate`) are defined here once; a field whose
    values are limited to choices or list items carries its :func:`rule` in ``field.metadata``.
    The faces offer the fields under their own names (the command line's ``build`` options:
    :mod:`mdlshapemodel.options`).

    One rule joins two fields: ``max_smoothing_sigma`` left None becomes
    max(:data:`MAX_SMOOTHING_SIGMA`, ``smoothing_sigma``) on construction (so
    ``dataclasses.replace`` keeps the value it became; pass None again to apply the rule anew).
    """

    # inputs
    labels: list[int] = field(default_factory=list, metadata=rule(item="label"))
    parts: list[str] = field(default_factory=list, metadata=rule(item="part"))
    voxel_size: float | None = None
    mirror: list[str] = field(default_factory=list, metadata=rule(item="pattern"))
    allow_duplicates: bool = False
    # surfaces and sphere maps
    surface_method: str = field(default="gaussian", metadata=rule(choices=SURFACE_METHODS))
    smoothing_factor: float = 0.5
    decimation: float = 0.0
    smoothing_sigma: float = 1.0
    # None: MAX_SMOOTHING_SIGMA or smoothing_sigma, whichever is larger (set on construction)
    max_smoothing_sigma: float | None = None
    edge_length: float = 1.0
    # None: target_vertices_for(points) (set on construction)
    target_vertices: int | None = None
    # correspondence
    correspondence: str = field(default="mdl", metadata=rule(choices=CORRESPONDENCES))
    baselines: list[str] = field(default_factory=lambda: ["none"],
                                 metadata=rule(choices=BASELINES, item="baseline"))
    # None: SURFACE_POINTS on surfaces, CURVE_POINTS on 2-D curves (points_for)
    points: int | None = None  # n_p
    placement: str = field(default=PLACEMENT, metadata=rule(choices=PLACEMENTS))
    # optimisation: our gradient strategy by default (the paper's four remain selectable); the
    # other defaults are those of OptimisationSettings (one source)
    strategy: str = field(default="fast", metadata=rule(choices=STRATEGIES))
    warps: list[str] = field(default_factory=lambda: list(OptimisationSettings.warps),
                             metadata=rule(choices=WARPS, item="warp kind", nonempty=True))
    scaling: bool = True  # Procrustes removes scale
    # [Delta_min, Delta_max] of eq. 14 (Table I); fixed_delta: Delta of eq. 13; sigma_g (Table I)
    delta_range: tuple[float, float] = (1e-4, 0.5)
    fixed_delta: float = 0.1
    sigma_g: float = OptimisationSettings.sigma_g
    max_amplitude: float = OptimisationSettings.max_amplitude  # the bound of an amplitude A
    max_time: float = OptimisationSettings.max_time
    fixed_fraction: float = OptimisationSettings.fixed_fraction
    tolerance: float = OptimisationSettings.tolerance
    max_sweeps: int = OptimisationSettings.max_sweeps
    coarse_points: int = OptimisationSettings.coarse_points
    curvature_pairs: str = field(default=OptimisationSettings.curvature_pairs,
                                 metadata=rule(choices=CURVATURE_PAIRS))
    landmarks: str | None = None
    landmark_weight: float = LANDMARK_WEIGHT
    check_landmarks: bool = False
    # None: SMOOTHNESS on surfaces (GUIDED_SMOOTHNESS with guides), none on 2-D curves
    # (smoothness_for)
    smoothness: float | None = None
    seed: int = 0
    # evaluation
    evaluation_modes: int = 10
    specificity_samples: int = 10_000
    surface_samples: int = 200
    # beyond this many cases, the generalization leaves out a random subset of this many
    # (model.evaluation.leave_out_cases): its cost then stops growing as n_s^2
    generalization_cases: int = 500
    # running
    workers: int = field(default_factory=lambda: os.cpu_count() or 1)
    # None: the per-case work runs here (``workers``)
    scheduler: str | None = None
    # per-case preprocessing cache; None: the default place, "": none
    cache_dir: str | None = None
    strict: bool = False

    def __post_init__(self):
        # the rules between fields: unless set, the blur may rise to MAX_SMOOTHING_SIGMA,
        # or stays at smoothing_sigma when that is larger
        if self.max_smoothing_sigma is None and isinstance(self.smoothing_sigma, (int, float)):
            self.max_smoothing_sigma = max_smoothing_for(self.smoothing_sigma)
        # and unless set, the surfaces are about as fine as the sampling grid needs
        if self.target_vertices is None and isinstance(self.points, (int, type(None))):
            self.target_vertices = target_vertices_for(self.points_for(curves=False))

    def validate(self) -> "BuildConfig":
        """Raise :class:`ConfigError` naming the first bad field; return self."""
        def need(condition: bool, name: str, text: str):
            if not condition:
                problem = f"{text} (got {getattr(self, name)!r})"
                raise ConfigError(f"{name}: {problem}", setting=name, problem=problem)

        need(all(isinstance(v, int) and v > 0 for v in self.labels), "labels",
             "label values must be positive integers")
        try:
            names = [part.name for part in self.part_specs()]
        except ConfigError as error:
            raise ConfigError(f"parts: {error}", setting="parts", problem=str(error)) from None
        need(len(set(names)) == len(names), "parts", "part names must differ")
        need(self.voxel_size is None or self.voxel_size > 0, "voxel_size", "must be positive")
        need(self.surface_method in SURFACE_METHODS, "surface_method",
             f"must be one of {', '.join(SURFACE_METHODS)}")
        need(0 <= self.smoothing_factor <= 1, "smoothing_factor", "must be between 0 and 1")
        need(0 <= self.decimation < 1, "decimation", "must be in [0, 1)")
        need(self.smoothing_sigma >= 0, "smoothing_sigma", "must be >= 0")
        need(self.max_smoothing_sigma is not None
             and self.max_smoothing_sigma >= self.smoothing_sigma, "max_smoothing_sigma",
             "must be >= smoothing_sigma")
        need(self.edge_length > 0, "edge_length", "must be positive")
        need(self.target_vertices >= 100, "target_vertices", "must be at least 100")
        need(self.correspondence in CORRESPONDENCES, "correspondence",
             f"must be one of {', '.join(CORRESPONDENCES)}")
        need(all(b in BASELINES for b in self.baselines), "baselines",
             f"each must be one of {', '.join(BASELINES)}")
        need(self.points is None or self.points >= 12, "points", "must be at least 12")
        need(self.strategy in STRATEGIES, "strategy", f"must be one of {', '.join(STRATEGIES)}")
        need(self.placement in PLACEMENTS, "placement",
             f"must be one of {', '.join(PLACEMENTS)}")
        need(isinstance(self.warps, (list, tuple)) and len(self.warps) > 0
             and all(w in WARPS for w in self.warps) and len(set(self.warps)) == len(self.warps),
             "warps", f"must be distinct kinds from {', '.join(WARPS)}")
        need(list(self.warps) == ["symmetric"] or self.strategy in WARP_STRATEGIES, "warps",
             f"kinds other than symmetric need the strategy {' or '.join(WARP_STRATEGIES)}")
        need(len(self.delta_range) == 2 and 0 < self.delta_range[0] < self.delta_range[1],
             "delta_range", "must be two numbers 0 < min < max")
        need(self.fixed_delta > 0, "fixed_delta", "must be positive")
        need(self.sigma_g > 0, "sigma_g", "must be positive")
        need(self.max_amplitude > 0, "max_amplitude", "must be positive")
        need(self.max_time >= 0, "max_time", "must be >= 0")
        need(0 <= self.fixed_fraction <= 1, "fixed_fraction", "must be between 0 and 1")
        need(0 < self.tolerance < 1, "tolerance", "must be between 0 and 1")
        need(self.max_sweeps >= 1, "max_sweeps", "must be at least 1")
        need(self.coarse_points == 0 or self.coarse_points >= 12, "coarse_points",
             "must be 0 (no coarse stage) or at least 12")
        need(self.curvature_pairs in CURVATURE_PAIRS, "curvature_pairs",
             f"must be one of {', '.join(CURVATURE_PAIRS)}")
        need(self.landmarks is None or (isinstance(self.landmarks, str)
                                        and self.landmarks.strip() != ""),
             "landmarks", "must be a folder of landmark files")
        need(self.landmark_weight >= 0, "landmark_weight", "must be >= 0")
        need(not self.check_landmarks or self.landmarks is not None, "check_landmarks",
             "needs --landmarks (the folder of the landmarks to check)")
        need(self.smoothness is None or self.smoothness >= 0, "smoothness", "must be >= 0")
        need(self.evaluation_modes >= 1, "evaluation_modes", "must be at least 1")
        need(self.specificity_samples >= 2, "specificity_samples", "must be at least 2")
        need(self.surface_samples == 0 or self.surface_samples >= 2, "surface_samples",
             "must be 0 (none) or at least 2")
        need(self.generalization_cases >= 2, "generalization_cases", "must be at least 2")
        need(self.workers >= 1, "workers", "must be at least 1")
        need(self.scheduler is None or (isinstance(self.scheduler, str)
                                        and self.scheduler.strip() != ""),
             "scheduler", "must be a Dask scheduler's address, e.g. tcp://127.0.0.1:8786")
        return self

    def landmarks_guide(self, given: bool | None = None) -> bool:
        """Whether landmarks guide the correspondence: given (``given``; by default, whether
        ``landmarks`` names a folder) and a positive ``landmark_weight``; with 0 they only
        measure it (:meth:`checks_landmarks`)."""
        return (self.landmarks is not None if given is None else given) \
            and self.landmark_weight > 0

    def checks_landmarks(self) -> bool:
        """Whether the build measures how far its correspondence carries the landmarks where
        they do not guide it: asked for (``check_landmarks``), or landmarks given only to be
        measured (``landmark_weight`` 0, which costs no optimisation)."""
        return self.landmarks is not None and (self.check_landmarks
                                               or not self.landmarks_guide())

    def landmark_folds(self, labels) -> list[tuple]:
        """The labels left out of the guides in each fold of the landmark check: one label per
        fold up to :data:`LANDMARK_CHECK_FOLDS` labels, else the sorted labels dealt in turn to
        that many folds. None where nothing is guided (``landmark_weight`` 0, or the CPD
        correspondence, which follows no guides): the build itself then measures every label.
        """
        labels = sorted(labels)
        if not labels or not self.landmarks_guide(True) or self.correspondence == "cpd":
            return []
        folds = min(len(labels), LANDMARK_CHECK_FOLDS)
        return [tuple(labels[k::folds]) for k in range(folds)]

    def points_for(self, curves: bool) -> int:
        """The sample points of each part: ``points``, or unless set :data:`CURVE_POINTS` for
        2-D curves and :data:`SURFACE_POINTS` for surfaces."""
        if self.points is not None:
            return self.points
        return CURVE_POINTS if curves else SURFACE_POINTS

    def smoothness_for(self, curves: bool, guided: bool = False) -> float:
        """The weight of the prior on smooth correspondence: ``smoothness``, or unless set 0
        (none) for 2-D curves, :data:`GUIDED_SMOOTHNESS` for surfaces whose correspondence
        landmarks guide (``guided``) and :data:`SMOOTHNESS` for other surfaces."""
        if self.smoothness is not None:
            return self.smoothness
        if curves:
            return 0.0
        return GUIDED_SMOOTHNESS if guided else SMOOTHNESS

    def part_specs(self) -> list[PartSpec]:
        """The parts of ``parts`` (:func:`parse_part`); none for a one-part object."""
        return [parse_part(text) for text in self.parts]

    def optimisation_settings(self) -> OptimisationSettings:
        """The optimiser's settings of this build."""
        return OptimisationSettings(strategy=self.strategy, sigma_g=self.sigma_g,
                                    max_amplitude=self.max_amplitude, max_time=self.max_time,
                                    fixed_fraction=self.fixed_fraction,
                                    tolerance=self.tolerance, max_sweeps=self.max_sweeps,
                                    coarse_points=self.coarse_points,
                                    curvature_pairs=self.curvature_pairs,
                                    warps=tuple(self.warps), threads=self.workers)

    def to_dict(self) -> dict:
        data = asdict(self)
        data["delta_range"] = list(self.delta_range)
        return data

    @classmethod
    def from_dict(cls, data: dict) -> "BuildConfig":
        names = {f.name for f in fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ConfigError(f"{sorted(unknown)[0]}: unknown setting")
        values = dict(data)
        if "delta_range" in values:
            values["delta_range"] = tuple(values["delta_range"])
        return cls(**values).validate()


# What the analysis tests at each point: the displacement along the mean surface's outward
# normal (one number; a correspondence that slides along the surface does not change it), or the
# displacement vector (Hotelling's T^2 of 3 numbers, 2 for 2-D curves).
DISPLACEMENTS = ("normal", "vector")
# How the analysis aligns the shapes: size kept (rigid; a loss of volume shows) or removed
# (each scaled to the mean centroid size first).
ANALYSIS_SIZES = ("kept", "removed")
# How the analysis superimposes the shapes: least-squares generalized Procrustes (every point
# pulls on a case's pose by its squared residual) or resistant (iteratively reweighted, a
# biweight of each point's residual, so that a local change moves the poses little; the
# default, as it found planted local changes with fewer far findings and kept the level).
SUPERIMPOSITIONS = ("least-squares", "resistant")
# The per-point statistic of a group comparison: one covariance per group ("groups": Welch's v or
# G, James' statistic for the vector displacement; valid when the groups differ in variance and
# size) or one pooled covariance for all cases ("pooled": Student's t, the F, Pillai's trace or
# Hotelling's T^2, which assume equal covariances). Covariates are always tested pooled.
VARIANCES = ("groups", "pooled")
# The family-wise correction over the points: the maximum of the per-point statistic (pivotal:
# the same null distribution at every point under normal errors) or min-p (the smallest
# per-point p; no point dominates whatever its tails, but it needs permutations well above the
# number of points / alpha)
FAMILY_WISE = ("maximum", "min-p")
# The alternative of a test of one effect column: two-sided, or one-sided towards a positive
# ("greater") or a negative ("less": an inward displacement, atrophy) effect.
TAILS = ("both", "greater", "less")
# Threshold-free cluster enhancement of a per-point map over the mean surface (``--tfce``; Smith
# and Nichols 2009): TFCE(v) = sum over the heights h = dh, 2 dh, ... up to the point's own of
# e(h)^E h^H dh, e(h) the area (mm^2; the length of a curve, mm) of the connected region above h
# that holds the point. E = 1, H = 2 as is usual on surfaces; dh in units of the enhanced map (a
# t or z value). Heights are clipped at TFCE_LEVELS steps.
TFCE_EXTENT = 1.0
TFCE_HEIGHT = 2.0
TFCE_STEP = 0.1
TFCE_LEVELS = 100_000
# How the analysis aligns a multi-part object: as one (the parts' relative positions count) or
# each part on its own (only each part's own shape counts).
PART_ALIGNMENTS = ("whole", "each")


@dataclass
class Roles:
    """What each column of an analysis's model is: :func:`analysis_roles`."""

    tested: list          # the columns whose effect is tested
    adjusted_for: list    # the other columns of the model (nuisance)
    categorical: list     # the model's categorical columns (coded as indicators of levels)
    numeric: list         # the model's numeric columns
    interactions: list = field(default_factory=list)   # tested products, "a:b"


def parse_contrast(text: str) -> dict:
    """The levels and coefficients of a contrast written as text: level names joined by ``+``
    and ``-``, each with an optional coefficient (``2*level``); the coefficients must add up to
    0 (a comparison of levels, not of their overall mean). Levels whose names hold ``+``, ``-``
    or ``*`` cannot be written.

    Raises :class:`ConfigError` with a one-line message naming the contrast.

    Examples
    --------
    >>> parse_contrast("patient-control")
    {'patient': 1.0, 'control': -1.0}
    >>> parse_contrast("0.5*mild + 0.5*severe - control")
    {'mild': 0.5, 'severe': 0.5, 'control': -1.0}
    """
    terms = re.findall(r"([+-]?)([^+-]+)", text.replace(" ", ""))
    coefficients = {}
    for sign, term in terms:
        weight, _, level = term.rpartition("*")
        try:
            value = float(weight) if weight else 1.0
        except ValueError:
            raise ConfigError(f"contrast {text!r}: {weight!r} is not a number") from None
        if not level:
            raise ConfigError(f"contrast {text!r}: a term without a level")
        coefficients[level] = coefficients.get(level, 0.0) + (-value if sign == "-" else value)
    if sum(1 for v in coefficients.values() if v != 0) < 2 or "".join(
            sign + term for sign, term in terms) != text.replace(" ", ""):
        raise ConfigError(f"contrast {text!r}: write levels joined by + and -, such as "
                          "'patient-control' or 'mild+severe-2*control'")
    if abs(sum(coefficients.values())) > 1e-9 * max(abs(v) for v in coefficients.values()):
        raise ConfigError(f"contrast {text!r}: its coefficients add up to "
                          f"{sum(coefficients.values()):g}, not 0")
    return coefficients


def analysis_roles(group: str | None, covariates=(), nuisance=(), categorical=(),
                   test=(), subject: str | None = None, time: str | None = None,
                   interactions=()) -> Roles:
    """The roles of the columns of one analysis, declared by how they are named: ``group`` is
    categorical, ``covariates`` and ``nuisance`` columns are numeric unless named in
    ``categorical`` (a tested categorical covariate is one test over its levels). The tested
    effect is ``test`` when given (each one the group or a covariate), else the group, else the
    covariates; every other column is adjusted for.

    Repeated measures: ``subject`` names each case's subject and ``time`` its time point; the
    time is tested (the change within subjects) when nothing else is, else the tested columns'
    effect on the change. A ``subject`` without a time: the tested columns are the subjects'
    (whole subjects are permuted). ``interactions`` ("a:b", two columns of the model) are
    tested, with the columns named by ``test`` if any; their columns are adjusted for. The time's kind is decided with its levels
    (:func:`~mdlshapemodel.analysis.table.subjects`): it is in neither ``categorical`` nor
    ``numeric`` here.

    Raises
    ------
    ConfigError
        Nothing to test, a column named twice, ``test`` naming a column of the wrong kind,
        ``categorical`` naming a column not in the model, a time without a subject.

    Examples
    --------
    >>> roles = analysis_roles("diagnosis", ["age"], ["site"], categorical=["site"])
    >>> roles.tested, roles.adjusted_for, roles.categorical
    (['diagnosis'], ['age', 'site'], ['diagnosis', 'site'])
    >>> analysis_roles("diagnosis", ["age"], test=["age"]).adjusted_for
    ['diagnosis']
    >>> analysis_roles(None, ["site"], categorical=["site"]).categorical
    ['site']
    >>> analysis_roles(None, subject="id", time="visit").tested
    ['visit']
    >>> roles = analysis_roles("diagnosis", ["age"], interactions=["diagnosis:age"])
    >>> roles.tested, roles.adjusted_for
    (['diagnosis:age'], ['diagnosis', 'age'])
    """
    covariates, nuisance = list(covariates), list(nuisance)
    categorical, test = list(categorical), list(test)
    if time is not None and subject is None:
        raise ConfigError(f"--time {time} needs --subject (whose case each is): repeated "
                          "measures are a subject's cases")
    if group is None and not covariates and time is None:
        raise ConfigError("nothing to test: give a group column or a covariate")
    model = ([group] if group else []) + covariates + nuisance
    if subject is not None:
        for name in (subject, time):
            if name in model:
                raise ConfigError(f"column {name!r} is given twice (as --subject or --time and "
                                  "as a column of the model)")
        if subject == time:
            raise ConfigError(f"column {subject!r} is given twice (as --subject and --time)")
    for names in (model, categorical, test):
        repeated = sorted({c for c in names if names.count(c) > 1})
        if repeated:
            raise ConfigError(f"column {repeated[0]!r} is given twice")
    for name in test:
        if name != group and name not in covariates:
            raise ConfigError(f"test: {name!r} is not the group or a covariate (a tested "
                              "column is given by --group or --covariate)")
    for name in categorical:
        if name != group and name not in covariates and name not in nuisance and name != time:
            raise ConfigError(f"categorical: {name!r} is not a column of the model (give it "
                              f"with --covariate {name} to test it, or --nuisance {name})")
    interactions = list(interactions)
    for term in interactions:
        parts = term.split(":")
        if len(parts) != 2 or parts[0] == parts[1] or not all(c in model for c in parts):
            raise ConfigError(f"interaction {term!r}: write two different columns of the model "
                              "(the group, covariates or nuisance columns) as a:b")
    if len(set(interactions)) < len(interactions):
        raise ConfigError(f"interaction {interactions[0]!r} is given twice")
    tested = test or ([] if interactions else [group] if group else covariates)
    kinds = {name: name == group or name in categorical for name in model}
    if not tested and not interactions:
        return Roles(tested=[time], adjusted_for=list(model),
                     categorical=[c for c in model if kinds[c]],
                     numeric=[c for c in model if not kinds[c]])
    return Roles(tested=[c for c in model if c in tested] + interactions,
                 adjusted_for=[c for c in model if c not in tested],
                 categorical=[c for c in model if kinds[c]],
                 numeric=[c for c in model if not kinds[c]], interactions=interactions)


@dataclass
class AnalysisConfig:
    """Settings of one analysis of a build (``mdlshapemodel analyze``): which variables of the
    subjects table are tested and how. ``validate`` names the field at fault.

    A column's kind is declared by its role (:func:`analysis_roles`): the group is categorical,
    covariates and nuisance columns numeric unless named in ``categorical``. Beside a group,
    covariates are adjusted for unless named in ``test``.
    """

    group: str | None = None          # categorical column: the groups compared
    covariates: list[str] = field(default_factory=list)   # numeric columns
    nuisance: list[str] = field(default_factory=list)     # columns adjusted for, never tested
    categorical: list[str] = field(default_factory=list)  # covariate or nuisance columns that
    #                                                       are categorical (coded by levels)
    test: list[str] = field(default_factory=list)  # the tested columns (default: group, else
    #                                                the covariates); the rest is adjusted for
    reference: str | None = None      # the group the others are compared with (default: first)
    subject: str | None = None        # repeated measures: the column naming each case's subject
    time: str | None = None           # ... and the one naming its time point
    baseline: str | None = None       # the time the change is measured from (default: first)
    tail: str = "both"                # one-sided tests of a single-column effect
    contrasts: list[str] = field(default_factory=list)   # comparisons of a tested factor's
    #                                                      levels, each with its signed map
    interactions: list[str] = field(default_factory=list)  # tested products "a:b" of two
    #                                                        columns, which are adjusted for
    permutations: int = 10_000
    size: str = "kept"
    superimposition: str = "resistant"
    parts: str = "whole"              # multi-part objects: aligned as one, or each part alone
    displacement: str = "normal"
    variance: str = "groups"          # a tested group's statistic: per-group or pooled variance
    family_wise: str = "maximum"      # the family-wise correction over the points
    tfce: bool = False                # also each map enhanced over the mean surface (TFCE)
    alpha: float = 0.05
    seed: int = 0
    folds: int = 10                   # k of the classification's stratified k-fold
    repeats: int = 5                  # ... repeated with other folds
    classification_permutations: int = 200   # labelings permuted for the p of its AUC (0: none)
    long_table: bool = False          # also long.csv: one row per case and point (R, pandas)

    def validate(self) -> "AnalysisConfig":
        """Raise :class:`ConfigError` naming the first bad field; return self."""
        def need(condition: bool, name: str, text: str):
            if not condition:
                problem = f"{text} (got {getattr(self, name)!r})"
                raise ConfigError(f"{name}: {problem}", setting=name, problem=problem)

        need(self.permutations >= 1, "permutations", "must be at least 1")
        need(self.size in ANALYSIS_SIZES, "size", f"must be one of {', '.join(ANALYSIS_SIZES)}")
        need(self.superimposition in SUPERIMPOSITIONS, "superimposition",
             f"must be one of {', '.join(SUPERIMPOSITIONS)}")
        need(self.parts in PART_ALIGNMENTS, "parts",
             f"must be one of {', '.join(PART_ALIGNMENTS)}")
        need(self.displacement in DISPLACEMENTS, "displacement",
             f"must be one of {', '.join(DISPLACEMENTS)}")
        need(self.variance in VARIANCES, "variance", f"must be one of {', '.join(VARIANCES)}")
        need(self.family_wise in FAMILY_WISE, "family_wise",
             f"must be one of {', '.join(FAMILY_WISE)}")
        need(0 < self.alpha < 1, "alpha", "must be between 0 and 1")
        need(self.tail in TAILS, "tail", f"must be one of {', '.join(TAILS)}")
        for contrast in self.contrasts:
            parse_contrast(contrast)
        need(self.baseline is None or self.time is not None, "baseline",
             "is a level of the time column: give --time too")
        need(self.folds >= 2, "folds", "must be at least 2")
        need(self.repeats >= 1, "repeats", "must be at least 1")
        need(self.classification_permutations >= 0, "classification_permutations",
             "must be 0 (no p-value) or more")
        if (self.group is not None or self.covariates or self.time is not None
                or self.subject is not None):
            roles = self.roles()
            need(not (self.variance_groups() and self.displacement == "vector"
                      and (roles.adjusted_for or len(roles.tested) > 1)), "variance",
                 "per-group variances of the vector displacement (James' statistic) need the "
                 "groups compared alone, nothing adjusted for; use --variance pooled or the "
                 "normal displacement")
        return self

    def variance_groups(self) -> bool:
        """Whether the per-point test has a variance group per level of the group: a group is
        tested and ``variance`` is "groups" (a covariate's test is always pooled, and so is a
        test that permutes whole subjects: ``subject`` without ``time``)."""
        return (self.variance == "groups" and self.group is not None
                and self.group in self.roles().tested
                and not (self.subject is not None and self.time is None))

    def roles(self) -> Roles:
        """What each column of the model is (:func:`analysis_roles`); ConfigError when the
        names contradict each other."""
        return analysis_roles(self.group, self.covariates, self.nuisance, self.categorical,
                              self.test, self.subject, self.time, self.interactions)
