"""A headless 3D Slicer for the module's tests and scripts: slicer-core's real MRML, and stand-ins
for the few parts of the Slicer application that slicer-core does not have.

Real (from the ``slicer-core`` package, Kitware's build of Slicer's libraries): the MRML scene and
every node class, storage nodes and their file formats, the Segmentations module logic with its
closed-surface conversion rules, subject hierarchy, tables, and ``slicer.util``.

Stand-ins, each for exactly one thing the application provides:

- ``slicer.mrmlScene``: the application's scene -> a real ``vtkMRMLScene`` made by
  :func:`new_scene` (the Segmentations and Subject Hierarchy logics attached, as the
  application attaches them);
- ``slicer.app``: the application object -> :class:`Application`, its temporary folder only;
- ``slicer.modules``: the application's registry of loaded modules -> the Colors module's entry
  only, whose ``logic()`` is the real ``vtkSlicerColorLogic`` of the current scene (without the
  application it finds no colour-table files: the built-in tables and the colour legends work);
- ``slicer.ScriptedLoadableModule``: the base classes of scripted modules -> the same four
  classes with the behaviour the module relies on (``getParameterNode`` finds or makes the
  module's singleton ``vtkMRMLScriptedModuleNode`` as Slicer's does; no GUI);
- ``slicer.parameterNodeWrapper``: the typed parameter-node decorator -> :func:`parameterNodeWrapper`
  for the types the module uses (int, float, str, bool, pathlib.Path, MRML nodes, lists of these,
  with ``Choice`` and ``WithinRange``), storing values exactly as Slicer's does (``SetParameter`` strings, node
  references), so a scene saved here holds the parameters as Slicer writes them; no GUI binding;
- ``qt``: PythonQt's flat ``qt`` module -> PySide6's QtCore, QtGui, QtWidgets and QtUiTools in
  one namespace (when PySide6 is installed; an offscreen QApplication is made on first use).

Use from any script or test::

    import harness
    harness.install()                      # once; then `import MDLShapeModel` works
    scene = harness.new_scene()            # a fresh real scene as slicer.mrmlScene
"""

from __future__ import annotations

import os
import pathlib
import sys
import tempfile
import types
import typing
import unittest

HERE = pathlib.Path(__file__).resolve().parent
MODULE_DIRECTORY = HERE.parents[1] / "MDLShapeModel"

_installed = False


class Application:
    """Stands in for ``slicer.app``: its temporary folder only."""

    def __init__(self):
        self.temporaryPath = tempfile.mkdtemp(prefix="slicer-harness-")

    def processEvents(self):
        pass


def new_scene():
    """A new real ``vtkMRMLScene``, made ``slicer.mrmlScene``, with the Segmentations module's
    logic (the segmentation conversion rules and node classes) and the Subject Hierarchy module's
    logic (an item for every new data node) attached."""
    import slicer
    import vtk

    scene = slicer.vtkMRMLScene()
    logic = slicer.vtkSlicerSegmentationsModuleLogic()
    logic.SetMRMLScene(scene)
    hierarchy = slicer.vtkSlicerSubjectHierarchyModuleLogic()
    hierarchy.SetMRMLScene(scene)
    colors = slicer.vtkSlicerColorLogic()
    shown = vtk.vtkObject.GetGlobalWarningDisplay()
    vtk.vtkObject.GlobalWarningDisplayOff()  # it finds no colour-table files: there are none
    colors.SetMRMLScene(scene)
    vtk.vtkObject.SetGlobalWarningDisplay(shown)
    scene._harness_logics = (logic, hierarchy, colors)  # kept alive with the scene
    slicer.modules = types.SimpleNamespace(colors=types.SimpleNamespace(logic=lambda: colors))
    slicer.mrmlScene = scene
    return scene


def segmentations_logic():
    """The Segmentations module logic of the current scene (``slicer.modules.segmentations
    .logic()`` in the application)."""
    import slicer

    return slicer.mrmlScene._harness_logics[0]


