"""The optimisation state: every example's parameterization, warp and pose, and the fast objective.

An *example* (one subject) has one or more *parts* (multi-part objects, III-E), each a closed surface
with its own bijective sphere map and its own reparameterization phi, and one pose shared by its
parts. The shape vector x_i concatenates the parts' samples S_ij(phi_ij(u_k)) after the pose.

The objective F is a function of the reduced covariance D'_ij = sum_k w_k (x_ik - xbar_k).(x_jk - xbar_k)
(eq. 15-17), with the area weights w on the mean shape. We keep the uncentred weighted Gram matrix
K_ij = sum_k w_k (x_ik - r_k).(x_jk - r_k) about a fixed reference r, so that changing one example
costs O(n_s n_p) (one row of K) and D' = H K H with H = I - 11^T / n_s. Past
:func:`~.objective.covariance_route` (more shapes than coordinates, 3 n_p), no K is kept: F and
its gradient come from the centred, weighted shapes A (D' = A A^T) through the 3 n_p x 3 n_p
matrix A^T A, in time and memory linear in n_s.

Scale: with pose in the optimisation, F must not fall by shrinking the population. F is always
evaluated on the population rescaled so that the mean shape keeps the centroid size it had after
Procrustes alignment (``target_size``); the rescaling is folded into the poses at each rebuild.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ..errors import ArgumentError, InternalError
from ..geometry import Pose, centroid_size, generalized_procrustes, weighted_centroid
from ..prepare.curve import segment_vertex_lengths
from ..prepare.surface import face_areas, triangle_vertex_areas
from .carried import CarriedGrid, folds, kind_counts
from .guides import Guides
from .smoothness import Smoothness
from .objective import Objective, covariance_route
from .sampling import SphereLocator, grid_order, icosphere
from .warps import WARP_KINDS, SymmetricTheta, Warp, apply_symmetric_theta, apply_warps


class PartState:
    """One part of one example: surface, sphere map, current sample positions on the sphere."""

    #: whether the part lies in the plane z = 0 (curves: :class:`.circle.CurvePart`)
    planar = False
    #: the parameter domain (the fast strategy picks its field block by it)
    kind = "sphere"

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, sphere: np.ndarray,
                 grid: np.ndarray, grid_triangles: np.ndarray):
        # the mesh renumbered in the order the grid visits it (same surface, faster sampling);
        # its triangles are the locator's, in the locator's narrow index type (one copy)
        order, faces = grid_order(np.asarray(sphere, dtype=np.float64),
                                  np.asarray(faces, dtype=np.int64), grid)
        self.vertices = np.asarray(vertices, dtype=np.float64)[order]
        self.sphere = np.asarray(sphere, dtype=np.float64)[order]
        self.locator = SphereLocator(self.sphere, faces)
        self.faces = self.locator.faces
        # the surface's area shares, made when a random surface point is first asked for (the
        # fast strategy never asks)
        self.cumulative_area = None
        self.start_at(grid, grid_triangles)

    def on_grid(self, grid: np.ndarray, grid_cells: np.ndarray, near: bool = False
                ) -> "PartState":
        """The same surface and map sampled on another grid, with the same warps: a new part
        that shares this one's surface, sphere map and locator (read-only there). ``near``: the
        new grid's points are located starting from the triangle of this part's nearest sample
        (much faster where the new grid lies among the present samples)."""
        view = object.__new__(type(self))
        view.__dict__.update(self.__dict__)
        hint = None
        if near and self.hint is not None:
            hint = self.hint[cKDTree(self.positions).query(np.asarray(grid))[1]]
        view.start_at(grid, grid_cells, hint)
        if self.warps is None:        # the map is known where this part samples it
            view.take_first_positions(self)
        elif self.warps:
            view.replay(self.warps)
        return view

    def take_first_positions(self, finer: "PartState"):
        """The map of ``finer``, a part that keeps no warps (:meth:`carry`), sampled on this
        part's grid, which must be the first points of ``finer``'s (nested icospheres): its
        positions there. A warp moves each point on its own, so these are the positions the
        warps would give on this grid, bit for bit."""
        n = len(self.grid)
        if not np.array_equal(finer.grid[:n], self.grid):
            raise InternalError("a part that keeps no warps has its map on its own grid only: "
                                "the grid asked for is not its first points")
        self.warps, self.counts = None, dict(finer.counts)
        self.positions = finer.positions[:n].copy()
        self.points, self.hint = self.sample(self.positions)

    def replay_unfolded(self, warps: list) -> int:
        """Set the reparameterization to the longest first part of ``warps`` that, applied to
        the grid one after the other, flips no grid triangle; returns how many warps that is.

        Every warp is a homeomorphism of the sphere, so a grid triangle can only turn over where
        a warp varies faster than the grid resolves: warps accepted on a coarser grid are
        carried over to a finer one with this check. (Only where the whole composition folds
        are the warps checked one by one.)"""
        positions = apply_warps(self.grid, warps)
        kept = list(warps)
        if self.folds(positions):
            positions, kept = self.grid, []
            for warp in warps:
                moved = warp.apply(positions)
                if self.folds(moved):
                    break
                positions = moved
                kept.append(warp)
        self.warps = kept
        self.counts = kind_counts(kept)
        self.positions = np.array(positions, dtype=np.float64)
        self.points, self.hint = self.sample(self.positions)
        return len(kept)

    def carry(self, finer: "PartState"):
        """From now on, move ``finer``'s grid with every warp this part accepts
        (:class:`CarriedGrid`), and keep no warps: the coarse stage's parts (:mod:`.coarse`)
        carry their model-grid positions along instead of their warps, whose field coefficients
        outgrow those positions within a few rounds. :meth:`take_carried` gives ``finer`` the
        result."""
        if finer.warps is None:
            self.carried = CarriedGrid(finer.positions, finer.grid_triangles, finer.counts)
        else:
            self.carried = CarriedGrid(finer.grid, finer.grid_triangles)
            for warp in finer.warps:
                self.carried.move(warp)
        self.warps = None

    def take_carried(self, carried: "CarriedGrid") -> int:
        """Set the reparameterization to the positions a coarser part carried for this one
        (:meth:`carry`), by :meth:`replay_unfolded`'s rule; this part then keeps no warps.
        Returns how many warps were left out."""
        positions, counts = carried.settled()
        self.warps, self.counts = None, dict(counts)
        self.positions = np.asarray(positions, dtype=np.float64)
        self.points, self.hint = self.sample(self.positions)
        return sum(carried.counts.values()) - sum(counts.values())

    def start_at(self, grid: np.ndarray, grid_cells: np.ndarray, hint: np.ndarray | None = None):
        """No warp yet: the sample positions are the grid's (its triangles, or segments on a
        circle), and the samples are taken there (located from ``hint``'s faces if given)."""
        #: every accepted warp, in order: ``apply_warps(grid, warps)`` gives ``positions``;
        #: None in a part that keeps only the positions (:meth:`carry`, :meth:`take_carried`)
        self.warps: list[Warp] | None = []
        #: how many warps of each kind (a key of ``warps.WARP_KINDS``) were accepted
        self.counts: dict[str, int] = {}
        #: the finer grid this part moves along (:meth:`carry`), or None
        self.carried: CarriedGrid | None = None
        self.grid = np.asarray(grid, dtype=np.float64)
        # the grid itself, read-only (all parts sampled on it share it): a warp makes new
        # positions, never writes these
        self.positions = self.grid.view()
        self.positions.flags.writeable = False
        self.grid_triangles = np.asarray(grid_cells, dtype=np.int64)
        self.hint = None
        self.points, self.hint = self.sample(self.positions, hint)

    def sample(self, positions: np.ndarray, hint: np.ndarray | None = None):
        """S(phi(u_k)) at sphere positions; returns (points, located faces)."""
        if self.locator is None:
            raise RuntimeError("the part's point location was released "
                               "(CorrespondenceState.release_sampling): its points are final")
        return self.locator.evaluate(self.vertices, positions,
                                     self.hint if hint is None else hint)

    def random_surface_parameter(self, rng: np.random.Generator) -> np.ndarray:
        """Sphere coordinate of a point drawn uniformly over the *surface* (by area)."""
        if self.cumulative_area is None:
            areas = face_areas(self.vertices, self.faces)
            self.cumulative_area = np.cumsum(areas) / areas.sum()
        face = int(np.searchsorted(self.cumulative_area, rng.random(), side="right"))
        face = min(face, len(self.faces) - 1)
        r1, r2 = rng.random(2)
        s = np.sqrt(r1)
        bary = np.array([1 - s, s * (1 - r2), s * r2])
        point = bary @ self.sphere[self.faces[face]]
        return point / np.linalg.norm(point)

    def kernel(self, center, amplitude: float, omega: float) -> SymmetricTheta:
        """The part's kernel warp, the symmetric theta map (the strategies draw kernels through
        this, so that a curve part can give its own)."""
        return SymmetricTheta(center, amplitude, omega)

    @staticmethod
    def kernel_centres(level: int) -> np.ndarray:
        """The kernel centres that level ``level`` of III-D1 adds: the vertices that the
        ``level``-th subdivision of the icosahedron adds (level 0: its 12 vertices)."""
        previous = len(icosphere(level - 1)[0]) if level > 0 else 0
        return icosphere(level)[0][previous:]

    def folds(self, positions: np.ndarray) -> bool:
        """Whether any sampling-grid triangle is flipped at these positions.

        Every kernel is a homeomorphism of the sphere, but a kernel much narrower than the grid
        spacing can still turn a grid triangle over (its straight edges are not mapped exactly);
        amplitudes that would do so are never used.
        """
        return folds(positions, self.grid_triangles)

    def feasible_amplitude(self, center: np.ndarray, omega: float, upper: float,
                           steps: int = 12) -> float:
        """Largest amplitude in [0, upper] (to 2**-steps relative) that flips no grid triangle."""
        return self.feasible_parameter(
            lambda amplitude: apply_symmetric_theta(self.positions, center, amplitude, omega),
            upper, steps)

    def feasible_parameter(self, move, upper: float, steps: int = 12) -> float:
        """Largest t in [0, upper] (to 2**-steps relative) such that ``move(t)``, the current
        positions moved by a warp of parameter t (``move(0)``: unmoved), flips no grid triangle.

        Bisection: assumes the unfolded t form an interval containing 0, as they do for a warp
        whose distortion grows with |t| (an amplitude, a twist angle)."""
        if not self.folds(move(upper)):
            return upper
        low, high = 0.0, upper
        for _ in range(steps):
            middle = 0.5 * (low + high)
            if self.folds(move(middle)):
                high = middle
            else:
                low = middle
        return low

    def propose(self, warp: Warp, check_folds: bool = True):
        """Positions, points and hint after applying one more warp to the current positions (not
        committed); None when ``check_folds`` and it flips a grid triangle."""
        positions = warp.apply(self.positions)
        if check_folds and self.folds(positions):
            return None
        points, hint = self.sample(positions)
        return positions, points, hint

    def commit(self, warp: Warp, positions, points, hint):
        """Accept a warp (:meth:`accept`) and the positions, points and hint it gave."""
        self.accept(warp)
        self.positions, self.points, self.hint = positions, points, hint

    def accept(self, warp: Warp):
        """Record an accepted warp whose move the positions have (or are given next): in
        ``warps`` where they are kept, in ``counts``, and on the carried grid."""
        if self.warps is not None:
            self.warps.append(warp)
        self.counts[warp.kind] = self.counts.get(warp.kind, 0) + 1
        if self.carried is not None:
            self.carried.move(warp)

    def replay(self, warps: list):
        """Set the reparameterization to ``warps`` applied to the grid (a recorded state); a
        part that carries a finer grid moves it by them from that grid's start."""
        if self.warps is not None:
            self.warps = list(warps)
        self.counts = kind_counts(warps)
        if self.carried is not None:
            self.carried.restart()
            for warp in warps:
                self.carried.move(warp)
        self.positions = apply_warps(self.grid, warps)
        self.points, self.hint = self.sample(self.positions)

    def warp_counts(self) -> dict:
        """How many accepted warps of each kind (a key of ``warps.WARP_KINDS``) make its map."""
        return {kind: self.counts.get(kind, 0) for kind in WARP_KINDS}

    def __getstate__(self):
        # a copy in another process (a Dask worker's) does not move the carried grid: the
        # state's own part does, as it commits what the worker found
        return {**self.__dict__, "carried": None}


@dataclass
class Example:
    """One training example: its name, parts and pose."""

    name: str
    parts: list
    pose: Pose = field(default_factory=Pose)

    def raw_points(self, replace: dict | None = None) -> np.ndarray:
        """Concatenated unposed samples; ``replace`` maps part index -> trial points."""
        replace = replace or {}
        return np.concatenate([replace.get(j, part.points) for j, part in enumerate(self.parts)])


@dataclass
class FixedExample:
    """An example whose correspondence is given and kept (e.g. a model's training shapes when a
    new case is fitted): it has no parts to reparameterize, only a pose."""

    name: str
    points: np.ndarray
    pose: Pose = field(default_factory=Pose)
    parts: list = field(default_factory=list)

    def raw_points(self, replace: dict | None = None) -> np.ndarray:
        return self.points


@dataclass(frozen=True)
class ObjectiveParts:
    """The objective the optimisation minimises and its parts (nats): the description length
    (eq. 14, or eq. 13 for the fixed-Delta objective), the smoothness prior's energy and the
    landmark guides' term (each 0 where the state has none)."""

    description_length: float
    prior: float
    guides: float

    @property
    def total(self) -> float:
        """F: their sum, in the order :meth:`CorrespondenceState.value` adds them."""
        return self.description_length + self.guides + self.prior

    def to_json(self) -> dict:
        return {"description_length": self.description_length, "prior": self.prior,
                "guides": self.guides}


class CorrespondenceState:
    """All examples, the sampling grids, the area weights and the incrementally updated covariance.

    Parameters
    ----------
    examples : list of Example
    grids : list of (points, triangles)
        One sampling grid per part: points u_k on the sphere and their triangulation.
    objective : Objective
        F as a function of the (rescaled) reduced covariance.
    scaling : bool
        Whether Procrustes alignment removes scale.
    planar : bool, optional
        Whether the shapes lie in the plane z = 0 and poses rotate about z only; by default when
        every part is planar (closed curves).
    guides : Guides, optional
        Landmarks that guide the correspondence (:mod:`.guides`): their term is part of
        :meth:`value`.
    smoothness : Smoothness, optional
        The prior on smooth correspondence (:mod:`.smoothness`): its energy is part of
        :meth:`value` and its gradient of :meth:`shape_gradient`.
    """

    def __init__(self, examples: list, grids: list, objective: Objective | None = None,
                 scaling: bool = True, planar: bool | None = None, guides: Guides | None = None,
                 smoothness: Smoothness | None = None):
        self.examples = examples
        self.guides = guides
        self.smoothness = smoothness
        self.grids = grids
        self.objective = objective
        self.scaling = scaling
        if planar is None:
            parts = [part for example in examples for part in example.parts]
            planar = bool(parts) and all(part.planar for part in parts)
        self.planar = planar
        sizes = [len(points) for points, _ in grids]
        self.part_slices = [slice(a, b) for a, b in zip(np.cumsum([0] + sizes[:-1]),
                                                         np.cumsum(sizes))]
        self.n_points = int(sum(sizes))
        self.evaluations = 0
        self.gradient_evaluations = 0
        self.weights = np.full(self.n_points, 1.0 / self.n_points)
        self.target_size = None
        self.procrustes()

    @property
    def n_shapes(self) -> int:
        return len(self.examples)

    # ------------------------------------------------------------------ alignment and weights
    def area_weights(self, mean: np.ndarray) -> np.ndarray:
        """w_k: a third of the area, on the mean shape, of the triangles around point k (eq. 17);
        for a curve's grid (segments), half the length of the two segments around it."""
        weights = np.concatenate([vertex_measures(mean[s], cells)
                                  for s, (_, cells) in zip(self.part_slices, self.grids)])
        return weights / weights.sum()

    def procrustes(self, rounds: int = 3):
        """Weighted generalized Procrustes of the current samples; sets the poses (eq. 18)."""
        raw = np.stack([e.raw_points() for e in self.examples])
        weights = np.full(self.n_points, 1.0 / self.n_points)
        for _ in range(rounds):
            aligned, poses = generalized_procrustes(raw, weights, scaling=self.scaling,
                                                    target_size=self.target_size,
                                                    planar=self.planar)
            weights = self.area_weights(aligned.mean(axis=0))
        for example, pose in zip(self.examples, poses):
            example.pose = pose
        self.weights = weights
        if self.target_size is None:
            self.target_size = centroid_size(aligned.mean(axis=0), weights)
        self.rebuild()

    def rebuild(self, update_weights: bool = True):
        """Fold the scale correction into the poses, recompute weights, X and K from scratch."""
        shapes = np.stack([e.pose.apply(e.raw_points()) for e in self.examples])
        if update_weights:
            self.weights = self.area_weights(shapes.mean(axis=0))
        mean = shapes.mean(axis=0)
        centre = weighted_centroid(mean, self.weights)
        correction = Pose(self.target_size / centroid_size(mean, self.weights), np.eye(3),
                          np.zeros(3)).compose(Pose(1.0, np.eye(3), -centre))
        for example in self.examples:
            example.pose = correction.compose(example.pose)
        self.refresh()

    def refresh(self):
        """X, its reference and K from the current poses, samples and weights (no correction)."""
        self.shapes = np.stack([e.pose.apply(e.raw_points()) for e in self.examples])
        self.reference = self.shapes.mean(axis=0)
        self.sum_shapes = self.shapes.sum(axis=0)
        self.gram = None if self.by_covariance else self._gram(self.shapes)
        self.guide_costs = (None if self.guides is None
                            else self.guides.costs(self.raw_shapes()))
        # the prior's terms about this reference, and its energy and B~ D of the current shapes,
        # are made when first asked for: a state that is never evaluated with the prior (the
        # model's grid while the fast strategy optimises on the coarse one) never pays for them
        self._terms = None
        self._smoothed = None

    @property
    def by_covariance(self) -> bool:
        """Whether F goes through the 3 n_p x 3 n_p covariance (no n_s x n_s Gram matrix K)."""
        return covariance_route(self.n_shapes, 3 * self.n_points)

    def _gram(self, shapes: np.ndarray) -> np.ndarray:
        """K of ``shapes`` (n_s, n_p, 3) about the reference."""
        centred = ((shapes - self.reference) * np.sqrt(self.weights)[None, :, None]).reshape(
            len(shapes), -1)
        return centred @ centred.T

    def _scaled_data(self, i: int | None = None, shape: np.ndarray | None = None):
        """A (n_s, 3 n_p), the shapes centred on their mean, times sqrt(w_k) and the rescaling f,
        so that D' = A A^T (shape i replaced by ``shape`` if given); the sum of the shapes; f."""
        shapes, total = self.shapes, self.sum_shapes
        if i is not None:
            shapes = shapes.copy()
            shapes[i] = shape
            total = total - self.shapes[i] + shape
        factor = self.target_size / centroid_size(total / self.n_shapes, self.weights)
        data = shapes - total / self.n_shapes
        data *= (factor * np.sqrt(self.weights))[None, :, None]
        return data.reshape(self.n_shapes, -1), total, factor

    @property
    def smoothness_terms(self):
        """The prior's terms about the reference of the last refresh (None without a prior)."""
        if self.smoothness is None:
            return None
        if self._terms is None:
            self._terms = self.smoothness.at(self.reference)
        return self._terms

    @property
    def smooth_energy(self) -> float:
        """The prior's energy E of the current shapes (0 without a prior)."""
        return self._smooth()[0]

    @property
    def bent(self):
        """B~ D_i of the current shapes, (n_s, n_p, 3) (None without a prior)."""
        return self._smooth()[1]

    def _smooth(self) -> tuple:
        """(E, B~ D) of the current shapes, with the terms held fixed; made once per change."""
        if self._smoothed is None:
            terms = self.smoothness_terms
            self._smoothed = (0.0, None) if terms is None else terms.energy(self.shapes)
        return self._smoothed

    def _smooth_trial(self, i: int, shape: np.ndarray) -> tuple[float, np.ndarray]:
        """The prior's energy with example i's shape replaced by ``shape``, and B~ Delta
        (:meth:`.smoothness.SmoothnessTerms.trial`)."""
        return self.smoothness_terms.trial(self.smooth_energy, self.bent[i],
                                           shape - self.shapes[i], self.n_shapes)

    # ------------------------------------------------------------------ objective
    def _row(self, shape: np.ndarray) -> tuple[np.ndarray, float]:
        d = (shape - self.reference) * self.weights[:, None]
        row = np.einsum("ikd,kd->i", self.shapes - self.reference, d)
        return row, float(np.sum((shape - self.reference) * d))

    def covariance(self, i: int | None = None, shape: np.ndarray | None = None) -> np.ndarray:
        """Reduced covariance D' (eq. 15), with shape i replaced by ``shape`` if given, rescaled so
        that the mean keeps ``target_size``. An n_s x n_s matrix, also past the covariance route
        (:meth:`description_length` measures F without it)."""
        if self.gram is None:
            data = self._scaled_data(i, shape)[0]
            return data @ data.T
        gram = self.gram
        total = self.sum_shapes
        if i is not None:
            gram = gram.copy()
            row, diagonal = self._row(shape)
            gram[i, :] = row
            gram[:, i] = row
            gram[i, i] = diagonal
            total = total - self.shapes[i] + shape
        n = self.n_shapes
        row_mean = gram.mean(axis=1)
        centred = gram - row_mean[:, None] - row_mean[None, :] + row_mean.mean()
        factor = self.target_size / centroid_size(total / n, self.weights)
        return centred * factor ** 2

    def value(self, i: int | None = None, shape: np.ndarray | None = None,
              raw: np.ndarray | None = None) -> float:
        """F of the current state, or with shape i replaced by ``shape``: the description length
        of the covariance, plus the landmark term of the guides (if any), for which a trial also
        gives ``raw``, its unposed samples, and the smoothness prior's energy (if any)."""
        self.evaluations += 1
        return (self.description_length(None, i, shape) + self.guide_cost(i, raw)
                + self.smoothness_energy(i, shape))

    def description_length(self, objective: Objective | None = None, i: int | None = None,
                           shape: np.ndarray | None = None) -> float:
        """``objective`` (the state's by default) of D', with shape i replaced by ``shape`` if
        given: through K, or past the covariance route through A^T A."""
        objective = self.objective if objective is None else objective
        if self.gram is None:
            return objective.from_data(self._scaled_data(i, shape)[0])
        return objective(self.covariance(i, shape))

    def objective_parts(self, objective: Objective | None = None) -> ObjectiveParts:
        """The parts of F of the current state, with ``objective`` (the state's by default) as
        its description length: their total is :meth:`value` with that objective."""
        return ObjectiveParts(self.description_length(objective), self.smoothness_energy(),
                              self.guide_cost())

    def smoothness_energy(self, i: int | None = None, shape: np.ndarray | None = None) -> float:
        """The prior's energy (0 without a prior) of the population rescaled as F sees it,
        f^2 E with f = target_size / cs(mean) (E is quadratic in the shapes' size: unscaled,
        it would fall by shrinking the population), or with example i's shape replaced."""
        if self.smoothness_terms is None:
            return 0.0
        if i is None:
            return self._size_factor(self.sum_shapes) * self.smooth_energy
        total = self.sum_shapes - self.shapes[i] + shape
        return self._size_factor(total) * self._smooth_trial(i, shape)[0]

    def _size_factor(self, total: np.ndarray) -> float:
        """f^2 = (target_size / cs(mean))^2 for the shapes summing to ``total``."""
        return (self.target_size / centroid_size(total / self.n_shapes, self.weights)) ** 2

    def _smoothness_gradient(self, total: np.ndarray, energy: float, bent: np.ndarray
                             ) -> np.ndarray:
        """d(f^2 E)/dX for one example (``bent`` its B~ D, (n_p, 3)) or all ((n_s, n_p, 3)):
        f^2 (w/h^2) B~ D_i plus the change of f^2 (:meth:`scale_gradient`)."""
        scaled = self._size_factor(total)
        return (scaled * self.smoothness_terms.factor * bent
                + self.scale_gradient(total, scaled * energy))

    def guide_cost(self, i: int | None = None, raw: np.ndarray | None = None) -> float:
        """The landmark term C of the guides (0 without), or with example i's unposed samples
        replaced by ``raw`` (n_p, 3)."""
        if self.guides is None:
            return 0.0
        total = float(self.guide_costs.sum())
        if i is None:
            return total
        if raw is None:
            raise ArgumentError("a trial of a guided state needs its unposed samples (raw)")
        return total - float(self.guide_costs[i]) + self.guides.cost(i, raw)

    def shape_gradient(self) -> tuple[float, np.ndarray]:
        """F of the current state and G = dF/dX, (n_s, n_p, 3): the derivative of the description
        length with respect to every example's posed points, with the area weights w held fixed
        (docs/method.md section 2). F includes the guides' landmark term (:meth:`guide_cost`),
        which depends on the unposed samples only: its gradient is the guides' own
        (:meth:`.guides.Guides.gradients`), not part of G. F and G include the smoothness
        prior's energy and gradient (:mod:`.smoothness`).

        F = F(D'), D' = f^2 H K H, f = target_size / cs(mean). With Gd = dF/dD' (symmetric,
        :meth:`Objective.gradient`) and M = f^2 H Gd H,

            dF/dx_ik = 2 w_k sum_j M_ij (x_jk - r_k) - (2 / n_s) <Gd, D'> w_k (xbar_k - c) / cs^2,

        the second term from the rescaling (c, cs: weighted centroid and centroid size of the
        mean xbar). Cost: one (n_s x n_s) by (n_s x 3 n_p) product, O(n_s^2 n_p). Past the
        covariance route, dF/dx_ik = f sqrt(w_k) (H dF/dA)_ik, dF/dA from
        :meth:`Objective.data_gradient`, and <Gd, D'> = <dF/dA, A> / 2: O(n_s n_p^2).
        """
        if self.gram is None:
            value, grad, total, amount = self._data_gradient(None, None)
            grad += self.scale_gradient(total, amount)
        else:
            value, grad_cov, covariance, multiplier = self._covariance_gradient(None, None)
            # flat, contiguous element-wise products: broadcasting over a last axis of 3 is slow
            flat = (self.shapes - self.reference).reshape(self.n_shapes, -1)
            flat *= np.repeat(2.0 * self.weights, 3)
            grad = multiplier @ flat
            grad += self.scale_gradient(self.sum_shapes,
                                        float(np.sum(grad_cov * covariance))).reshape(1, -1)
            grad = grad.reshape(self.shapes.shape)
        if self.smoothness_terms is not None:
            grad += self._smoothness_gradient(self.sum_shapes, self.smooth_energy, self.bent)
        return value + self.guide_cost() + self.smoothness_energy(), grad

    def example_gradient(self, i: int, shape: np.ndarray | None = None
                         ) -> tuple[float, np.ndarray]:
        """F and dF/dX_i, (n_p, 3), for example i alone (its shape replaced by ``shape`` if
        given, as in :meth:`covariance`). Cost O(n_s n_p) beyond the O(n_s^3) objective (past
        the covariance route, the whole dF/dX, O(n_s n_p^2), of which row i is kept)."""
        if self.gram is None:
            value, grad, total, amount = self._data_gradient(None if shape is None else i, shape)
            gradient = grad[i] + self.scale_gradient(total, amount)
        else:
            value, grad_cov, covariance, multiplier = self._covariance_gradient(
                None if shape is None else i, shape)
            total = self.sum_shapes
            row = np.tensordot(multiplier[i], self.shapes - self.reference, axes=1)
            if shape is not None:
                row += multiplier[i, i] * (shape - self.shapes[i])
                total = total - self.shapes[i] + shape
            data = 2.0 * row * self.weights[:, None]
            gradient = data + self.scale_gradient(total, float(np.sum(grad_cov * covariance)))
        if self.smoothness_terms is not None:
            bent = self.bent[i]
            if shape is not None:
                energy, bent_delta = self._smooth_trial(i, shape)
                bent = bent + (1.0 - 1.0 / self.n_shapes) * bent_delta
            else:
                energy = self.smooth_energy
            value += self._size_factor(total) * energy
            gradient = gradient + self._smoothness_gradient(total, energy, bent)
        return value, gradient

    def _covariance_gradient(self, i, shape):
        """F, dF/dD', D' and dF/dK = f^2 H (dF/dD') H at the current (or trial) state."""
        self.gradient_evaluations += 1
        covariance = self.covariance(i, shape)
        value, grad_cov = self.objective.gradient(covariance)
        total = self.sum_shapes if i is None else self.sum_shapes - self.shapes[i] + shape
        factor = self.target_size / centroid_size(total / self.n_shapes, self.weights)
        centred = grad_cov - grad_cov.mean(axis=1)[:, None]
        centred = centred - centred.mean(axis=0)[None, :]
        return value, grad_cov, covariance, centred * factor ** 2

    def _data_gradient(self, i, shape):
        """F, dF/dX (n_s, n_p, 3) without the rescaling's term, the sum of the shapes and
        <dF/dD', D'> at the current (or trial) state, through the covariance route."""
        self.gradient_evaluations += 1
        data, total, factor = self._scaled_data(i, shape)
        value, grad = self.objective.data_gradient(data)
        amount = 0.5 * float(np.sum(grad * data))
        grad -= grad.mean(axis=0)
        grad *= factor * np.repeat(np.sqrt(self.weights), 3)
        return value, grad.reshape(self.shapes.shape), total, amount

    def scale_gradient(self, total, amount: float) -> np.ndarray:
        """(n_p, 3): the part of dT/dx_ik (the same for every example i) due to the rescaling
        factor f = target_size / cs(mean), for a term T of F evaluated on the rescaled
        population with dT/df^2 = ``amount`` / f^2 (the description length: amount = <Gd, D'>;
        the smoothness prior, f^2 E: amount = f^2 E). d f^2 = -f^2 d cs^2 / cs^2 and
        d cs^2 / dx_ik = 2 w_k (xbar_k - c) / n_s."""
        mean = total / self.n_shapes
        offset = mean - weighted_centroid(mean, self.weights)
        size_squared = centroid_size(mean, self.weights) ** 2
        return -2.0 / self.n_shapes * amount / size_squared * self.weights[:, None] * offset

    @contextlib.contextmanager
    def trial_shapes(self, shapes: np.ndarray, raw: np.ndarray | None = None):
        """Within the block, :meth:`value`, :meth:`covariance` and :meth:`shape_gradient` see
        *every* example's shape replaced by ``shapes`` (n_s, n_p, 3) (and a guided state's
        unposed samples by ``raw``, needed then): the Gram matrix (if kept) is rebuilt from
        scratch about the same reference, O(n_s^2 n_p). The state is restored afterwards."""
        if self.guides is not None and raw is None:
            raise ArgumentError("a trial of a guided state needs its unposed samples (raw)")
        saved = (self.shapes, self.sum_shapes, self.gram, self.guide_costs, self._smoothed)
        self.shapes, self.sum_shapes = shapes, shapes.sum(axis=0)
        self.gram = None if self.gram is None else self._gram(shapes)
        if self.guides is not None:
            self.guide_costs = self.guides.costs(raw)
        self._smoothed = None
        try:
            yield self
        finally:
            (self.shapes, self.sum_shapes, self.gram, self.guide_costs, self._smoothed) = saved

    def commit_shape(self, i: int):
        """Record that example i's parts or pose changed: update X, K and the sums."""
        shape = self.examples[i].pose.apply(self.examples[i].raw_points())
        if self.smoothness_terms is not None:
            energy, bent_delta = self._smooth_trial(i, shape)
            bent = self.bent
            bent -= bent_delta / self.n_shapes
            bent[i] += bent_delta
            self._smoothed = (energy, bent)
        if self.gram is not None:
            row, diagonal = self._row(shape)
            self.gram[i, :] = row
            self.gram[:, i] = row
            self.gram[i, i] = diagonal
        self.sum_shapes += shape - self.shapes[i]
        self.shapes[i] = shape
        if self.guides is not None:
            self.guide_costs[i] = self.guides.cost(i, self.examples[i].raw_points())

    # ------------------------------------------------------------------ views
    def _model_frame(self) -> tuple[np.ndarray, float]:
        mean = self.sum_shapes / self.n_shapes
        return weighted_centroid(mean, self.weights), self.target_size / centroid_size(
            mean, self.weights)

    def aligned_shapes(self) -> np.ndarray:
        """(n_s, n_p, 3) shapes in the model frame, rescaled to ``target_size``."""
        centre, factor = self._model_frame()
        return (self.shapes - centre) * factor

    def to_model_frame(self, i: int, points: np.ndarray) -> np.ndarray:
        """Points in example i's own coordinates (e.g. its input surface) -> the model frame."""
        centre, factor = self._model_frame()
        return ModelFrame.moved(self.examples[i].pose, centre, factor, points)

    def model_frame(self) -> "ModelFrame":
        """The model frame as it is now, with a copy of every example's pose: it moves points
        as :meth:`to_model_frame` does now, whatever the state does afterwards."""
        centre, factor = self._model_frame()
        return ModelFrame(tuple(e.pose.copy() for e in self.examples), centre, factor)

    def triangles(self) -> np.ndarray:
        """Connectivity of the concatenated sampling grids of all parts."""
        return np.concatenate([triangles + s.start
                               for s, (_, triangles) in zip(self.part_slices, self.grids)])

    def raw_shapes(self) -> np.ndarray:
        """(n_s, n_p, 3) samples in each example's own physical coordinates."""
        return np.stack([e.raw_points() for e in self.examples])

    def release_sampling(self):
        """The correspondence is final: drop what only moving the sample points needs, each
        part's point locator and its copy of the surface and sphere map (most of the state's
        memory). The samples, poses, weights and warps stay; sampling afterwards raises
        RuntimeError. A build calls it before it evaluates the model."""
        for example in self.examples:
            for part in getattr(example, "parts", ()):
                if isinstance(part, PartState):
                    part.locator = part.vertices = part.faces = part.sphere = None
                    part.cumulative_area = None

    def set_aside(self):
        """While a :func:`~.coarse.coarse_view` of this state is optimised in its place, drop
        what :func:`~.coarse.carry_over` makes again from the warps and poses: each sphere
        part's samples, X, its reference and sums, K and the prior's terms. The located faces
        stay: the points are located again from them, as they would have been. Until then the
        state has no shapes (``shapes`` is None)."""
        for example in self.examples:
            for part in getattr(example, "parts", ()):
                if isinstance(part, PartState) and part.kind == "sphere":
                    part.points = None
        self.shapes = self.reference = self.sum_shapes = self.gram = None
        self.guide_costs = self._terms = self._smoothed = None

    def snapshot(self) -> list:
        """Everything the optimisation changes: per example its pose and per part its positions,
        located faces, warps (their counts) and carried grid."""
        return [(e.pose.copy(), [(p.positions.copy(), p.points.copy(), p.hint.copy(),
                                  None if p.warps is None else list(p.warps), dict(p.counts),
                                  None if p.carried is None else p.carried.copy())
                                 for p in e.parts]) for e in self.examples]

    def restore(self, snapshot: list):
        """Return to a :meth:`snapshot`."""
        for example, (pose, parts) in zip(self.examples, snapshot):
            example.pose = pose.copy()
            for part, (positions, points, hint, warps, counts, carried) in zip(example.parts,
                                                                                 parts):
                part.positions, part.points, part.hint = positions.copy(), points.copy(), hint.copy()
                part.warps = None if warps is None else list(warps)
                part.counts = dict(counts)
                part.carried = None if carried is None else carried.copy()
        self.rebuild()


@dataclass(frozen=True)
class ModelFrame:
    """Every example's pose and the model frame's centre and scale factor at one moment
    (:meth:`CorrespondenceState.model_frame`): a few numbers per example, which move a case's
    own coordinates (its input surface) into the frame of the aligned shapes."""

    poses: tuple          # of Pose, one per example
    centre: np.ndarray    # (3,) the weighted centroid of the mean shape, after the poses
    factor: float         # the rescaling to the state's target size

    @staticmethod
    def moved(pose: Pose, centre: np.ndarray, factor: float, points: np.ndarray) -> np.ndarray:
        """``points`` moved by ``pose``, then centred on ``centre`` and scaled by ``factor``."""
        return (pose.apply(points) - centre) * factor

    def to_model_frame(self, i: int, points: np.ndarray) -> np.ndarray:
        """Points in example i's own coordinates -> the model frame."""
        return self.moved(self.poses[i], self.centre, self.factor, points)


def vertex_measures(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """The measure of eq. 17 around each grid point: a third of the area of its triangles (cells
    of 3 points, a sphere's grid) or half the length of its segments (cells of 2, a curve's)."""
    if cells.shape[1] == 2:
        return segment_vertex_lengths(points, cells)
    return triangle_vertex_areas(points, cells)


def state_record(state: CorrespondenceState) -> dict:
    """The state's correspondence as named arrays: per example its pose, per part the sample
    positions, the sampled points and the faces they lie in, and its accepted warps (kinds,
    parameter vectors; where the part keeps none, :meth:`PartState.carry`, how many of each
    kind, and the finer grid's positions it carries). With the same prepared cases and
    settings, :func:`replay_record` rebuilds the state from it bit for bit."""
    arrays = {"names": np.array([e.name for e in state.examples]), "weights": state.weights,
              "target_size": np.array(state.target_size)}
    for i, example in enumerate(state.examples):
        arrays[f"pose_{i}"] = np.concatenate([[example.pose.scale],
                                              example.pose.rotation.ravel(),
                                              example.pose.translation])
        for j, part in enumerate(getattr(example, "parts", [])):
            arrays[f"positions_{i}_{j}"] = part.positions
            # the samples and the faces they were located in (where a walk starts next): a
            # resumed optimisation must see exactly these, not a fresh location's rounding
            arrays[f"points_{i}_{j}"] = part.points
            arrays[f"hint_{i}_{j}"] = np.asarray(part.hint)
            if part.warps is not None:
                vectors = [warp.to_vector() for warp in part.warps]
                arrays[f"warp_kinds_{i}_{j}"] = np.array([w.kind for w in part.warps], dtype=str)
                arrays[f"warp_sizes_{i}_{j}"] = np.array([len(v) for v in vectors],
                                                         dtype=np.int64)
                arrays[f"warp_values_{i}_{j}"] = (np.concatenate(vectors) if vectors
                                                  else np.zeros(0))
            else:
                arrays.update(_counts_record(f"counts_{i}_{j}", part.counts))
            carried = part.carried
            if carried is not None:
                arrays[f"carried_{i}_{j}"] = carried.positions
                arrays.update(_counts_record(f"carried_counts_{i}_{j}", carried.counts))
                if carried.unfolded is not None:
                    arrays[f"unfolded_{i}_{j}"] = carried.unfolded[0]
                    arrays.update(_counts_record(f"unfolded_counts_{i}_{j}",
                                                 carried.unfolded[1]))
    return arrays


def _counts_record(name: str, counts: dict) -> dict:
    return {f"{name}_kinds": np.array(list(counts), dtype=str),
            name: np.array(list(counts.values()), dtype=np.int64)}


def _recorded_counts(arrays, name: str) -> dict:
    return {str(kind): int(count) for kind, count in zip(arrays[f"{name}_kinds"], arrays[name])}


def replay_record(state: CorrespondenceState, arrays) -> None:
    """Give ``state`` (the initial state of the same cases and settings) the correspondence of a
    :func:`state_record`: every part's warps re-applied to the grid (or its recorded positions,
    where the part kept no warps), every pose set. Raises ValueError when the record is of
    other cases or other sample points."""
    names = [str(n) for n in arrays["names"]]
    if names != [e.name for e in state.examples]:
        raise ArgumentError("the record is of other cases")
    for i, example in enumerate(state.examples):
        pose = np.asarray(arrays[f"pose_{i}"], dtype=np.float64)
        example.pose = Pose(float(pose[0]), pose[1:10].reshape(3, 3), pose[10:13])
        for j, part in enumerate(getattr(example, "parts", [])):
            if len(arrays[f"positions_{i}_{j}"]) != len(part.grid):
                raise ArgumentError("the record has another number of sample points")
            if f"warp_kinds_{i}_{j}" in arrays:
                kinds = [str(k) for k in arrays[f"warp_kinds_{i}_{j}"]]
                ends = np.cumsum(arrays[f"warp_sizes_{i}_{j}"])
                values = np.asarray(arrays[f"warp_values_{i}_{j}"], dtype=np.float64)
                part.replay([WARP_KINDS[kind].from_vector(values[end - size:end])
                             for kind, end, size in zip(kinds, ends,
                                                        arrays[f"warp_sizes_{i}_{j}"])])
            else:
                part.warps = None
                part.counts = _recorded_counts(arrays, f"counts_{i}_{j}")
                part.positions = np.array(arrays[f"positions_{i}_{j}"], dtype=np.float64)
            if f"carried_{i}_{j}" in arrays and part.carried is not None:
                carried = part.carried
                carried.positions = np.array(arrays[f"carried_{i}_{j}"], dtype=np.float64)
                carried.counts = _recorded_counts(arrays, f"carried_counts_{i}_{j}")
                carried.unfolded = None
                if f"unfolded_{i}_{j}" in arrays:
                    carried.unfolded = (np.array(arrays[f"unfolded_{i}_{j}"], dtype=np.float64),
                                        _recorded_counts(arrays, f"unfolded_counts_{i}_{j}"))
            if f"points_{i}_{j}" in arrays:
                part.points = np.array(arrays[f"points_{i}_{j}"], dtype=np.float64)
                part.hint = np.array(arrays[f"hint_{i}_{j}"])
                if part.kind == "sphere":     # faces (a record may hold them in int64)
                    part.hint = part.hint.astype(part.faces.dtype)
            elif part.warps is None:
                part.points, part.hint = part.sample(part.positions)
    if len(arrays["weights"]) != state.n_points:
        raise ArgumentError("the record has another number of sample points")
    state.weights = np.asarray(arrays["weights"], dtype=np.float64).copy()
    state.target_size = float(arrays["target_size"])
    state.refresh()
