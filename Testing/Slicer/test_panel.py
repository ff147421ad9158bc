"""The panel's .ui loaded by a real Qt loader (PySide6, offscreen) with stand-ins for the CTK and
qMRML widgets (panel.py): it has every widget the module's Widget uses, one widget per parameter
of the parameter node, the sections the module describes, and it draws."""

import pathlib
import re
import typing

import pytest

pytest.importorskip("PySide6")

from PySide6 import QtGui, QtWidgets  # noqa: E402

import harness  # noqa: E402
import MDLShapeModel as module  # noqa: E402
import panel  # noqa: E402
from MDLShapeModelLib.messages import panelLabels, panelMessage  # noqa: E402
from mdlshapemodel.config import AnalysisConfig  # noqa: E402
from mdlshapemodel.errors import ConfigError  # noqa: E402

UI = module.resourcePath("UI/MDLShapeModel.ui")


@pytest.fixture(scope="module")
def loaded():
    messages = []
    return panel.load_panel(UI, messages), messages


def test_the_ui_loads_and_only_what_needs_slicer_is_left_unread(loaded):
    root, messages = loaded
    assert type(root).__name__ == "qMRMLWidget"
    # the stand-ins cannot declare the scene signal (its type is MRML's) nor ctkPathLineEdit's
    # Filters flags (CTK's enum)
    unexpected = [m for m in messages if "mrmlSceneChanged(vtkMRMLScene*)" not in m
                  and "(sender name:" not in m and "(receiver name:" not in m
                  and "set-type property filters" not in m]
    assert unexpected == []


def test_every_widget_the_module_uses_is_in_the_ui(loaded):
    root, _ = loaded
    source = pathlib.Path(module.__file__).read_text()
    used = set(re.findall(r"self\.ui\.(\w+)", source))
    assert {"applyButton", "cancelButton", "inputNodesSelector", "progressBar"} <= used
    names = {w.objectName() for w in root.findChildren(QtWidgets.QWidget)}
    assert used - names == set()


def test_every_parameter_has_exactly_one_widget_of_its_kind(loaded):
    root, _ = loaded
    widgets = panel.parameter_widgets(root)
    parameters = module.MDLShapeModelParameterNode.allParameters
    # the parameters of several nodes are shown by checkable selectors, kept in step by the Widget
    checked = module.CHECKED_NODE_PARAMETERS
    assert set(widgets) == set(parameters) - set(checked)
    for name, selector in checked.items():
        assert isinstance(root.findChild(QtWidgets.QWidget, selector),
                          panel.qMRMLCheckableNodeComboBox), name
    hints = typing.get_type_hints(module.MDLShapeModelParameterNode, include_extras=True)
    for name, (widget,) in widgets.items():
        kind = typing.get_args(hints[name])[0] if typing.get_origin(hints[name]) else hints[name]
        extras = typing.get_args(hints[name])[1:]
        if any(isinstance(e, harness.Choice) for e in extras):
            expected = QtWidgets.QComboBox
        elif isinstance(kind, type) and issubclass(kind, module.slicer.vtkMRMLNode):
            expected = panel.qMRMLNodeComboBox
        else:
            expected = {int: QtWidgets.QSpinBox, float: QtWidgets.QDoubleSpinBox,
                        bool: QtWidgets.QCheckBox, str: QtWidgets.QLineEdit,
                        pathlib.Path: panel.ctkPathLineEdit}[kind]
        assert isinstance(widget, expected), name


def test_every_parameter_the_ui_binds_is_declared_by_name_in_the_modules_source(loaded):
    root, _ = loaded
    source = pathlib.Path(module.__file__).read_text()
    declared = set(re.findall(r"^    (\w+): ", source, re.M))
    bound = set(panel.parameter_widgets(root))
    assert {"labels", "strategy", "outputDirectory", "analysisColorBy", "analysisTfce",
            "analysisFolds", "analysisRepeats", "analysisClassificationPermutations"} <= bound
    assert bound - declared == set()
    assert set(module.CHECKED_NODE_PARAMETERS) <= declared


def test_the_sections_are_inputs_parameters_run_results_with_advanced_and_analysis_collapsed(
        loaded):
    root, _ = loaded
    sections = {w.getText(): w.getCollapsed() for w in root.findChildren(panel.ctkCollapsibleButton)}
    assert sections == {"Inputs": False, "Parameters": False, "Run": False, "Results": False,
                        "Advanced": True, "Analysis": True, "Classification": True}
    advanced = root.findChild(panel.ctkCollapsibleButton, "advancedCollapsibleButton")
    main = set(panel.parameter_widgets(advanced))
    # beside the smoothness weight, whether BuildConfig's rule chooses it
    assert main == set(module.ADVANCED_SETTINGS) | {"defaultSmoothness"}
    # the analysis's classifier settings in a collapsed part of the Analysis section
    analysis = root.findChild(panel.ctkCollapsibleButton, "analysisCollapsibleButton")
    classification = analysis.findChild(panel.ctkCollapsibleButton,
                                        "classificationCollapsibleButton")
    assert set(panel.parameter_widgets(classification)) == {
        "analysisFolds", "analysisRepeats", "analysisClassificationPermutations"}


def test_the_panel_draws(loaded, tmp_path):
    root, _ = loaded
    panel.fill(root, module.MDLShapeModelParameterNode)
    strategy = root.findChild(QtWidgets.QComboBox, "strategyComboBox")
    assert strategy.currentText() == module.BuildConfig().strategy
    panel.render(root, tmp_path / "panel.png")
    image = QtGui.QImage(str(tmp_path / "panel.png"))
    assert image.width() >= 400 and image.height() >= 600
    colours = {image.pixel(x, y) for x in range(0, image.width(), 7)
               for y in range(0, image.height(), 7)}
    assert len(colours) > 5


@pytest.mark.parametrize("picture, sections", [("panel.png", ()), ("analysis.png", ("Analysis",))])
def test_the_committed_pictures_show_the_current_panel(picture, sections, tmp_path):
    """Resources/Screenshots/PICTURE, drawn again as panel.py draws it (the whole panel; the
    Analysis section alone open): the same size (every section and widget where the .ui puts
    it) and nearly every pixel the same (fonts may differ a little between installations).
    When it fails: python Testing/Slicer/panel.py Resources/Screenshots/PICTURE [SECTION]."""
    committed = QtGui.QImage(str(harness.HERE.parents[1] / "Resources" / "Screenshots" / picture))
    assert not committed.isNull(), picture
    fresh_panel = panel.load_panel(UI)
    panel.fill(fresh_panel, module.MDLShapeModelParameterNode)
    if sections:
        panel.show_only(fresh_panel, sections)
    panel.render(fresh_panel, tmp_path / picture)
    fresh = QtGui.QImage(str(tmp_path / picture))
    assert (committed.width(), committed.height()) == (fresh.width(), fresh.height()), picture
    grid = [(x, y) for x in range(0, fresh.width(), 3) for y in range(0, fresh.height(), 3)]
    same = sum(committed.pixel(x, y) == fresh.pixel(x, y) for x, y in grid)
    assert same >= 0.95 * len(grid), (picture, same / len(grid))


@pytest.mark.parametrize("settings, said", [
    ({"folds": 1}, "Folds: must be at least 2 (got 1)"),
    ({"classification_permutations": -1},
     "Label permutations: must be 0 (no p-value) or more (got -1)")])
def test_a_refused_classifier_setting_is_named_by_its_fields_label(settings, said):
    with pytest.raises(ConfigError) as raised:
        AnalysisConfig(**settings).validate()
    assert panelMessage(raised.value, panelLabels(UI)) == said
