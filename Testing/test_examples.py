"""The scripts in examples/ run as a user runs them, and write what their docstrings say.

The README's Python section points to these files, so running them here keeps the documentation
and the code together.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def run_example(name: str, *arguments, cwd: Path) -> str:
    completed = subprocess.run([sys.executable, str(EXAMPLES / name), *map(str, arguments)],
                               cwd=cwd, capture_output=True, text=True, timeout=600)
    assert completed.returncode == 0, completed.stderr[-3000:]
    return completed.stdout


def read_points(path: Path) -> np.ndarray:
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    reader = vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    polydata = reader.GetOutput()
    assert polydata.GetNumberOfPolys() > 0, path
    return vtk_to_numpy(polydata.GetPoints().GetData())


@pytest.mark.slow
def test_build_model_and_instances(tmp_path):
    from mdlshapemodel import ShapeModel

    printed = run_example("build_model.py", "out", cwd=tmp_path)
    assert "12 cases, 0 rejected" in printed
    model_file = tmp_path / "out" / "model" / "model.h5"
    model = ShapeModel.load(model_file)
    assert model.mean.shape == (162, 3) and len(model.names) == 12
    assert (tmp_path / "out" / "model" / "report.html").is_file()

    run_example("instances.py", model_file, "shapes", cwd=tmp_path)
    mean = read_points(tmp_path / "shapes" / "mean.vtp")
    minus = read_points(tmp_path / "shapes" / "mode1_minus2sd.vtp")
    plus = read_points(tmp_path / "shapes" / "mode1_plus2sd.vtp")
    assert np.allclose(mean, model.mean, atol=1e-4)
    assert np.allclose(plus, model.instance(standard_deviations=[2.0]), atol=1e-4)
    assert np.allclose((plus + minus) / 2, mean, atol=1e-4)     # symmetric about the mean
    assert not np.allclose(plus, mean, atol=1e-3)


@pytest.mark.slow
def test_vtk_pipeline(tmp_path):
    from mdlshapemodel import ShapeModel

    printed = run_example("vtk_pipeline.py", "out", cwd=tmp_path)
    assert "8 corresponded cases of 162 points" in printed
    model = ShapeModel.load(tmp_path / "out" / "model.h5")
    assert len(model.names) == 8
    plus = read_points(tmp_path / "out" / "plus2sd.vtp")
    assert np.allclose(plus, model.instance(standard_deviations=[2.0]), atol=1e-4)
