"""The module's analysis (Logic.analyzeModel, the analysis's process) on a real MRML scene
and a real build: the effect map as a coloured model node with a legend, the points as a table."""

import json

import numpy as np
import pytest
import SimpleITK as sitk
import slicer
import vtk
from vtk.util.numpy_support import vtk_to_numpy

import MDLShapeModel as module
from mdlshapemodel import BuildConfig
from mdlshapemodel.errors import Cancelled, InputError
from mdlshapemodel.prepare import io
from synthetic import small_mask

N = 8
LPS_TO_RAS = np.array([-1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def build(tmp_path_factory):
    folder = tmp_path_factory.mktemp("slicer-analysis")
    paths = []
    for k, position in enumerate(np.linspace(-0.5, 0.5, N)):
        mask = small_mask(float(position), 0.9 if k % 2 else 1.0).astype(np.uint8)
        paths.append(folder / f"case_{k}.nii.gz")
        sitk.WriteImage(sitk.GetImageFromArray(mask), str(paths[-1]))
    config = BuildConfig(points=162, strategy="none", baselines=[], workers=1,
                         evaluation_modes=2, specificity_samples=100, surface_samples=0)
    module.MDLShapeModelLogic().buildModel(paths, folder / "build", config)
    return folder / "build"


def table_node(groups: dict):
    node = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLTableNode", "subjects")
    for name in ("case", "group"):
        array = vtk.vtkStringArray()
        array.SetName(name)
        for case, group in groups.items():
            array.InsertNextValue(case if name == "case" else group)
        node.GetTable().AddColumn(array)
    return node


GROUPS = {f"case_{k}": "small" if k % 2 else "large" for k in range(N)}


def test_analyze_model_loads_a_coloured_effect_map_with_a_legend_and_the_points_table(
        scene, build, tmp_path):
    logic = module.MDLShapeModelLogic()
    reports = []
    nodes = logic.analyzeModel(build, table_node(GROUPS), group="group",
                               outputDirectory=tmp_path / "findings", permutations=199,
                               progress=lambda f, m: reports.append((f, m)))
    summary = json.loads((tmp_path / "findings" / "analysis.json").read_text())
    assert nodes.summary == summary and summary["n_per_group"] == {"large": 4, "small": 4}
    assert any("permutations" in m for _, m in reports)
    effect = nodes.effectModelNode
    vertices, _ = io.read_mesh(tmp_path / "findings" / "effects.vtp")
    np.testing.assert_allclose(vtk_to_numpy(effect.GetPolyData().GetPoints().GetData()),
                               vertices * LPS_TO_RAS, atol=1e-4)
    display = effect.GetDisplayNode()
    assert display.GetActiveScalarName() == "minus_log10_p_fwer"
    assert display.GetScalarVisibility()
    significance = vtk_to_numpy(effect.GetPolyData().GetPointData().GetArray(
        "minus_log10_p_fwer"))
    assert display.GetScalarRange() == pytest.approx((0.0, significance.max()))
    assert display.GetColorNode().GetName() == "MDLShapeModel viridis"
    legends = [effect.GetNthDisplayNode(k) for k in range(effect.GetNumberOfDisplayNodes())
               if effect.GetNthDisplayNode(k).IsA("vtkMRMLColorLegendDisplayNode")]
    assert len(legends) == 1 and legends[0].GetTitleText() == "-log10 p (FWER)"
    table = nodes.pointsTableNode.GetTable()
    assert table.GetNumberOfRows() == 162
    rows = io.read_csv(tmp_path / "findings" / "points.csv")
    column = vtk_to_numpy(table.GetColumnByName("p_fwer"))
    np.testing.assert_allclose(column, [float(r["p_fwer"]) for r in rows])

    logic.colorEffectMap(effect, "normal_difference_mm")
    normal = vtk_to_numpy(effect.GetPolyData().GetPointData().GetArray("normal_difference_mm"))
    limit = np.abs(normal).max()
    assert display.GetActiveScalarName() == "normal_difference_mm"
    assert display.GetScalarRange() == pytest.approx((-limit, limit))
    assert display.GetColorNode().GetName() == "MDLShapeModel coolwarm"
    assert legends[0].GetTitleText() == "effect along the normal [mm]"
    with pytest.raises(ValueError, match="colour by one of"):
        logic.colorEffectMap(effect, "nonsense")


def test_the_background_job_reports_progress_and_a_csv_table_works_too(scene, build, tmp_path):
    table = tmp_path / "subjects.csv"
    table.write_text("case,group\n" + "".join(f"{c},{g}\n" for c, g in GROUPS.items()))
    job = module.MDLShapeModelLogic().startAnalysis(build, table, group="group",
                                                    outputDirectory=tmp_path / "out",
                                                    permutations=99)
    assert job.wait(300)
    reports = job.poll()
    nodes = job.finish()
    assert nodes.summary["settings"]["permutations"] == 99
    assert any("permutations" in report.message for report in reports)
    assert nodes.pageFile.is_file()


def test_cancel_stops_the_analysis_and_writes_nothing(scene, build, tmp_path):
    logic = module.MDLShapeModelLogic()
    with pytest.raises(Cancelled):
        logic.analyzeModel(build, table_node(GROUPS), group="group",
                           outputDirectory=tmp_path / "cancelled", permutations=5000,
                           progress=lambda fraction, message: fraction is None or fraction < 0.1)
    assert not (tmp_path / "cancelled").exists()
    assert [p for p in tmp_path.iterdir()] == []


def test_a_bad_table_is_refused_with_the_librarys_one_line(scene, build, tmp_path):
    with pytest.raises(InputError, match="group group='small' has 1 case"):
        module.MDLShapeModelLogic().analyzeModel(
            build, table_node({**{c: "large" for c in GROUPS}, "case_1": "small"}),
            group="group", outputDirectory=tmp_path / "bad", permutations=9)
    assert not (tmp_path / "bad").exists()


def test_an_analysis_with_tfce_loads_its_shapes_its_arrays_and_the_findings_as_text(
        scene, build, tmp_path):
    nodes = module.MDLShapeModelLogic().analyzeModel(
        build, table_node(GROUPS), group="group", outputDirectory=tmp_path / "tfce",
        permutations=99, tfce=True, folds=4, repeats=2, classification_permutations=19)
    summary = nodes.summary
    # the effect map carries effects.vtp's point arrays: TFCE's, the effect sizes, the intervals
    data = nodes.effectModelNode.GetPolyData().GetPointData()
    names = {data.GetArrayName(k) for k in range(data.GetNumberOfArrays())}
    assert {"tfce", "tfce_p_fwer", "cohens_d", "partial_eta2", "ci_lower_mm",
            "ci_upper_mm"} <= names
    rows = io.read_csv(tmp_path / "tfce" / "points.csv")
    np.testing.assert_allclose(vtk_to_numpy(data.GetArray("tfce_p_fwer")),
                               [float(r["tfce_p_fwer"]) for r in rows], rtol=1e-5)
    # each shape of shapes/ (the two group means) a hidden model node in the analysis's folder
    files = sorted((tmp_path / "tfce" / "shapes").glob("*.vtp"))
    assert len(files) == 2
    assert [n.GetName() for n in nodes.shapeModelNodes] == [f"tfce shape {f.stem}"
                                                            for f in files]
    hierarchy = slicer.mrmlScene.GetSubjectHierarchyNode()
    for node, path in zip(nodes.shapeModelNodes, files):
        vertices, _ = io.read_mesh(path)
        np.testing.assert_allclose(vtk_to_numpy(node.GetPolyData().GetPoints().GetData()),
                                   vertices * LPS_TO_RAS, atol=1e-4)
        assert hierarchy.GetItemParent(hierarchy.GetItemByDataNode(node)) == nodes.folderItemID
        assert not node.GetDisplayNode().GetVisibility()
    # the findings: TFCE's significant points, the effect sizes, the classifier's AUC and p
    found = summary["classification"]
    low, high = found["auc_interval"]
    assert summary["settings"]["classification_permutations"] == 19 and found["folds"] == 4
    assert f"TFCE: {summary['point_test']['tfce']['significant_points']} significant" in nodes.text
    assert f"AUC {found['auc']:.3g} (95% interval {low:.3g} to {high:.3g})" in nodes.text
    assert f"p = {found['p']:.3g} ({found['permutations']} permutations)" in nodes.text
    largest = summary["effect_sizes"]["maps"][0]["partial_eta2"]["largest"]
    assert f"largest {largest:.3g}" in nodes.text
