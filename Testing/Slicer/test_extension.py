"""The extension's CMake files configured against a stand-in Slicer (Testing/Slicer/cmake: the
macros' checks and copies, no Slicer build), and the module finding its resources in the tree
that gives, as in an installed extension."""

import shutil
import subprocess
import sys

import pytest

import harness

ROOT = harness.HERE.parents[1]
STANDIN = harness.HERE / "cmake"
MODULES = "lib/Slicer-5.10/qt-scripted-modules"
CMAKE = shutil.which("cmake")
pytestmark = pytest.mark.skipif(CMAKE is None, reason="cmake is not installed")


def configure(source, build):
    return subprocess.run([CMAKE, "-S", str(source), "-B", str(build), f"-DSlicer_DIR={STANDIN}"],
                          capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def build_tree(tmp_path_factory):
    build = tmp_path_factory.mktemp("extension-build")
    done = configure(ROOT, build)
    assert done.returncode == 0, done.stdout + done.stderr
    return build


def test_configuring_lists_every_package_file_and_copies_the_module_with_its_resources(build_tree):
    listed = (build_tree / "standin-MDLShapeModel-scripts.txt").read_text().split()
    package = ROOT / "MDLShapeModel"
    tree = ["MDLShapeModel.py"] + [str(p.relative_to(package))
                                   for folder in ("MDLShapeModelLib", "mdlshapemodel")
                                   for p in (package / folder).rglob("*.py")]
    assert sorted(listed) == sorted(tree)
    modules = build_tree / MODULES
    for relative in tree:
        assert (modules / relative).read_bytes() == (package / relative).read_bytes()
    for resource in ("UI/MDLShapeModel.ui", "Icons/MDLShapeModel.png", "requirements.txt"):
        assert (modules / "Resources" / resource).is_file()
    assert (build_tree / "standin-python-unittests.txt").read_text().split() == ["MDLShapeModel.py"]
    assert "category=Shape Analysis" in (build_tree / "standin-extension.txt").read_text()


def test_the_built_module_finds_its_resources_next_to_itself(build_tree):
    modules = build_tree / MODULES
    code = (f"import sys; sys.path.insert(0, {str(harness.HERE)!r}); import harness; "
            f"harness.install(); sys.path.insert(0, {str(modules)!r}); import MDLShapeModel; "
            "print(MDLShapeModel.__file__); print(MDLShapeModel.resourcePath('UI/MDLShapeModel.ui'))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    module_file, ui_file = done.stdout.strip().splitlines()[-2:]
    assert module_file == str(modules / "MDLShapeModel.py")
    assert ui_file == str(modules / "Resources" / "UI" / "MDLShapeModel.ui")


def test_a_listed_file_that_is_missing_fails_the_configuration(tmp_path):
    source = tmp_path / "source"
    source.mkdir()
    shutil.copy(ROOT / "CMakeLists.txt", source)
    shutil.copytree(ROOT / "MDLShapeModel", source / "MDLShapeModel")
    (source / "MDLShapeModel" / "mdlshapemodel" / "demo.py").unlink()
    done = configure(source, tmp_path / "build")
    assert done.returncode != 0
    said = " ".join((done.stdout + done.stderr).split())   # CMake wraps its messages
    assert "nonexistent file 'mdlshapemodel/demo.py'" in said
