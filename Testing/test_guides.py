"""Landmarks as guides of the correspondence: their placing on the surfaces and the sphere, the
alignment they steer, their term of the objective and its gradient, and builds guided by them."""

import csv
import json
import re
from dataclasses import replace

import numpy as np
import pytest

from mdlshapemodel.correspondence.guides import Guides, guides_on_grid, place_landmarks
from mdlshapemodel.correspondence.sampling import icosphere
from mdlshapemodel.correspondence.smoothness import Smoothness
from mdlshapemodel.correspondence.strategies.fast import FieldRound, gradient_at
from mdlshapemodel.model.fitting import build_config_of
from mdlshapemodel.model.shape_model import ShapeModel
from mdlshapemodel.prepare.case import PreparedCase, PreparedPart
from mdlshapemodel.prepare.landmarks import Landmarks, on_surface
from mdlshapemodel.prepare.sphere import SphereMap, align_parameterizations
from mdlshapemodel.build import shape_model_of
from mdlshapemodel.config import (GUIDED_SMOOTHNESS, SMOOTHNESS, BuildConfig,
                                  OptimisationSettings)
from mdlshapemodel.correspondence.initial import initial_state
from mdlshapemodel.correspondence.strategies import optimise
from mdlshapemodel.correspondence.trace import Trace
from mdlshapemodel.correspondence.state import state_record
from common import central_difference, run_cli
from resuming import assert_same_record, optimised_with_checkpoints, resumed_from
from files import write_label_map
from synthetic import build_objectives, small_bump_top, small_mask, small_state

AXES = np.array([12.0, 7.0, 4.0])


def ellipsoid_case(name: str, rotation: np.ndarray = np.eye(3)) -> PreparedCase:
    """An ellipsoid (semi-axes AXES) whose sphere map is its icosphere turned by ``rotation``."""
    sphere, faces = icosphere(3)
    vertices = sphere * AXES
    return PreparedCase(name, [PreparedPart("", f"{name}.vtp",
                                            SphereMap(vertices, faces, sphere @ rotation.T))], 1.0)