# -- slicer.parameterNodeWrapper ----------------------------------------------------------------


class Choice:
    """The value must be one of ``choices``."""

    def __init__(self, choices):
        self.choices = list(choices)

    def validate(self, value):
        if value not in self.choices:
            raise ValueError(f"{value!r} is not one of {self.choices}")


class WithinRange:
    """The value must lie in [minimum, maximum]."""

    def __init__(self, minimum, maximum):
        self.minimum, self.maximum = minimum, maximum

    def validate(self, value):
        if not self.minimum <= value <= self.maximum:
            raise ValueError(f"{value!r} is not within [{self.minimum}, {self.maximum}]")


class _Parameter:
    """One typed parameter of a parameter node, stored as Slicer's serializers store it: a list
    as ``name_len`` and one entry ``name_<index>`` per item (a node: a node reference)."""

    def __init__(self, name, annotated, default):
        import slicer

        self.name = name
        self.validators = []
        kind = annotated
        if typing.get_origin(annotated) is typing.Annotated:
            kind, *extras = typing.get_args(annotated)
            self.validators = [e for e in extras if hasattr(e, "validate")]
        self.item = None
        if typing.get_origin(kind) is list:
            (item,) = typing.get_args(kind)
            self.item = _Parameter(name, item, _NO_DEFAULT)
            kind = list
        self.kind = kind
        self.is_node = isinstance(kind, type) and issubclass(kind, slicer.vtkMRMLNode)
        if default is _NO_DEFAULT:
            default = {int: 0, float: 0.0, str: "", bool: False}.get(kind)
            if kind is pathlib.Path:
                default = pathlib.Path()
            if kind is list:
                default = []
        self.default = default

    def write(self, node, value, name=None):
        name = name or self.name
        if self.item is not None:
            old = int(node.GetParameter(f"{name}_len") or 0)
            for index, item in enumerate(value):
                self.item.write(node, item, f"{name}_{index}")
            node.SetParameter(f"{name}_len", str(len(value)))
            for index in range(len(value), old):
                node.UnsetParameter(f"{name}_{index}")
                node.RemoveNodeReferenceIDs(f"{name}_{index}")
            return
        if self.is_node:
            if value is not None and not isinstance(value, self.kind):
                raise TypeError(f"{name}: expected a {self.kind.__name__}")
            node.SetParameter(name, "")
            node.SetNodeReferenceID(name, value.GetID() if value is not None else None)
            return
        if self.kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, self.kind):
            raise TypeError(f"{name}: expected {self.kind.__name__}, got {value!r}")
        for validator in self.validators:
            validator.validate(value)
        text = ("True" if value else "False") if self.kind is bool else str(value)
        node.SetParameter(name, text)

    def read(self, node, name=None):
        name = name or self.name
        if self.item is not None:
            count = int(node.GetParameter(f"{name}_len") or 0)
            return [self.item.read(node, f"{name}_{index}") for index in range(count)]
        if self.is_node:
            return node.GetNodeReference(name)
        text = node.GetParameter(name)
        if self.kind is bool:
            return text == "True"
        return self.kind(text)

    def stored(self, node) -> bool:
        return node.HasParameter(f"{self.name}_len" if self.item is not None else self.name)


_NO_DEFAULT = object()


def parameterNodeWrapper(classtype):
    """Stands in for Slicer's ``@parameterNodeWrapper``: typed properties over a
    ``vtkMRMLScriptedModuleNode`` (``wrapper.parameterNode``), defaults written on wrapping."""
    hints = typing.get_type_hints(classtype, include_extras=True)
    parameters = {name: _Parameter(name, kind, classtype.__dict__.get(name, _NO_DEFAULT))
                  for name, kind in hints.items()}

    def __init__(self, parameterNode):
        self.parameterNode = parameterNode
        for parameter in parameters.values():
            if not parameter.stored(parameterNode):
                parameter.write(parameterNode, parameter.default)

    for name, parameter in parameters.items():
        setattr(classtype, name, property(
            lambda self, p=parameter: p.read(self.parameterNode),
            lambda self, value, p=parameter: p.write(self.parameterNode, value)))
    classtype.__init__ = __init__
    classtype.allParameters = parameters
    classtype.getValue = lambda self, name: getattr(self, name)
    classtype.setValue = lambda self, name, value: setattr(self, name, value)
    classtype.default = lambda self, name: types.SimpleNamespace(value=parameters[name].default)
    return classtype


