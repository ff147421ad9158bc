"""3D Slicer markups JSON files (.mrk.json) read by the library, without Slicer: written here
as Slicer 5 writes them (schema, control points with orientation and status, display), in RAS
and in LPS, with a control point of the list never placed. The points come back in LPS, equal to
the same points given as a plain LPS table. And what a guided build writes of the corresponded
landmarks: landmarks.csv's rows and metrics.json's summary, recomputed here."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mdlshapemodel.folders import LANDMARK_COLUMNS, CorrespondedLandmark
from mdlshapemodel.outputs import landmark_summary
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


def test_landmarks_csv_rows_and_the_summary_of_their_distances():
    """Each row: the corresponded point, the given one and the Euclidean distance between them;
    the summary: per label the number of cases, the mean and the largest distance with its case,
    over all the mean and the largest; a case without a given landmark counts in none."""
    rng = np.random.default_rng(12)

    class Model:
        landmarks = {"tip": 3, "base": 40}

    records = []
    for case in ("a", "b", "c", "d"):
        for label in Model.landmarks:
            point = rng.normal(scale=10.0, size=3)
            given = None if (case, label) == ("d", "tip") else point + rng.normal(size=3)
            records.append(CorrespondedLandmark(case, label, point, given))
    distances = {}
    for record in records:
        row = dict(zip(LANDMARK_COLUMNS, record.row()))
        if record.given is None:
            assert row["given_x"] == row["distance_mm"] == ""
            continue
        point = np.array([float(row[c]) for c in "xyz"])
        given = np.array([float(row[f"given_{c}"]) for c in "xyz"])
        distance = float(np.sqrt(np.sum((point - given) ** 2)))
        assert float(row["distance_mm"]) == pytest.approx(distance, abs=2e-6)
        distances.setdefault(record.label, {})[record.case] = distance
    summary = landmark_summary(Model, records)
    assert summary["labels"] == ["tip", "base"] and summary["given"] == 7
    every = [d for mine in distances.values() for d in mine.values()]
    assert summary["distance_mm"]["mean"] == pytest.approx(np.mean(every), abs=1e-5)
    assert summary["distance_mm"]["max"] == pytest.approx(max(every), abs=1e-5)
    for label, mine in distances.items():
        found = summary["per_label"][label]
        assert found["cases"] == len(mine)
        assert found["mean_mm"] == pytest.approx(np.mean(list(mine.values())), abs=1e-5)
        assert found["max_case"] == max(mine, key=mine.get)
        assert found["max_mm"] == pytest.approx(max(mine.values()), abs=1e-5)