def rotation_about(axis, degrees: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = np.radians(degrees)
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def test_a_landmark_is_put_at_the_closest_surface_point_and_its_sphere_image():
    sphere, faces = icosphere(3)
    vertices = sphere * AXES
    turned = sphere @ rotation_about([1, 2, 3], 40).T
    # on the surface at a vertex, and 2 mm off the surface along the x axis
    points = np.array([vertices[17] + 0.0, [AXES[0] + 2.0, 0.0, 0.0]])
    placed = on_surface(vertices, faces, turned, points)
    assert placed.distance[0] == pytest.approx(0.0, abs=1e-9)
    assert placed.distance[1] == pytest.approx(2.0, abs=1e-6)
    np.testing.assert_allclose(placed.surface[1], [AXES[0], 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(placed.sphere[0], turned[17], atol=1e-9)
    # the image under a map is the same barycentric point of the same triangle
    np.testing.assert_allclose(placed.on_sphere(sphere, faces)[0], sphere[17], atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(placed.sphere, axis=1), 1.0)


def test_landmarks_steer_the_alignment_of_the_parameterizations():
    """Two copies of one ellipsoid with the same sphere map, whose landmarks name places half a
    turn apart about its long axis (which the ellipsoid's symmetry allows): the first-order maps
    align the parameterizations as they are; the landmarks turn the second's by half a turn, so
    that each label's images nearly coincide (the first-order maps still pull a little)."""
    cases = [ellipsoid_case("a"), ellipsoid_case("b")]
    sphere, faces = icosphere(3)
    on_a = np.array([[AXES[0], 0, 0], [0, AXES[1], 0], [0, 0, AXES[2]]]) * [0.999, 1, 1]
    on_b = on_a @ rotation_about([1, 0, 0], 180).T
    marks = {"a": Landmarks(("x", "y", "z"), on_a), "b": Landmarks(("x", "y", "z"), on_b)}
    placed = place_landmarks(cases, marks)
    originals = [case.map for case in cases]
    plain = align_parameterizations(originals)
    guided = align_parameterizations(originals, landmarks=placed.images(0, originals))
    images_plain = placed.images(0, plain)
    images_guided = placed.images(0, guided)
    assert np.max(np.linalg.norm(images_plain[0] - images_plain[1], axis=1)) > 1.9
    assert np.max(np.linalg.norm(images_guided[0] - images_guided[1], axis=1)) < 0.15


def test_a_label_some_cases_lack_and_a_case_without_landmarks():
    cases = [ellipsoid_case(name, rotation_about([0, 0, 1], angle))
             for name, angle in (("a", 0), ("b", 20), ("c", -15))]
    tip = np.array([[AXES[0], 0.0, 0.0], [0.0, 0.0, AXES[2]]])
    marks = {"a": Landmarks(("tip", "top"), tip), "b": Landmarks(("tip",), tip[:1])}
    placed = place_landmarks(cases, marks)
    assert placed.labels == ("tip", "top")
    np.testing.assert_array_equal(placed.present, [[True, True], [True, False], [False, False]])
    images = placed.images(0, [case.map for case in cases])
    assert np.all(np.isnan(images[1][1])) and np.all(np.isnan(images[2]))
    aligned = [align_parameterizations([case.map for case in cases],
                                       landmarks=images)]
    grid, _ = icosphere(2)
    guides = guides_on_grid(placed, aligned, [grid], 42, [0], weight=2.0, scale=0.5)
    assert guides.indices.max() < 42 and len(set(guides.indices)) == 2
    np.testing.assert_allclose(guides.targets[0], tip, atol=1e-9)
    assert guides.far_from_surface(["a", "b", "c"]) == []
    assert place_landmarks(cases, {}) is None
    # a landmark 4 mm off the surface (8 voxels of 0.5 mm) is reported, with its distance
    off = {**marks, "c": Landmarks(("top",), np.array([[0.0, 0.0, AXES[2] + 4.0]]))}
    placed = place_landmarks(cases, off)
    far = guides_on_grid(placed, aligned, [grid], 42, [0], 2.0, 0.5).far_from_surface(
        ["a", "b", "c"])
    assert [(case, label) for case, label, _ in far] == [("c", "top")]
    assert far[0][2] == pytest.approx(4.0, abs=1e-6)


def test_each_label_is_guided_at_the_grid_vertex_nearest_its_place():
    """Three turned ellipsoids, landmarks at the tips of their axes: each label's guide is the
    candidate grid vertex nearest the mean of its images on the aligned spheres, and within
    the grid's spacing of every case's image."""
    cases = [ellipsoid_case(name, rotation_about([1, 1, 0], angle))
             for name, angle in (("a", 0), ("b", 25), ("c", -30))]
    tips = np.diag(AXES) * 0.999
    marks = {case.name: Landmarks(("x", "y", "z"), tips) for case in cases}
    placed = place_landmarks(cases, marks)
    maps = align_parameterizations([case.map for case in cases],
                                   landmarks=placed.images(0, [case.map for case in cases]))
    grid, _ = icosphere(2)
    guides = guides_on_grid(placed, [maps], [grid], 42, [0], weight=1.0, scale=1.0)
    images = np.stack(placed.images(0, maps))                     # (cases, labels, 3)
    for label, vertex in enumerate(guides.indices):
        place = images[:, label].mean(axis=0)
        assert vertex == int(np.argmax(grid[:42] @ place)), placed.labels[label]
        angles = np.arccos(np.clip(images[:, label] @ grid[vertex], -1.0, 1.0))
        assert angles.max() < 0.6, (placed.labels[label], angles)


def guided_state(weight: float = 3.0, smoothness: float = 0.0):
    """The small synthetic state with two guided labels (one lacking in case 1), targets off
    its current samples (and the smoothness prior of that weight, if any)."""
    state = small_state()
    state.smoothness = Smoothness(smoothness, 0.8) if smoothness else None
    raw = state.raw_shapes()
    indices = np.array([5, 40])
    targets = raw[:, indices] + np.random.default_rng(0).normal(0.0, 1.5, (state.n_shapes, 2, 3))
    present = np.ones((state.n_shapes, 2), dtype=bool)
    present[1, 0] = False
    state.guides = Guides(("a", "b"), indices, targets, present, weight, 0.8)
    state.objective = build_objectives(state)[1]
    state.rebuild()
    return state



def test_the_priors_default_weight_is_the_guided_one_where_landmarks_guide():
    """Unless --smoothness is given, the initial correspondence of surfaces gets the prior at
    GUIDED_SMOOTHNESS where landmarks guide and at SMOOTHNESS where none do; the model records
    the weight as applied (``fit`` applies the same); a weight given is applied either way."""
    cases = [ellipsoid_case(name, rotation_about([1, 1, 0], angle))
             for name, angle in (("a", 0), ("b", 25), ("c", -30))]
    marks = {case.name: Landmarks(("x", "y", "z"), np.diag(AXES) * 0.999) for case in cases}
    config = BuildConfig(points=42, coarse_points=0, workers=1)
    guided, *_ = initial_state(cases, config, marks)
    plain, *_ = initial_state(cases, config)
    assert guided.guides is not None and plain.guides is None
    assert GUIDED_SMOOTHNESS != SMOOTHNESS
    assert guided.smoothness.weight == GUIDED_SMOOTHNESS
    assert plain.smoothness.weight == SMOOTHNESS
    for state in (guided, plain):
        model = shape_model_of(state, config, 0.0, 1.0, 1.0)
        assert build_config_of(model).smoothness == state.smoothness.weight
    given = replace(config, smoothness=0.3)
    for landmarks in (marks, None):
        assert initial_state(cases, given, landmarks)[0].smoothness.weight == 0.3

def test_the_guides_term_is_the_direct_sum_and_part_of_every_value():
    state = guided_state()
    raw = state.raw_shapes()
    guides = state.guides
    direct = sum(guides.weight / 2 / guides.scale ** 2
                 * np.sum((raw[i, guides.indices[k]] - guides.targets[i, k]) ** 2)
                 for i in range(state.n_shapes) for k in range(2) if guides.present[i, k])
    assert state.guide_cost() == pytest.approx(direct, rel=1e-12)
    description = state.objective(state.covariance())
    assert state.value() == pytest.approx(description + direct, rel=1e-12)
    # a trial of one example: its unposed samples change the term, its pose does not
    example = state.examples[2]
    moved = raw[2] + 0.3
    trial = state.value(2, example.pose.apply(moved), moved)
    expected_term = direct - guides.cost(2, raw[2]) + guides.cost(2, moved)
    assert trial == pytest.approx(state.objective(state.covariance(2, example.pose.apply(moved)))
                                  + expected_term, rel=1e-12)
    with pytest.raises(ValueError, match="unposed"):
        state.value(2, example.pose.apply(moved))
    with pytest.raises(ValueError, match="unposed"):
        with state.trial_shapes(state.shapes):
            pass
    np.testing.assert_allclose(np.nansum(guides.distances(raw) ** 2 * guides.present),
                               direct * 2 * guides.scale ** 2 / guides.weight)


def test_the_fast_round_gradient_with_guides_matches_finite_differences():
    state = guided_state()
    round_ = FieldRound(state, [0, 1, 3], level=1, support=2.0)
    rng = np.random.default_rng(5)
    upper = round_.limit
    x = rng.uniform(-0.3, 0.3, round_.size) * np.where(np.isfinite(upper), upper, 0.05)

    def value(x):
        trial = round_.trial(x)
        return gradient_at(state, trial.shapes, trial.unposed)[0]

    trial = round_.trial(x)
    analytic = round_.gradient(trial, gradient_at(state, trial.shapes, trial.unposed)[1])
    chosen = np.concatenate([rng.choice(round_.size, 12, replace=False),
                             round_.pose_index.ravel()])
    for k in chosen:
        assert analytic[k] == pytest.approx(central_difference(value, x, k), rel=2e-5,
                                            abs=1e-6)


def test_a_guided_optimisation_starts_on_the_landmarks_and_resumes_exactly():
    """The staged fast strategy runs a landmark phase first (its F is the guides' term and the
    smoothness prior, which falls), carries the guides and the prior to the coarse grid, and ends
    as the uninterrupted run from a checkpoint of each phase."""
    settings = OptimisationSettings(strategy="fast", max_time=1e6, fixed_fraction=0.5,
                                    coarse_points=42, max_sweeps=3)
    state = guided_state(smoothness=0.2)
    start = state.guide_cost()
    final, trace, saved = optimised_with_checkpoints(state, settings)
    phases = [point.phase for point, *_ in saved]
    assert phases[0] == "coarse landmarks" and "coarse integrated" in phases
    landmark_rows = [row for row in trace.rows if row.phase == "coarse landmarks"]
    assert landmark_rows and landmark_rows[-1].objective < landmark_rows[0].objective
    assert state.guide_cost() < start and state.smoothness_energy() > 0
    expected = state_record(state)
    for phase in ("coarse landmarks", "coarse fixed"):
        resumed = guided_state(smoothness=0.2)
        value, _ = resumed_from(resumed, settings, saved[phases.index(phase)])
        assert value == final, phase
        assert_same_record(state_record(resumed), expected)


@pytest.mark.parametrize("strategy, options", [
    ("one-at-a-time", dict(max_sweeps=2)), ("one-at-a-time-pose", dict(max_sweeps=2)),
    ("multiscale", dict(max_sweeps=2)),
    ("multiresolution", dict(max_sweeps=1, simplex_evaluations=300, simplex_step=0.3))])
def test_every_strategy_draws_the_landmarks_to_their_sample_points(strategy, options):
    """The paper's strategies see the guides' term in every trial's F: their landmark phase
    lowers it, and F at the end (description length plus the term) is below its start."""
    state = guided_state()
    start = state.guide_cost()
    settings = OptimisationSettings(strategy=strategy, max_time=1e6, fixed_fraction=0.5,
                                    pose_evaluations=20, **options)
    trace = Trace()
    optimise(state, build_objectives(state), settings, np.random.default_rng(3), trace)
    landmark_rows = [row.objective for row in trace.rows if row.phase == "landmarks"]
    assert landmark_rows[0] == pytest.approx(start) and landmark_rows[-1] < 0.9 * start
    assert state.guide_cost() < start


def test_guides_carried_to_rows_of_a_coarser_grid():
    guides = Guides(("a", "b"), np.array([3, 170]), np.zeros((2, 2, 3)),
                    np.ones((2, 2), dtype=bool), 1.0, 1.0)
    rows = np.concatenate([np.arange(0, 42), np.arange(162, 204)])
    np.testing.assert_array_equal(guides.on_rows(rows).indices, [3, 50])
    with pytest.raises(ValueError, match="b"):
        guides.on_rows(np.arange(42))


def test_a_model_keeps_its_landmarks(tmp_path):
    shapes = np.random.default_rng(1).normal(size=(4, 10, 3))
    model = ShapeModel.from_shapes(shapes, np.full(10, 0.1))
    model.landmarks = {"tip": 7, "base": 2}
    model.save(tmp_path / "model.h5")
    loaded = ShapeModel.load(tmp_path / "model.h5")
    assert loaded.landmarks == {"tip": 7, "base": 2}
    np.testing.assert_array_equal(loaded.landmark_points()["tip"], loaded.mean[7])
    model.landmarks = {"tip": 10}
    with pytest.raises(ValueError, match="landmark rows"):
        model.check()


# ---------------------------------------------------------------- builds through the CLI

POSITIONS = np.linspace(-0.6, 0.6, 5)


def write_guided_population(folder):
    """Five bumpy ellipsoids (label maps, 1 mm voxels, origin 0) and a landmark folder: the bump's
    top in every case, and the +x end of the long axis in all but the last; RAS in one case's
    .fcsv."""
    (folder / "labels").mkdir(parents=True)
    (folder / "marks").mkdir()
    for k, position in enumerate(POSITIONS):
        write_label_map(folder / "labels" / f"s{k}.nii.gz", small_mask(float(position)))
        tip = small_bump_top(float(position))
        end = np.array([(28 - 1) / 2.0 + 10.0, (20 - 1) / 2.0, (18 - 1) / 2.0])
        if k == 0:
            lines = ["# Markups fiducial file version = 4.11", "# CoordinateSystem = RAS",
                     "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID"]
            for n, (label, point) in enumerate((("tip", tip), ("end", end))):
                ras = point * [-1, -1, 1]
                lines.append(f"m{n},{ras[0]},{ras[1]},{ras[2]},0,0,0,1,1,1,0,{label},,")
            (folder / "marks" / f"s{k}.fcsv").write_text("\n".join(lines) + "\n")
            continue
        rows = [("tip", tip)] + ([("end", end)] if k < len(POSITIONS) - 1 else [])
        with open(folder / "marks" / f"s{k}.csv", "w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(["label", "x", "y", "z"])
            writer.writerows([label, *point] for label, point in rows)
    return folder


@pytest.mark.slow
def test_a_guided_build_puts_its_corresponded_landmarks_on_the_given_ones(tmp_path):
    data = write_guided_population(tmp_path)
    common = ["--points", 162, "--coarse-points", 42, "--workers", 1, "--max-time", 60,
              "--specificity-samples", 200, "--surface-samples", 0, "--evaluation-modes", 2,
              "--no-cache", "-q"]
    guided = run_cli("build", data / "labels", "-o", tmp_path / "guided", "--landmarks",
                 data / "marks", *common)
    assert guided.returncode == 0, guided.stderr
    rows = list(csv.DictReader(open(tmp_path / "guided" / "landmarks.csv")))
    assert {(row["case"], row["label"]) for row in rows} == {
        (f"s{k}", label) for k in range(5) for label in ("end", "tip")}
    given = [row for row in rows if row["distance_mm"]]
    assert len(given) == 9                       # s4 lacks "end"
    distances = np.array([float(row["distance_mm"]) for row in given])
    assert distances.max() < 1.0                  # within a voxel of the given landmarks
    for row in given:
        point = np.array([float(row[c]) for c in "xyz"])
        target = np.array([float(row[f"given_{c}"]) for c in "xyz"])
        assert np.linalg.norm(point - target) == pytest.approx(float(row["distance_mm"]),
                                                               abs=1e-5)
    tips = {row["case"]: np.array([float(row[f"given_{c}"]) for c in "xyz"])
            for row in given if row["label"] == "tip"}
    np.testing.assert_allclose(tips["s0"], small_bump_top(POSITIONS[0]), atol=1e-5)   # RAS read
    model = ShapeModel.load(tmp_path / "guided" / "model.h5")
    assert sorted(model.landmarks) == ["end", "tip"]
    # the prior's default weight where landmarks guide, recorded as applied
    assert build_config_of(model).smoothness == GUIDED_SMOOTHNESS
    metrics = json.loads((tmp_path / "guided" / "metrics.json").read_text())
    assert metrics["landmarks"]["given"] == 9
    assert metrics["landmarks"]["distance_mm"]["max"] == pytest.approx(distances.max())
    assert {label: item["cases"] for label, item in metrics["landmarks"]["per_label"].items()} == {
        "end": 4, "tip": 5}
    assert "Landmarks that guided the correspondence" in (tmp_path / "guided" /
                                                         "report.html").read_text()
    log = (tmp_path / "guided" / "build.log").read_text()
    assert "2 landmark labels guide the correspondence (9 landmarks of 5 cases" in log
    # fit predicts a new case's landmarks: where its fitted correspondence puts them
    new = write_label_map(tmp_path / "n1.nii.gz", small_mask(0.3))
    fitted = run_cli("fit", tmp_path / "guided" / "model.h5", new, "-o", tmp_path / "fitted")
    assert fitted.returncode == 0, fitted.stderr
    predicted = {row["label"]: np.array([float(row[c]) for c in "xyz"])
                 for row in csv.DictReader(open(tmp_path / "fitted" / "landmarks.csv"))}
    assert sorted(predicted) == ["end", "tip"]
    assert np.linalg.norm(predicted["tip"] - small_bump_top(0.3)) < 2.0
    # unguided, the same sample point is not on the bump's top in every case
    plain = run_cli("build", data / "labels", "-o", tmp_path / "plain", *common)
    assert plain.returncode == 0, plain.stderr
    assert not (tmp_path / "plain" / "landmarks.csv").exists()
    assert build_config_of(ShapeModel.load(tmp_path / "plain" / "model.h5")).smoothness \
        == SMOOTHNESS
    from files import polydata_triangles

    row = model.landmarks["tip"]
    off = [np.linalg.norm(polydata_triangles(tmp_path / "plain" / "correspondence"
                                             / f"s{k}.vtp")[0][row] - small_bump_top(position))
           for k, position in enumerate(POSITIONS)]
    assert max(off) > 2.0 * distances.max()


def test_bad_landmark_files_are_refused_before_anything_is_written(tmp_path):
    data = tmp_path / "labels"
    data.mkdir()
    for k, position in enumerate(POSITIONS[:3]):
        write_label_map(data / f"s{k}.nii.gz", small_mask(float(position)))
    marks = tmp_path / "marks"
    marks.mkdir()
    (marks / "s1.csv").write_text("label,x,y,z\ntip,1,2,three\n")
    result = run_cli("build", data, "-o", tmp_path / "out", "--landmarks", marks, "--workers", 1)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "s1.csv" in result.stderr and "not numbers" in result.stderr
    assert not (tmp_path / "out").exists()
    (marks / "s1.csv").unlink()
    result = run_cli("build", data, "-o", tmp_path / "out", "--landmarks", marks, "--workers", 1)
    assert result.returncode == 2 and "no landmark file named after a case" in result.stderr
    result = run_cli("build", data, "-o", tmp_path / "out", "--landmarks", tmp_path / "none",
                 "--workers", 1)
    assert result.returncode == 2 and "no such landmark folder" in result.stderr
    assert not (tmp_path / "out").exists()
    # RAS coordinates in a CSV that does not say so: far from the surface, and the user is told
    top = small_bump_top(float(POSITIONS[1])) * [-1, -1, 1]
    (marks / "s1.csv").write_text("label,x,y,z\ntop,{},{},{}\n".format(*top))
    result = run_cli("build", data, "-o", tmp_path / "out", "--landmarks", marks, "--workers", 1,
                     "--points", 42, "--max-time", 5, "--baselines", "", "--no-cache",
                     "--specificity-samples", 100, "--surface-samples", 0)
    assert result.returncode == 0, result.stderr
    assert re.search(r"landmark top of s1 is [\d.]+ mm from the case's surface", result.stderr)


def test_landmarks_and_the_smoothness_prior_are_refused_for_2d_curves(tmp_path):
    from mdlshapemodel.demo import write_demo_curves

    paths = write_demo_curves(tmp_path / "curves", n_subjects=3)
    marks = tmp_path / "marks"
    marks.mkdir()
    (marks / f"{paths[0].name.split('.')[0]}.csv").write_text("label,x,y,z\ntip,1,2,0\n")
    for option in (["--landmarks", marks], ["--smoothness", "0.01"]):
        result = run_cli("build", tmp_path / "curves", "-o", tmp_path / "out", "--workers", 1,
                         "--no-cache", *option)
        assert result.returncode == 2 and "Traceback" not in result.stderr
        assert "these inputs are 2-D curves" in result.stderr, result.stderr
