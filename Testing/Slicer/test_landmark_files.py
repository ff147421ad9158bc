"""Landmark files written by 3D Slicer's own markups storage nodes (.mrk.json and .fcsv, in LPS
and in RAS) read by the library as the points Slicer placed, in LPS."""

import numpy as np
import pytest
import slicer

from mdlshapemodel.prepare.landmarks import read_landmarks

RAS_POINTS = {"tip": [1.0, 2.0, 3.0], "base": [-4.0, 5.5, 6.25], "notch": [10.5, -0.5, -7.0]}


@pytest.mark.parametrize("storage, suffix", [("vtkMRMLMarkupsJsonStorageNode", ".mrk.json"),
                                             ("vtkMRMLMarkupsFiducialStorageNode", ".fcsv")])
@pytest.mark.parametrize("system", ["LPS", "RAS"])
def test_slicer_markups_files_give_the_placed_points_in_lps(scene, tmp_path, storage, suffix,
                                                            system):
    node = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode")
    for label, point in RAS_POINTS.items():
        node.AddControlPoint(point, label)
    writer = getattr(slicer, storage)()
    scene.AddNode(writer)
    writer.SetCoordinateSystem(slicer.vtkMRMLStorageNode.CoordinateSystemLPS if system == "LPS"
                               else slicer.vtkMRMLStorageNode.CoordinateSystemRAS)
    path = tmp_path / f"case{suffix}"
    writer.SetFileName(str(path))
    assert writer.WriteData(node)
    assert system in path.read_text()          # the file says which frame it is in
    landmarks = read_landmarks(path)
    assert landmarks.labels == tuple(RAS_POINTS)
    lps = np.array(list(RAS_POINTS.values())) * [-1.0, -1.0, 1.0]
    np.testing.assert_allclose(landmarks.points, lps, atol=1e-9)


def test_an_unplaced_control_point_is_left_out(scene, tmp_path):
    node = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode")
    node.AddControlPoint([1.0, 2.0, 3.0], "tip")
    node.AddControlPoint([0.0, 0.0, 0.0], "base")
    node.UnsetNthControlPointPosition(1)       # in the list, never placed
    writer = slicer.vtkMRMLMarkupsJsonStorageNode()
    scene.AddNode(writer)
    writer.SetFileName(str(tmp_path / "case.mrk.json"))
    assert writer.WriteData(node)
    landmarks = read_landmarks(tmp_path / "case.mrk.json")
    assert landmarks.labels == ("tip",)
    np.testing.assert_allclose(landmarks.points, [[-1.0, -2.0, 3.0]])
