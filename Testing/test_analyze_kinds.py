"""The analysis of multi-part objects (aligned as one or part by part) and of 2-D models."""

from __future__ import annotations

import numpy as np
import pytest

from mdlshapemodel import BuildConfig, build_model
from mdlshapemodel.analysis import read_build, subjects
from mdlshapemodel.analysis.study import analyze_shapes
from mdlshapemodel.analyze import analyze_build
from mdlshapemodel.config import AnalysisConfig
from mdlshapemodel.demo import DEMO_PARTS, write_demo_curves, write_demo_population
from mdlshapemodel.prepare import io

pytestmark = pytest.mark.slow      # real builds

QUICK = dict(strategy="none", baselines=[], workers=1, evaluation_modes=2,
             specificity_samples=100, surface_samples=0, cache_dir="")


def groups_table(path, names):
    path.write_text("case,group\n" + "".join(f"{n},{'a' if k % 2 else 'b'}\n"
                                             for k, n in enumerate(names)))
    return path


@pytest.fixture(scope="module")
def two_parts(tmp_path_factory):
    folder = tmp_path_factory.mktemp("parts")
    paths = write_demo_population(folder / "labels", 8, 0, True)
    build_model(paths, folder / "build", BuildConfig(points=162, parts=list(DEMO_PARTS),
                                                     **QUICK))
    return folder / "build"


def weighted_centroids(shapes, weights):
    return np.einsum("p,npd->nd", weights / weights.sum(), shapes)


def test_a_two_part_object_is_aligned_as_one_or_part_by_part(two_parts, tmp_path):
    built = read_build(two_parts)
    model = built.model
    design = subjects(groups_table(tmp_path / "t.csv", model.names), model.names, "group")
    # least squares, which puts every case's area-weighted centroid on the mean's (the resistant
    # superimposition centres the robust-weighted one)
    whole = analyze_shapes(model, built.shapes, design,
                           AnalysisConfig(permutations=99, superimposition="least-squares"))
    each = analyze_shapes(model, built.shapes, design,
                          AnalysisConfig(permutations=99, parts="each",
                                         superimposition="least-squares"))
    rows = model.part_slices()
    assert len(rows) == 2
    for part in rows:
        centres = weighted_centroids(each.aligned[:, part], model.weights[part])
        assert np.abs(centres - centres[0]).max() < 1e-9      # each part centred on its own
    apart = [weighted_centroids(whole.aligned[:, part], model.weights[part]) for part in rows]
    spread = np.ptp(apart[0] - apart[1], axis=0)
    assert spread.max() > 1e-3           # as one object, the parts keep their relative places
    assert list(np.unique(whole.parts)) == [0, 1]


def test_a_two_part_analysis_writes_an_effect_map_per_part(two_parts, tmp_path):
    table = groups_table(tmp_path / "t.csv", read_build(two_parts).model.names)
    result = analyze_build(two_parts, table, tmp_path / "out",
                           AnalysisConfig(group="group", permutations=99, parts="each"))
    assert sorted(p.name for p in (tmp_path / "out" / "effects").iterdir()) == [
        f"{name}.vtp" for name in sorted(DEMO_PARTS_NAMES)]
    rows = io.read_csv(tmp_path / "out" / "points.csv")
    assert {row["part"] for row in rows} == {"0", "1"}
    assert result.summary["settings"]["parts"] == "each"


DEMO_PARTS_NAMES = [spec.split("=")[0] for spec in DEMO_PARTS]


def test_a_2d_model_is_analysed_along_the_outlines_normals(tmp_path):
    paths = write_demo_curves(tmp_path / "outlines", 10, 0)
    build_model(paths, tmp_path / "build", BuildConfig(**QUICK))
    names = read_build(tmp_path / "build").model.names
    result = analyze_build(tmp_path / "build", groups_table(tmp_path / "t.csv", names),
                           tmp_path / "out", AnalysisConfig(group="group", permutations=99,
                                                            displacement="vector"))
    analysis = result.analysis
    assert analysis.points.df == 8 and analysis.points.effect.shape[2] == 2   # x and y only
    outward = np.einsum("pd,pd->p", analysis.normals, analysis.mean - analysis.mean.mean(0))
    assert np.mean(outward > 0) > 0.9 and np.allclose(analysis.normals[:, 2], 0)
    polydata = io.read_polydata(tmp_path / "out" / "effects.vtp")
    assert polydata.GetNumberOfLines() == len(analysis.mean)
    assert (tmp_path / "out" / "analysis.html").stat().st_size > 5_000