# -- slicer.ScriptedLoadableModule --------------------------------------------------------------


class ScriptedLoadableModule:
    def __init__(self, parent):
        self.parent = parent
        self.moduleName = type(self).__name__


class ScriptedLoadableModuleLogic:
    def __init__(self, parent=None):
        name = type(self).__name__
        self.moduleName = name[:-len("Logic")] if name.endswith("Logic") else name

    def getParameterNode(self):
        """The module's singleton parameter node in ``slicer.mrmlScene``, made when missing."""
        import slicer

        scene = slicer.mrmlScene
        node = scene.GetSingletonNode(self.moduleName, "vtkMRMLScriptedModuleNode")
        if node is not None:
            return node
        node = scene.CreateNodeByClass("vtkMRMLScriptedModuleNode")
        node.UnRegister(None)
        node.SetSingletonTag(self.moduleName)
        node.SetModuleName(self.moduleName)
        node.SetName(scene.GenerateUniqueName(self.moduleName))
        return scene.AddNode(node)


class ScriptedLoadableModuleWidget:
    def __init__(self, parent=None):
        self.parent = parent
        self.moduleName = type(self).__name__[:-len("Widget")]

    def setup(self):
        raise NotImplementedError("the harness has no GUI: test the Logic, or the .ui with Qt")


class ScriptedLoadableModuleTest(unittest.TestCase):
    def delayDisplay(self, message, msec=None):
        print(message)


# -- qt ------------------------------------------------------------------------------------------


def qt_module():
    """PySide6's QtCore, QtGui, QtWidgets and QtUiTools as one module, with a QApplication on the
    offscreen platform; None when PySide6 is not installed."""
    try:
        from PySide6 import QtCore, QtGui, QtUiTools, QtWidgets
    except ImportError:
        return None
    module = types.ModuleType("qt", "PySide6 standing in for PythonQt's qt module")
    for part in (QtCore, QtGui, QtWidgets, QtUiTools):
        for name in dir(part):
            if not name.startswith("_"):
                setattr(module, name, getattr(part, name))
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    if QtWidgets.QApplication.instance() is None:
        module.application = QtWidgets.QApplication(["harness"])
    return module


def install():
    """Put the stand-ins in place and the module's folder on ``sys.path`` (idempotent)."""
    global _installed
    if _installed:
        return
    import slicer

    qt = qt_module() or types.ModuleType("qt", "no Qt: PySide6 is not installed")
    sys.modules["qt"] = qt
    loadable = types.ModuleType("slicer.ScriptedLoadableModule")
    for cls in (ScriptedLoadableModule, ScriptedLoadableModuleLogic, ScriptedLoadableModuleWidget,
                ScriptedLoadableModuleTest):
        setattr(loadable, cls.__name__, cls)
    wrapper = types.ModuleType("slicer.parameterNodeWrapper")
    for item in (parameterNodeWrapper, Choice, WithinRange):
        setattr(wrapper, item.__name__, item)
    sys.modules["slicer.ScriptedLoadableModule"] = loadable
    sys.modules["slicer.parameterNodeWrapper"] = wrapper
    slicer.ScriptedLoadableModule = loadable
    slicer.parameterNodeWrapper = wrapper
    slicer.app = Application()
    new_scene()
    if str(MODULE_DIRECTORY) not in sys.path:
        sys.path.insert(0, str(MODULE_DIRECTORY))
    _installed = True
