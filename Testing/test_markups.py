"""3D Slicer markups JSON files (.mrk.json) read by the library, without Slicer: written here
as Slicer 5 writes them (schema, control points with orientation and status, display), in RAS
and in LPS, with a control point of the list never placed. The points come back in LPS, equal to
the same points given as a plain LPS table."""

from __future__ import annotations

import json

import numpy as np

from mdlshapemodel.prepare.landmarks import read_landmark_folder, read_landmarks

SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/"
          "Resources/Schema/markups-schema-v1.0.3.json#")
# the landmarks in LPS (mm)
POINTS = {"tip": [12.5, -40.25, 7.0], "base": [-3.0, 22.0, -15.5], "notch": [0.0, 5.5, 30.0]}


def control_point(number: int, label: str, position, status: str = "defined") -> dict:
    return {"id": str(number), "label": label, "description": "", "associatedNodeID": "",
            "position": position, "orientation": [-1.0, -0.0, -0.0, -0.0, -1.0, -0.0, 0.0,
                                                  0.0, 1.0],
            "selected": True, "locked": False, "visibility": True, "positionStatus": status}


def markups_file(path, system: str, unplaced: bool = False):
    """A point list as Slicer 5 saves it; RAS positions are the LPS ones with x, y negated.
    ``unplaced``: a fourth control point left in the list with no position put anywhere."""
    flip = np.array([-1.0, -1.0, 1.0]) if system == "RAS" else np.ones(3)
    points = [control_point(k + 1, label, list(np.array(p) * flip))
              for k, (label, p) in enumerate(POINTS.items())]
    if unplaced:
        points.append(control_point(4, "apex", [0.0, 0.0, 0.0], status="undefined"))
    document = {"@schema": SCHEMA, "markups": [{
        "type": "Fiducial", "coordinateSystem": system, "coordinateUnits": "mm",
        "locked": False, "fixedNumberOfControlPoints": False, "labelFormat": "%N-%d",
        "lastUsedControlPointNumber": len(points), "controlPoints": points, "measurements": [],
        "display": {"visibility": True, "opacity": 1.0, "color": [0.4, 1.0, 1.0],
                    "selectedColor": [1.0, 0.5, 0.5], "glyphType": "Sphere3D",
                    "glyphScale": 1.0, "textScale": 3.0}}]}
    path.write_text(json.dumps(document, indent=4))
    return path


def test_ras_and_lps_markups_give_the_same_lps_points_as_a_table(tmp_path):
    table = tmp_path / "table.csv"
    table.write_text("label,x,y,z\n" + "".join(f"{k},{x},{y},{z}\n"
                                               for k, (x, y, z) in POINTS.items()))
    expected = read_landmarks(table)
    for system in ("RAS", "LPS"):
        read = read_landmarks(markups_file(tmp_path / f"{system}.mrk.json", system))
        assert read.labels == tuple(POINTS)
        np.testing.assert_array_equal(read.points, expected.points)
        np.testing.assert_array_equal(read.points, np.array(list(POINTS.values())))


def test_a_control_point_never_placed_is_not_a_landmark(tmp_path):
    folder = tmp_path / "landmarks"
    folder.mkdir()
    markups_file(folder / "case_01.mrk.json", "RAS", unplaced=True)
    found = read_landmark_folder(folder, ["case_01", "case_02"])
    assert list(found) == ["case_01"]
    assert found["case_01"].labels == tuple(POINTS)
    assert found["case_01"].get("apex") is None
