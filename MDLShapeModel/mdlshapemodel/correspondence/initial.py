"""The initial correspondence of prepared cases: their parameterizations aligned across the
population and sampled (sphere grids for surfaces, the circle for 2-D curves), Procrustes-aligned,
with the two objectives of the build."""

from __future__ import annotations

import numpy as np

from ..config import BuildConfig
from ..prepare.sphere import align_parameterizations, reference_frames
from .circle import curve_state
from .guides import guides_on_grid, place_landmarks
from .smoothness import Smoothness
from .objective import objectives
from .placement import icosphere_level, surface_grids
from .sampling import sphere_grid
from .state import CorrespondenceState, Example, PartState


def initial_state(prepared: list, config: BuildConfig, landmarks: dict | None = None):
    """The initial correspondence of prepared cases and the two objectives.

    2-D curves: :func:`.circle.curve_state` (origins aligned, ``config.points_for(curves=True)``
    equally spaced samples on the circle, planar pose). Surfaces: part by part (every case has
    the same parts, in the same order), the sphere maps are aligned
    across the population (in the frame of each case's whole surface) and sampled at
    ``config.points``; one pose per case moves all its
    parts (III-E). The objectives' Delta follow the mean voxel size. Returns (state, (fixed,
    integrated), voxel size, data range of the aligned shapes).

    ``landmarks`` (case name -> :class:`~mdlshapemodel.prepare.landmarks.Landmarks`, surfaces
    only): the alignment of the sphere maps also brings each label to one shared place, and the
    state gets their :class:`.guides.Guides` (weight ``config.landmark_weight``), on sample
    points of the coarse grid where the fast strategy runs one. A weight
    ``config.smoothness_for(curves=False, guided=...)`` > 0 (the guided weight where landmarks
    guide) gives the state the prior of :mod:`.smoothness`.
    """
    # the mean voxel size: the unit of the coding accuracy, the guides and the prior
    voxel = float(np.mean([case.voxel_size for case in prepared]))
    if prepared[0].is_curve:
        state = curve_state([[part.map for part in case.parts] for case in prepared],
                            [case.name for case in prepared], config.points_for(curves=True),
                            scaling=config.scaling)
        return _with_objectives(state, voxel, config)
    n_parts = len(prepared[0].parts)
    n_points = config.points_for(curves=False)
    # several parts: each case's frame from its whole surface, the same for all its parts
    frames = reference_frames([case.surface() for case in prepared]) if n_parts > 1 else None
    placed = place_landmarks(prepared, landmarks) if landmarks else None
    maps = []
    for j in range(n_parts):
        originals = [case.parts[j].map for case in prepared]
        images = None if placed is None else placed.images(j, originals)
        maps.append(align_parameterizations(originals, frames=frames, landmarks=images))
    coarse = config.coarse_points
    nested = coarse if 0 < coarse < n_points else 0     # the grid's first points
    grids = [sphere_grid(n_points)] * n_parts
    examples = [Example(case.name, [PartState(maps[j][i].vertices, maps[j][i].faces,
                                              maps[j][i].sphere, *grids[j])
                                    for j in range(n_parts)])
                for i, case in enumerate(prepared)]
    if config.placement == "surface":
        grids = surface_grids(CorrespondenceState(examples, grids, scaling=config.scaling),
                              nested if icosphere_level(nested) else 0)
        # one example at a time, in place: its samples on the first grid go as it moves
        for i, example in enumerate(examples):
            examples[i] = Example(example.name, [part.on_grid(*grid, near=True)
                                                 for part, grid in zip(example.parts, grids)])
    guides = None
    if placed is not None:
        guides = guides_on_grid(placed, maps, [grid for grid, _ in grids], nested or n_points,
                                [j * n_points for j in range(n_parts)],
                                config.landmark_weight, voxel)
    weight = config.smoothness_for(curves=False, guided=guides is not None)
    smoothness = Smoothness(weight, voxel) if weight > 0 else None
    state = CorrespondenceState(examples, grids,
                                scaling=config.scaling, guides=guides, smoothness=smoothness)
    return _with_objectives(state, voxel, config)


def _with_objectives(state: CorrespondenceState, voxel: float, config: BuildConfig):
    """(state, its two objectives, the mean voxel size, the data range of the aligned shapes)."""
    data_range = float(np.max(np.ptp(state.aligned_shapes().reshape(-1, 3), axis=0)))
    return state, objectives(config, voxel, data_range), voxel, data_range

