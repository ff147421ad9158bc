"""A batch with every kind of bad input: each gets one clear line, the rest of the batch goes on."""

import numpy as np
import SimpleITK as sitk

from mdlshapemodel.prepare.io import read_csv, write_polydata
from mdlshapemodel.correspondence.sampling import icosphere

from synthetic import small_mask, torus
from test_cli import run


def write_image(path, array):
    sitk.WriteImage(sitk.GetImageFromArray(array.astype(np.uint8)), str(path))


def test_every_bad_input_gets_one_line_and_the_build_goes_on(tmp_path):
    folder = tmp_path / "inputs"
    folder.mkdir()
    for k, position in enumerate((-0.5, 0.0, 0.5)):
        write_image(folder / f"good_{k}.nii.gz", small_mask(position))
    sphere, faces = icosphere(2)
    sphere = sphere * 10.0
    expected = {}

    write_image(folder / "empty.nii.gz", np.zeros((12, 12, 12)))
    expected["empty"] = "empty"
    write_image(folder / "other_label.nii.gz", small_mask(0.0) * 5)
    expected["other_label"] = "label 1 not present (labels found: 5)"
    (folder / "not_an_image.nii.gz").write_bytes(b"plain text, not gzip")
    expected["not_an_image"] = "not a readable image"
    write_polydata(folder / "with_holes.vtp", sphere, faces[5:])
    expected["with_holes"] = "boundary edges (holes)"
    extra = np.vstack([sphere, [[30.0, 0.0, 0.0]]])
    write_polydata(folder / "non_manifold.ply", extra,
                   np.vstack([faces, [[faces[0, 0], faces[0, 1], len(sphere)]]]))
    expected["non_manifold"] = "non-manifold edges"
    write_polydata(folder / "torus.vtk", *torus())
    expected["torus"] = "genus 1"
    nan_points = sphere.copy()
    nan_points[7] = np.nan
    write_polydata(folder / "nan_points.vtp", nan_points, faces)
    expected["nan_points"] = "non-finite"
    write_polydata(folder / "two_spheres.stl", np.vstack([sphere, sphere + 50.0]),
                   np.vstack([faces, faces + len(sphere)]))
    expected["two_spheres"] = "2 disconnected components"
    two_blobs = np.zeros((20, 20, 40), bool)
    two_blobs[5:15, 5:15, 3:15] = True
    two_blobs[5:15, 5:15, 25:37] = True
    write_image(folder / "two_objects.nii.gz", two_blobs)
    expected["two_objects"] = "2 disjoint objects"

    out = tmp_path / "out"
    result = run("build", folder, "-o", out, "--label", 1, "--points", 42, "--max-sweeps", 1,
                 "--workers", 2, "--specificity-samples", 50, "--evaluation-modes", 1)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    rejected = {row["case"]: row["reason"] for row in read_csv(out / "rejected.csv")}
    assert set(rejected) == set(expected)
    for name, phrase in expected.items():
        lines = [line for line in result.stderr.splitlines() if f"/{name}." in line]
        assert len(lines) == 1, (name, lines)
        assert phrase in lines[0] and phrase in rejected[name], (name, lines[0])
    assert sorted(p.stem for p in (out / "correspondence").iterdir()) == ["good_0", "good_1",
                                                                         "good_2"]
    strict = run("build", folder, "-o", tmp_path / "strict", "--label", 1, "--points", 42,
                 "--workers", 2, "--strict")
    assert strict.returncode == 2 and "strict" in strict.stderr


def test_a_missing_label_map_is_a_rejection_that_says_so(tmp_path):
    """Through the Python API (the CLI checks paths before), a file that is not there is a
    rejection with a plain reason, not SimpleITK's message."""
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.prepare import prepare_case

    missing = tmp_path / "gone.nii.gz"
    result = prepare_case(str(missing), BuildConfig())
    assert result.name == "gone"
    assert "no such file" in result.reason
    write_image(missing, small_mask(0.0))
    assert not hasattr(prepare_case(str(missing), BuildConfig(cache_dir="")), "reason")


def test_a_bug_while_preparing_stops_the_build_naming_the_case(tmp_path, monkeypatch):
    """Only problems of the input are rejections: an exception of our own code (here a
    ZeroDivisionError planted in the sphere map) stops the build with a message that says it is a
    bug and names the case, and the traceback goes to build.log."""
    import pytest

    from mdlshapemodel import BuildConfig, InternalError, build_model
    from mdlshapemodel.prepare import case as preparation, prepare_case

    folder = tmp_path / "inputs"
    folder.mkdir()
    for k, position in enumerate((-0.5, 0.0, 0.5)):
        write_image(folder / f"case_{k}.nii.gz", small_mask(position))

    def broken_sphere_map(vertices, faces, **options):
        raise ZeroDivisionError("planted")

    monkeypatch.setattr(preparation, "sphere_map", broken_sphere_map)
    with pytest.raises(ZeroDivisionError):
        prepare_case(str(folder / "case_0.nii.gz"), BuildConfig(cache_dir=""))
    output = tmp_path / "out"
    with pytest.raises(InternalError) as raised:
        build_model([folder], output, BuildConfig(workers=1, cache_dir="", points=42))
    message = str(raised.value)
    assert "case_0.nii.gz" in message and "bug" in message and "ZeroDivisionError" in message
    log = (output / "build.log").read_text()
    assert "Traceback" in log and "broken_sphere_map" in log
    assert not (output / "model.h5").exists()
    # a bug is not an input error: code that rejects inputs by catching those lets it through
    from mdlshapemodel import MDLShapeModelError

    assert not isinstance(raised.value, MDLShapeModelError)
