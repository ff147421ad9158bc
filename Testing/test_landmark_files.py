"""Landmark files (prepare/landmarks.py): plain tables and the older Slicer .fcsv read into LPS,
and every malformed file refused with a message naming it. Files written by Slicer's own storage
nodes are read in Testing/Slicer/test_landmark_files.py."""

import json

import numpy as np
import pytest

from mdlshapemodel.errors import InputError
from mdlshapemodel.prepare.landmarks import find_landmark_file, read_landmarks


def test_a_table_is_read_in_any_column_order_with_extra_columns(tmp_path):
    path = tmp_path / "s01.csv"
    path.write_text("z,label,x,note,y\n3,tip,1,first,2\n-6.5,base, 4 ,,5e-1\n")
    landmarks = read_landmarks(path)
    assert landmarks.labels == ("tip", "base")
    np.testing.assert_array_equal(landmarks.points, [[1, 2, 3], [4, 0.5, -6.5]])
    np.testing.assert_array_equal(landmarks.get("base"), [4, 0.5, -6.5])
    assert landmarks.get("knee") is None


def test_a_table_that_says_ras_is_turned_into_lps(tmp_path):
    path = tmp_path / "s01.csv"
    path.write_text("# CoordinateSystem = RAS\nlabel,x,y,z\ntip,1,2,3\n")
    np.testing.assert_array_equal(read_landmarks(path).points, [[-1, -2, 3]])


def test_an_fcsv_without_a_columns_line_uses_slicers_order_and_ras(tmp_path):
    # what Slicer 4.6 wrote: no columns comment, CoordinateSystem 0 (RAS)
    path = tmp_path / "s01.fcsv"
    path.write_text("# Markups fiducial file version = 4.6\n# CoordinateSystem = 0\n"
                    "vtkMRMLMarkupsFiducialNode_0,1,2,3,0,0,0,1,1,1,0,tip,,\n")
    landmarks = read_landmarks(path)
    assert landmarks.labels == ("tip",)
    np.testing.assert_array_equal(landmarks.points, [[-1, -2, 3]])
    path.write_text(path.read_text().replace("= 0", "= 1"))       # 1: LPS
    np.testing.assert_array_equal(read_landmarks(path).points, [[1, 2, 3]])


@pytest.mark.parametrize("name, text, problem", [
    ("a.csv", "label,x,y,z\ntip,1,2,3\ntip,4,5,6\n", "label 'tip' appears twice"),
    ("a.csv", "label,x,y,z\ntip,1,two,3\n", "are not numbers"),
    ("a.csv", "label,x,y,z\ntip,1,nan,3\n", "are not finite"),
    ("a.csv", "label,x,y\ntip,1,2\n", "no column z"),
    ("a.csv", "label,x,y,z\n,1,2,3\n", "has no label"),
    ("a.csv", "label,x,y,z\ntip,1,2\n", "row 1 has 3 fields"),
    ("a.csv", "label,x,y,z\n", "no landmark in the file"),
    ("a.csv", "", "empty landmark table"),
    ("a.csv", "# CoordinateSystem = IJK\nlabel,x,y,z\ntip,1,2,3\n", "neither LPS nor RAS"),
    ("a.mrk.json", "{not json", "not valid JSON"),
    ("a.mrk.json", json.dumps({"points": []}), "no 'markups' list"),
    ("a.mrk.json", json.dumps({"markups": [{"controlPoints": [{"label": "tip",
                                                                "position": [1, 2]}]}]}),
     "has no position"),
    ("a.txt", "tip 1 2 3\n", "not a landmark file"),
])
def test_a_malformed_file_is_refused_naming_it_and_the_problem(tmp_path, name, text, problem):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(InputError) as error:
        read_landmarks(path)
    assert str(path) in str(error.value) and problem in str(error.value)


def test_a_case_finds_its_one_file_and_two_are_refused(tmp_path):
    (tmp_path / "s01.csv").write_text("label,x,y,z\ntip,1,2,3\n")
    (tmp_path / "s02.csv").write_text("label,x,y,z\ntip,1,2,3\n")
    (tmp_path / "s02.mrk.json").write_text("{}")
    assert find_landmark_file(tmp_path, "s01") == tmp_path / "s01.csv"
    assert find_landmark_file(tmp_path, "s03") is None
    with pytest.raises(InputError, match="several landmark files for case 's02'"):
        find_landmark_file(tmp_path, "s02")
