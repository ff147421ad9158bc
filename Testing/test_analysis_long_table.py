"""analyze --long-table's long.csv, of an analysis of shapes without a build: a row per used case
and point, the case's displacement along the mean's normal recomputed from the shapes, its
principal scores and its own row of the subjects table."""

import csv

import numpy as np

from mdlshapemodel.analysis import align, analyze_shapes, subjects, vertex_normals
from mdlshapemodel.analyze import long_table
from mdlshapemodel.config import AnalysisConfig
from synthetic import two_sized_ellipsoids


def test_long_table_rows_hold_each_cases_normal_displacement_and_its_table_row(tmp_path):
    model, shapes, table = two_sized_ellipsoids(tmp_path)
    design = subjects(table, model.names, group="group")
    found = analyze_shapes(model, shapes, design,
                           AnalysisConfig(group="group", permutations=19, long_table=True))
    header, body = long_table(found, table)
    rows = [dict(zip(header, row)) for row in body]
    used = [name for k, name in enumerate(model.names) if k != 5]   # case_05 has no group
    points = len(model.mean)
    assert len(rows) == len(used) * points
    assert [rows[k * points]["case"] for k in range(len(used))] == used
    assert [int(row["point"]) for row in rows[:points]] == list(range(points))
    # the displacement along the outward normal of the aligned cases' mean: the smaller (thin)
    # cases lie inside it
    aligned = align(shapes[design.indices], model.weights)
    mean = aligned.mean(axis=0)
    expected = np.einsum("npd,pd->np", aligned - mean, vertex_normals(mean, model.triangles))
    written = np.array([float(row["normal_displacement_mm"]) for row in rows]).reshape(
        len(used), points)
    np.testing.assert_allclose(written, expected, rtol=1e-5, atol=1e-6 * np.abs(expected).max())
    thin = np.array([group == "thin" for group in design.groups])
    assert written[thin].mean() < 0 < written[~thin].mean()
    # each case's scores and its own row of the table, by name
    k = found.scores.shape[1]
    for i, name in enumerate(used):
        row = rows[i * points]
        np.testing.assert_allclose([float(row[f"score_{j + 1}"]) for j in range(k)],
                                   found.scores[i], rtol=1e-5, atol=1e-6)
    given = {row[0]: row[1:] for row in csv.reader(open(table))}
    for row in rows[::points]:
        assert [row["group"], row["age"]] == given[row["case"]]
