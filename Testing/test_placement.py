"""Where a surface model's sample points lie (``--placement``): farthest-point sampling, the
spherical triangulation, grids that cover the population's mean surface evenly, and a build
with them."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mdlshapemodel.config import BuildConfig
from mdlshapemodel.correspondence.placement import icosphere_level, surface_grids
from mdlshapemodel.correspondence.state import CorrespondenceState, Example, PartState
from mdlshapemodel.correspondence.sampling import (SphereLocator, farthest_points, icosphere,
                                                   spherical_triangles)
from mdlshapemodel.errors import ConfigError
from mdlshapemodel.model.shape_model import ShapeModel
from mdlshapemodel.prepare.sphere import SphereMap
from mdlshapemodel.prepare.surface import triangle_vertex_areas
from common import hippocampi, needs_hippocampi, run_cli


def plain_farthest(points, count, first):
    """Farthest-point sampling written out: each next point maximises its smallest distance."""
    chosen = list(range(first)) or [0]
    while len(chosen) < count:
        gaps = [min(np.linalg.norm(p - points[c]) for c in chosen) for p in points]
        chosen.append(int(np.argmax(gaps)))
    return chosen


@pytest.mark.parametrize("first", [0, 1, 5])
def test_farthest_points_are_the_plain_greedy_choice(first):
    points = np.random.default_rng(first).normal(size=(60, 3))
    assert farthest_points(points, 20, first).tolist() == plain_farthest(points, 20, first)


def test_farthest_points_refuses_impossible_counts():
    with pytest.raises(ValueError):
        farthest_points(np.zeros((5, 3)), 6)
    with pytest.raises(ValueError):
        farthest_points(np.zeros((5, 3)), 3, first=4)


def test_the_spherical_triangulation_is_a_closed_outward_surface_on_every_point():
    points = np.random.default_rng(2).normal(size=(300, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    triangles = spherical_triangles(points)
    assert sorted(np.unique(triangles)) == list(range(300))
    edges = {tuple(sorted(e)) for t in triangles for e in ((t[0], t[1]), (t[1], t[2]),
                                                           (t[2], t[0]))}
    assert 300 - len(edges) + len(triangles) == 2                    # Euler: a sphere
    a, b, c = (points[triangles[:, k]] for k in range(3))
    assert np.all(np.einsum("ij,ij->i", a, np.cross(b - a, c - a)) > 0)   # outward


def test_icosphere_levels_are_recognised():
    assert [icosphere_level(n) for n in (12, 42, 642, 2562, 643, 0)] == [0, 1, 3, 4, None, None]


def spiked(spike: float):
    """A sphere with a thin spike: most of the spike's area maps to a small cap of the sphere."""
    sphere, faces = icosphere(5)
    axis = np.array([0.0, 0.0, 1.0])
    radius = 10.0 + spike * np.exp(-np.sum((sphere - axis) ** 2, axis=1) / 0.01)
    return SphereMap(sphere * radius[:, None], faces, sphere)


def spread_of_areas(points, triangles):
    """The coefficient of variation of the area around each sample point (eq. 17's weights)."""
    areas = triangle_vertex_areas(points, triangles)
    return float(areas.std() / areas.mean())


def test_surface_grids_cover_a_thin_process_that_the_sphere_squeezes():
    population = [spiked(spike) for spike in (12.0, 14.0, 16.0)]
    sphere, cells = icosphere(3)
    state = CorrespondenceState([Example(str(i), [PartState(m.vertices, m.faces, m.sphere,
                                                            sphere, cells)])
                                 for i, m in enumerate(population)], [(sphere, cells)])
    (grid, triangles), = surface_grids(state, 162)
    np.testing.assert_array_equal(grid[:162], icosphere(2)[0])       # the coarse grid first
    assert len(np.unique(grid, axis=0)) == 642

    def on_mean(points):
        return population_mean_at(population, points)

    def at_the_spike(points):
        return int(np.sum(points[:, 2] > 0.95))

    # around the spike's tip (the sphere's pole), more points than an icosphere puts there, and
    # the areas around the points on the mean surface far more even
    assert at_the_spike(grid) > 2 * at_the_spike(sphere)
    assert spread_of_areas(on_mean(grid), triangles) < 0.7 * spread_of_areas(on_mean(sphere), cells)
    # the same population gives the same grid (a resumed build finds it again)
    again, = surface_grids(state, 162)
    np.testing.assert_array_equal(again[0], grid)


def population_mean_at(population, points):
    """The mean of the population's surfaces at sphere points (through their sphere maps)."""
    return np.mean([SphereLocator(m.sphere, m.faces).evaluate(m.vertices, points)[0]
                    for m in population], axis=0)


def test_the_placement_option_is_checked():
    assert BuildConfig().placement in ("sphere", "surface")
    with pytest.raises(ConfigError, match="placement"):
        BuildConfig(placement="even").validate()


@needs_hippocampi
def test_a_build_places_its_points_evenly_over_the_mean_surface(tmp_path):
    inputs = hippocampi(6)
    models = {}
    for placement in ("sphere", "surface"):
        output = tmp_path / placement
        result = run_cli("build", *inputs, "--label", "1,2", "-o", output, "--placement",
                         placement, "--baselines", "", "--max-time", "60")
        assert result.returncode == 0, result.stderr
        models[placement] = ShapeModel.load(output / "model.h5")
    even, sphere = models["surface"], models["sphere"]
    assert even.parameters.shape == sphere.parameters.shape == (2562, 3)
    np.testing.assert_allclose(even.parameters[:642], icosphere(3)[0], atol=1e-12)
    assert not np.allclose(even.parameters, sphere.parameters)
    # on the mean surface the points are spaced more evenly: the spread of each point's distance
    # to its nearest neighbour is smaller
    assert spread_of_spacing(even.mean) < 0.97 * spread_of_spacing(sphere.mean)


def spread_of_spacing(points):
    """The coefficient of variation of each point's distance to its nearest neighbour."""
    nearest = cKDTree(points).query(points, k=2)[0][:, 1]
    return float(nearest.std() / nearest.mean())
