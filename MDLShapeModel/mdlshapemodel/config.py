"""One configuration object for every knob, with the paper's defaults (Table I).

The command line, the VTK filters and the Slicer panel all fill a :class:`BuildConfig`; ``validate``
names the field at fault. This module is a leaf: it imports nothing heavier than the standard
library, so a panel that only fills a configuration loads neither VTK, numba nor the optimiser.
"""

from __future__ import annotations

import math
import os
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


@dataclass
class BuildConfig:
    """Settings of a model build. Lengths marked *voxels* are in voxels of the source images."""

    # inputs
    labels: list = field(default_factory=list)   # label values whose union is the object; [] = all non-zero
    voxel_size: float | None = None   # mm per voxel for mesh inputs; default: their mean edge length
    mirror: list = field(default_factory=list)  # file-name patterns of inputs to reflect (x -> -x)
    # surfaces and sphere maps
    surface_method: str = "gaussian"  # "gaussian": blur + flying edges; "slicer": flying edges +
    smoothing_factor: float = 0.5     #   windowed sinc (3D Slicer's conversion, this factor)
    decimation: float = 0.0           # "slicer": fraction of triangles removed before smoothing
    smoothing_sigma: float = 1.0      # voxels: Gaussian blur of the mask before contouring
    max_smoothing_sigma: float = 2.0  # voxels: raised up to this when the surface is not genus 0
    edge_length: float = 1.0          # voxels: isotropic remeshing of label-map surfaces
    target_vertices: int = 20000      # meshes with more vertices are decimated
    # correspondence
    correspondence: str = "mdl"       # "mdl": optimised by MDL; "cpd": CPD template registration
    baselines: list = field(default_factory=lambda: ["none"])  # also evaluated on the same cases
    points: int = 2562                # n_p: sample points per shape (icosphere when 10*4^k+2)
    # optimisation: our gradient strategy by default (the paper's four remain selectable); the
    # other defaults are those of strategies.OptimisationSettings (one source)
    strategy: str = "fast"
    # one-at-a-time strategies: warp kinds each step draws from (uniformly), of symmetric,
    # asymmetric, shear, rotation; ["symmetric"] is the paper's strategy
    warps: list = field(default_factory=lambda: list(OptimisationSettings.warps))
    scaling: bool = True              # Procrustes removes scale
    delta_range: tuple = (1e-4, 0.5)  # voxels: [Delta_min, Delta_max] of eq. 14 (Table I)
    fixed_delta: float = 0.1          # voxels: Delta of the first phase (eq. 13)
    sigma_g: float = OptimisationSettings.sigma_g              # kernel widths (Table I)
    max_amplitude: float = OptimisationSettings.max_amplitude  # bound of a kernel amplitude A
    max_time: float = OptimisationSettings.max_time            # seconds of optimisation
    fixed_fraction: float = OptimisationSettings.fixed_fraction  # fixed-Delta share (0: none)
    tolerance: float = OptimisationSettings.tolerance          # sweep gain / total gain to stop
    max_sweeps: int = OptimisationSettings.max_sweeps          # per phase; a repeatable budget
    seed: int = 0
    # evaluation
    evaluation_modes: int = 10
    specificity_samples: int = 10_000
    surface_samples: int = 200        # specificity samples measured surface to surface (0: none)
    # running
    workers: int = field(default_factory=lambda: os.cpu_count() or 1)
    cache_dir: str | None = None      # per-case preprocessing cache; None: default place, "": off
    strict: bool = False

    def validate(self) -> "BuildConfig":
        """Raise :class:`ConfigError` naming the first bad field; return self."""
        def need(condition: bool, name: str, text: str):
            if not condition:
                raise ConfigError(f"{name}: {text} (got {getattr(self, name)!r})")

        need(all(isinstance(v, int) and v > 0 for v in self.labels), "labels",
             "label values must be positive integers")
        need(self.voxel_size is None or self.voxel_size > 0, "voxel_size", "must be positive")
        need(self.surface_method in SURFACE_METHODS, "surface_method",
             f"must be one of {', '.join(SURFACE_METHODS)}")
        need(0 <= self.smoothing_factor <= 1, "smoothing_factor", "must be between 0 and 1")
        need(0 <= self.decimation < 1, "decimation", "must be in [0, 1)")
        need(self.smoothing_sigma >= 0, "smoothing_sigma", "must be >= 0")
        need(self.max_smoothing_sigma >= self.smoothing_sigma, "max_smoothing_sigma",
             "must be >= smoothing_sigma")
        need(self.edge_length > 0, "edge_length", "must be positive")
        need(self.target_vertices >= 100, "target_vertices", "must be at least 100")
        need(self.correspondence in CORRESPONDENCES, "correspondence",
             f"must be one of {', '.join(CORRESPONDENCES)}")
        need(all(b in BASELINES for b in self.baselines), "baselines",
             f"each must be one of {', '.join(BASELINES)}")
        need(self.points >= 12, "points", "must be at least 12")
        need(self.strategy in STRATEGIES, "strategy", f"must be one of {', '.join(STRATEGIES)}")
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
        need(self.evaluation_modes >= 1, "evaluation_modes", "must be at least 1")
        need(self.specificity_samples >= 2, "specificity_samples", "must be at least 2")
        need(self.surface_samples == 0 or self.surface_samples >= 2, "surface_samples",
             "must be 0 (none) or at least 2")
        need(self.workers >= 1, "workers", "must be at least 1")
        return self

    def optimisation_settings(self) -> OptimisationSettings:
        """The optimiser's settings of this build."""
        return OptimisationSettings(strategy=self.strategy, sigma_g=self.sigma_g,
                                    max_amplitude=self.max_amplitude, max_time=self.max_time,
                                    fixed_fraction=self.fixed_fraction,
                                    tolerance=self.tolerance, max_sweeps=self.max_sweeps,
                                    warps=tuple(self.warps))

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
