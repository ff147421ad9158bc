"""A build's files are whole or absent, and a build never mixes with an earlier one in the same
folder: it is refused unless told to replace it, and then only the earlier build's files go."""

import os

import numpy as np
import pytest
import SimpleITK as sitk

from mdlshapemodel import ShapeModel
from mdlshapemodel.folders import BUILD_FILES, BuildFolder
from mdlshapemodel.prepare.io import write_csv, written_whole

from common import run_cli
from synthetic import small_mask

QUICK = ["--points", "42", "--baselines", "", "--max-sweeps", "2", "--evaluation-modes", "2",
         "--specificity-samples", "50", "--workers", "1", "-q"]


def test_a_file_is_replaced_only_when_written_whole(tmp_path):
    target = tmp_path / "table.csv"
    write_csv(target, ["a"], [[1]])
    with pytest.raises(RuntimeError):
        with written_whole(target) as temporary:
            temporary.write_text("half")
            raise RuntimeError("killed while writing")
    assert target.read_text().splitlines() == ["a", "1"]         # the old file, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["table.csv"]   # no temporary left


@pytest.fixture(scope="module")
def labels(tmp_path_factory):
    folder = tmp_path_factory.mktemp("labels")
    for k, position in enumerate(np.linspace(-0.6, 0.6, 3)):
        image = sitk.GetImageFromArray(small_mask(float(position)).astype(np.uint8))
        sitk.WriteImage(image, str(folder / f"case_{k}.nii.gz"))
    return folder


def build(labels, output, *extra):
    return run_cli("build", labels, "-o", output, *QUICK, *extra)


@pytest.mark.slow
def test_a_second_build_into_the_same_folder_is_refused_unless_overwrite(labels, tmp_path):
    output = tmp_path / "out"
    (output / "inputs").mkdir(parents=True)
    (output / "inputs" / "mine.txt").write_text("the user's")
    (output / "notes.txt").write_text("the user's")
    first = build(labels, output)
    assert first.returncode == 0, first.stderr
    # every file of a build but landmarks.csv and baselines.json, which a build guided by
    # landmarks and one with baselines write
    assert ({p.name for p in BuildFolder(output).previous_build()}
            == set(BUILD_FILES) - {"landmarks.csv", "baselines.json"})
    assert not [p for p in output.rglob("*") if ".partial" in p.name]
    assert not BuildFolder(output).surfaces_file.exists()     # the build's own, removed at its end
    model = (output / "model.h5").read_bytes()
    stamp = os.stat(output / "model.h5").st_mtime_ns

    again = build(labels, output)
    assert again.returncode == 2
    assert "holds an earlier build" in again.stderr and "--overwrite" in again.stderr
    assert "Traceback" not in again.stderr
    assert os.stat(output / "model.h5").st_mtime_ns == stamp       # nothing touched

    (output / "correspondence" / "stale_case.vtp").write_text("of the earlier build")
    (output / "landmarks.csv").write_text("case,label,x,y,z\n")          # as a guided build's
    (output / "baselines.json").write_text("{}")               # as a build's with baselines
    replaced = build(labels, output, "--overwrite")
    assert replaced.returncode == 0, replaced.stderr
    assert not (output / "correspondence" / "stale_case.vtp").exists()   # the earlier build's
    assert not (output / "landmarks.csv").exists() and not (output / "baselines.json").exists()
    assert (output / "notes.txt").read_text() == "the user's"            # not the build's
    assert (output / "inputs" / "mine.txt").read_text() == "the user's"
    (tmp_path / "first.h5").write_bytes(model)
    first_model, replacing = ShapeModel.load(tmp_path / "first.h5"), ShapeModel.load(output / "model.h5")
    np.testing.assert_array_equal(first_model.mean, replacing.mean)   # the same build again
