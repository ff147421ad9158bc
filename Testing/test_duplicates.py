"""A case given twice: named and refused before the optimisation unless --allow-duplicates.
Through the command line, on the shared hippocampi (hippocampus_010 and hippocampus_011 are one
label map twice)."""

import pytest
import SimpleITK as sitk

from common import HIPPOCAMPI, needs_hippocampi, run_cli_quietly as run

pytestmark = needs_hippocampi

FAST = ["--points", "162", "--baselines", "", "--specificity-samples", "200",
        "--surface-samples", "0", "--workers", "2"]


def hippocampus(number: int):
    return HIPPOCAMPI / f"hippocampus_{number:03d}.nii.gz"


def moved_copy(source, destination, shift_mm: float = 7.3):
    """The label map ``source`` written to ``destination`` (another format) with its origin
    moved: the same voxels, other bytes."""
    image = sitk.ReadImage(str(source))
    image.SetOrigin(tuple(o + shift_mm for o in image.GetOrigin()))
    sitk.WriteImage(image, str(destination))
    return destination


def test_identical_files_are_named_and_refused_before_anything_is_prepared(tmp_path):
    output = tmp_path / "out"
    inputs = [hippocampus(k) for k in (1, 3, 4, 10, 11)]
    refused = run("build", *inputs, "-o", output, *FAST)
    assert refused.returncode == 2, refused.stderr
    line = refused.stderr.strip().splitlines()[-1]
    assert str(hippocampus(10)) in line and str(hippocampus(11)) in line
    assert "identical files" in line and "--allow-duplicates" in line
    assert "remove all but one" in line
    assert "prepar" not in refused.stderr and "Traceback" not in refused.stderr
    assert not output.exists()                         # nothing written


@pytest.mark.slow
def test_a_moved_copy_in_another_format_is_refused_as_the_same_shape(tmp_path):
    """Other bytes, the same voxels: found by its shape in the initial correspondence, and the
    build stops before the optimisation starts."""
    copy = moved_copy(hippocampus(10), tmp_path / "moved.nrrd")
    output = tmp_path / "out"
    refused = run("build", *(hippocampus(k) for k in (1, 3, 4, 10)), copy, "-o", output, *FAST)
    assert refused.returncode == 2, refused.stderr
    line = refused.stderr.strip().splitlines()[-1]
    assert str(hippocampus(10)) in line and str(copy) in line
    assert "the same shape" in line and "--allow-duplicates" in line
    assert "initial objective" not in refused.stderr and "Traceback" not in refused.stderr
    assert not (output / "model.h5").exists()
