"""The default correspondence against a known truth: a population made by deforming one surface
with smooth fields, so that vertex k of every case is the same point, built through the command
line with the defaults and without the prior on smooth correspondence."""

from __future__ import annotations

import numpy as np
import pytest
import vtk
from vtk.util.numpy_support import vtk_to_numpy

from mdlshapemodel.correspondence.sampling import icosphere
from files import read_polydata, triangle_polydata
from common import run_cli


def write_mesh(path, vertices, faces):
    writer = vtk.vtkXMLPolyDataWriter()
    writer.SetFileName(str(path))
    writer.SetInputData(triangle_polydata(vertices, faces))
    assert writer.Write() == 1


def known_population(folder, n_cases: int = 10, seed: int = 4):
    """An egg with a knob, deformed by three smooth displacement fields (Gaussian bumps of random
    direction) in random combinations and posed at random; returns (template, faces, cases)."""
    rng = np.random.default_rng(seed)
    sphere, faces = icosphere(5)
    # an egg (one end broader) with a knob: no symmetry for the sphere maps' alignment to confuse
    template = sphere * [20.0, 10.0, 7.0] * (1.0 + 0.3 * sphere[:, :1])
    template += 8.0 * np.exp(-np.sum((sphere - [0.6, 0.8, 0.0]) ** 2, axis=1) / 0.05)[:, None] \
        * sphere
    centres = template[rng.choice(len(template), 3, replace=False)]
    directions = rng.normal(size=(3, 3))
    fields = [2.5 * np.exp(-np.sum((template - c) ** 2, axis=1) / (2 * 8.0 ** 2))[:, None] * d
              for c, d in zip(centres, directions)]
    cases = []
    for k in range(n_cases):
        shape = template + sum(rng.normal() * f for f in fields)
        q, r = np.linalg.qr(rng.normal(size=(3, 3)) * 0.1 + np.eye(3))
        rotation = q * np.sign(np.diag(r))                     # near the identity
        shape = shape @ rotation + rng.normal(size=3) * 3.0
        write_mesh(folder / f"case_{k:02d}.vtp", shape, faces)
        cases.append(shape)
    return template, faces, cases


def truth_error(build, template, faces, cases) -> float:
    """Each corresponded point located on its case's true mesh (closest point: a triangle and
    barycentric coordinates), carried to the template by the known correspondence; the mean
    distance of each point's carried copies from their mean (mm)."""
    carried = []
    for k, shape in enumerate(cases):
        locator = vtk.vtkCellLocator()
        locator.SetDataSet(triangle_polydata(shape, faces))
        locator.BuildLocator()
        located = vtk_to_numpy(read_polydata(build / "correspondence" / f"case_{k:02d}.vtp")
                               .GetPoints().GetData())
        copies = []
        for point in located:
            cell = vtk.reference(0)
            locator.FindClosestPoint(point, [0.0, 0.0, 0.0], cell, vtk.reference(0),
                                     vtk.reference(0.0))
            a, b, c = (shape[v] for v in faces[cell.get()])
            # barycentric coordinates of the point's projection onto its closest triangle
            t = np.linalg.lstsq(np.stack([b - a, c - a], axis=1), point - a, rcond=None)[0]
            ta, tb, tc = (template[v] for v in faces[cell.get()])
            copies.append(ta + t[0] * (tb - ta) + t[1] * (tc - ta))
        carried.append(copies)
    carried = np.asarray(carried)                                   # (cases, points, 3)
    return float(np.linalg.norm(carried - carried.mean(axis=0), axis=2).mean())


@pytest.mark.slow
def test_the_default_lands_closer_to_the_known_correspondence_than_no_prior(tmp_path):
    inputs = tmp_path / "meshes"
    inputs.mkdir()
    template, faces, cases = known_population(inputs)
    errors = {}
    for name, options in {"default": [], "no prior": ["--smoothness", "0"]}.items():
        output = tmp_path / name.replace(" ", "-")
        result = run_cli("build", inputs, "-o", output, "--baselines", "", *options)
        assert result.returncode == 0, result.stderr
        errors[name] = truth_error(output, template, faces, cases)
    assert errors["default"] < 0.85 * errors["no prior"], errors
