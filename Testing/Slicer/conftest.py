"""The Slicer-side tests run in a virtualenv with slicer-core (the second one `.ci/run` makes);
elsewhere they are not collected (slicer-core pins its own vtk, so it never shares the main
virtualenv)."""

import importlib.util
import pathlib
import sys

import pytest

HERE = pathlib.Path(__file__).resolve().parent
SHARED = HERE.parents[2] / "shared" / "data"

if importlib.util.find_spec("slicer") is None or importlib.util.find_spec("slicer_core") is None:
    collect_ignore_glob = ["test_*.py"]
else:
    sys.path.insert(0, str(HERE))
    import harness

    harness.install()


@pytest.fixture
def scene():
    """A fresh real MRML scene as slicer.mrmlScene."""
    return harness.new_scene()


@pytest.fixture(scope="session")
def hippocampus_files():
    """Four of the shared hippocampus label maps (labels 1 and 2)."""
    files = sorted((SHARED / "hippocampus" / "labels").glob("*.nii.gz"))[:4]
    if len(files) < 4:
        pytest.skip(f"the shared data ({SHARED}) is not here")
    return files
