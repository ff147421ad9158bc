"""Integration tests on the shared real data (skipped when ../shared/data is absent)."""

from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from mdlshapemodel import BuildConfig, build_model
from mdlshapemodel.prepare.io import read_csv
from mdlshapemodel.prepare import prepare_case
from mdlshapemodel.model.shape_model import ShapeModel
from mdlshapemodel.prepare.sphere import orientation, solid_angles
from mdlshapemodel.prepare.surface import topology

from common import DATA, HIPPOCAMPI

pytestmark = pytest.mark.skipif(not HIPPOCAMPI.is_dir(),
                                reason=f"shared hippocampus data not found at {HIPPOCAMPI}")


def hippocampus(number: int) -> Path:
    return HIPPOCAMPI / f"hippocampus_{number:03d}.nii.gz"


@pytest.mark.parametrize("number", [1, 3, 4])
def test_hippocampus_surface_and_sphere_map(number):
    case = prepare_case(str(hippocampus(number)), BuildConfig(labels=[1, 2]))
    assert not hasattr(case, "reason"), getattr(case, "reason", "")
    mapped = case.map
    assert topology(mapped.vertices, mapped.faces).is_sphere_like
    assert np.all(orientation(mapped.sphere, mapped.faces) > 0)
    assert np.sum(solid_angles(mapped.sphere, mapped.faces)) == pytest.approx(4 * np.pi, rel=1e-9)
    assert mapped.quality["mean_abs_log_area_ratio"] <= 0.3
    assert mapped.quality["p95_abs_log_area_ratio"] <= 1.0
    # the surface lies on the label map's boundary: its bounding box matches the mask's (mm)
    image = sitk.ReadImage(str(hippocampus(number)))
    index = np.argwhere(sitk.GetArrayFromImage(image) > 0)[:, ::-1].astype(float)
    voxels = np.array([image.TransformContinuousIndexToPhysicalPoint(p) for p in index])
    np.testing.assert_allclose(mapped.vertices.min(axis=0), voxels.min(axis=0), atol=1.5)
    np.testing.assert_allclose(mapped.vertices.max(axis=0), voxels.max(axis=0), atol=1.5)


def test_single_label_and_missing_label():
    one = prepare_case(str(hippocampus(1)), BuildConfig(labels=[2]))
    both = prepare_case(str(hippocampus(1)), BuildConfig(labels=[1, 2]))
    assert len(one.map.vertices) < len(both.map.vertices)
    missing = prepare_case(str(hippocampus(1)), BuildConfig(labels=[3]))
    assert "label 3 not present" in missing.reason and "1, 2" in missing.reason


@pytest.mark.slow
def test_small_hippocampus_build_is_faithful_and_fold_free(tmp_path):
    inputs = [hippocampus(n) for n in (1, 3, 4, 6, 7)]
    config = BuildConfig(labels=[1, 2], points=642, max_time=10, specificity_samples=500,
                         evaluation_modes=3)
    result = build_model(inputs, tmp_path, config)
    assert result.metrics["n_shapes"] == 5
    cases = read_csv(tmp_path / "cases.csv")
    assert max(float(c["mean_distance_voxels"]) for c in cases) < 0.5
    # every corresponded mesh is a homeomorphic image of the grid: no flipped triangle
    triangles = ShapeModel.load(tmp_path / "model.h5").triangles     # the grid's triangles
    state = np.load(tmp_path / "checkpoint.npz")
    for i in range(5):
        positions = state[f"positions_{i}_0"]
        assert np.all(orientation(positions, triangles) > 0)
    assert result.final_objective <= result.initial_objective


FEMUR = DATA / "femurs" / "m3_lfemur_mm.stl"


def voxelised(path: Path, spacing: float, output: Path) -> Path:
    """A label map (NIfTI) of the inside of a closed mesh file."""
    from mdlshapemodel.prepare.io import read_mesh
    from mdlshapemodel.prepare.surface import mesh_to_mask

    mask, origin = mesh_to_mask(*read_mesh(path), spacing)
    label_map = sitk.GetImageFromArray(mask)
    label_map.SetSpacing((spacing,) * 3)
    label_map.SetOrigin(tuple(float(o) for o in origin))
    sitk.WriteImage(label_map, str(output))
    return output


@pytest.mark.skipif(not FEMUR.is_file(), reason=f"shared femur not found at {FEMUR}")
def test_a_femur_label_map_at_half_a_millimetre_maps_at_the_sampling_grids_resolution(tmp_path):
    """A big bone: 345 x 200 x 130 voxels, a contour of about 150,000 vertices. Prepared at the
    resolution the sampling grid needs (BuildConfig.target_vertices), fold-free, and close to
    the bone's own surface."""
    from mdlshapemodel.prepare.io import read_mesh
    from mdlshapemodel.prepare.surface import point_surface_distances

    path = voxelised(FEMUR, 0.5, tmp_path / "femur.nii.gz")
    config = BuildConfig()
    case = prepare_case(str(path), config)
    assert not hasattr(case, "reason"), getattr(case, "reason", "")
    mapped = case.map
    assert abs(len(mapped.vertices) - config.target_vertices) < 0.1 * config.target_vertices
    assert np.all(orientation(mapped.sphere, mapped.faces) > 0)
    assert np.sum(solid_angles(mapped.sphere, mapped.faces)) == pytest.approx(4 * np.pi, rel=1e-9)
    assert mapped.quality["mean_abs_log_area_ratio"] <= 0.3
    bone, bone_faces = read_mesh(FEMUR)
    assert np.mean(point_surface_distances(mapped.vertices, bone, bone_faces)) < 0.25  # half a voxel


@pytest.mark.slow
def test_hippocampi_as_head_and_tail_from_labels_and_from_one_file_per_part(tmp_path):
    """The shared hippocampi as two parts, head (label 1) and body/tail (label 2): from the label
    maps with --part, and split into one file per part listed in a manifest: the same model."""
    from synthetic import split_into_part_files

    paths = [hippocampus(n) for n in (1, 3, 4, 6, 7)]
    manifest = split_into_part_files(paths, {"head": 1, "tail": 2}, tmp_path)
    settings = dict(points=162, max_sweeps=2, surface_samples=0, specificity_samples=200,
                    workers=1, cache_dir="")
    by_labels = build_model(paths, tmp_path / "labels",
                            BuildConfig(parts=["head=1", "tail=2"], **settings))
    by_files = build_model([], tmp_path / "files", BuildConfig(**settings),
                           manifest=manifest)
    for result in (by_labels, by_files):
        assert result.model.part_names == ["head", "tail"] and not result.rejected
        assert result.final_objective < result.initial_objective
    assert np.array_equal(by_labels.model.mean, by_files.model.mean)
    assert np.array_equal(by_labels.model.scores, by_files.model.scores)
    # the head is the front of the hippocampus: its points and the tail's lie apart
    mean = ShapeModel.load(tmp_path / "files" / "model.h5").mean
    head, tail = mean[:162].mean(axis=0), mean[162:].mean(axis=0)
    assert np.linalg.norm(head - tail) > 10.0
    assert len(read_csv(tmp_path / "files" / "cases.csv")) == 5
