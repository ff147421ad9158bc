"""The 3D Slicer extension's files agree with the package: the module's CMake list names every file
of the module's helpers and of the library, its resources exist in the module's Resources/
folder, and Resources/requirements.txt is pyproject.toml's dependencies without the two that
Slicer ships. (Testing/Slicer/test_extension.py configures the
CMake files themselves.)"""

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODULE = ROOT / "MDLShapeModel"


def cmake_list(name: str) -> list:
    text = (MODULE / "CMakeLists.txt").read_text()
    body = re.search(rf"set\({name}\s+(.*?)\)", text, re.S).group(1)
    return [line.split("#")[0].strip().replace("${MODULE_NAME}", "MDLShapeModel")
            for line in body.splitlines() if line.split("#")[0].strip()]


def test_the_module_cmake_list_names_every_python_file_of_the_package_and_no_other():
    listed = cmake_list("MODULE_PYTHON_SCRIPTS")
    tree = ["MDLShapeModel.py"] + sorted(str(p.relative_to(MODULE))
                                         for package in ("MDLShapeModelLib", "mdlshapemodel")
                                         for p in (MODULE / package).rglob("*.py"))
    assert sorted(listed) == sorted(tree)
    assert len(set(listed)) == len(listed)


def test_the_listed_resources_exist_in_the_modules_resources_folder():
    resources = cmake_list("MODULE_PYTHON_RESOURCES")
    assert {"Resources/Icons/MDLShapeModel.png", "Resources/UI/MDLShapeModel.ui",
            "Resources/requirements.txt"} <= set(resources)
    for resource in resources:
        assert (MODULE / resource).is_file(), resource


def test_requirements_are_the_dependencies_slicer_lacks():
    dependencies = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    lines = (MODULE / "Resources" / "requirements.txt").read_text().splitlines()
    requirements = [line.strip() for line in lines if line.strip() and not line.startswith("#")]
    shipped = {"vtk", "simpleitk"}
    expected = [d for d in dependencies if re.split(r"[<>=!~ ]", d)[0].lower() not in shipped]
    assert requirements == expected
    assert not any(re.split(r"[<>=!~ ]", r)[0].lower() in shipped for r in requirements)
