"""The module's panel (MDLShapeModel/Resources/UI/MDLShapeModel.ui) loaded by a real Qt loader:
PySide6's QUiLoader, offscreen, with stand-ins for the CTK and qMRML widget classes that only Slicer has.

The stand-ins are plain Qt widgets of the same names, with the properties the .ui sets (a
collapsible section shows its title and hides its body when collapsed; the node selectors are
combo boxes). The picture is therefore the panel as the .ui lays it out, filled the way the
parameter-node wrapper fills it (choices and defaults), not a screenshot of Slicer.

    python Testing/Slicer/panel.py Resources/Screenshots/panel.png     # (re)draw the picture
"""

from __future__ import annotations

import os
import sys
import typing

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

from PySide6 import QtCore, QtUiTools, QtWidgets  # noqa: E402
from PySide6.QtCore import Property  # noqa: E402


class qMRMLWidget(QtWidgets.QWidget):
    """Stands in for qMRMLWidget (a widget with an MRML scene)."""


class ctkCollapsibleButton(QtWidgets.QGroupBox):
    """Stands in for ctkCollapsibleButton: a titled section whose body hides when collapsed."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self._text, self._collapsed = "", False

    def _show(self):
        self.setTitle(("\u25b8 " if self._collapsed else "\u25be ") + self._text)
        for child in self.findChildren(QtWidgets.QWidget, options=QtCore.Qt.FindDirectChildrenOnly):
            child.setVisible(not self._collapsed)
        self.setFlat(self._collapsed)

    def getText(self):
        return self._text

    def setText(self, text):
        self._text = text
        self._show()

    def getCollapsed(self):
        return self._collapsed

    def setCollapsed(self, collapsed):
        self._collapsed = bool(collapsed)
        self._show()

    def showEvent(self, event):
        self._show()
        super().showEvent(event)

    text = Property(str, getText, setText)
    collapsed = Property(bool, getCollapsed, setCollapsed)


class ctkPathLineEdit(QtWidgets.QLineEdit):
    """Stands in for ctkPathLineEdit (a path with a browse button)."""


class qMRMLNodeComboBox(QtWidgets.QComboBox):
    """Stands in for qMRMLNodeComboBox (chooses a node of the scene)."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.addItem("None")


class qMRMLCheckableNodeComboBox(QtWidgets.QComboBox):
    """Stands in for qMRMLCheckableNodeComboBox (checks several nodes of the scene): it names
    the kinds of node its ``nodeTypes`` take, none checked."""

    KINDS = {"vtkMRMLSegmentationNode": "segmentations", "vtkMRMLLabelMapVolumeNode": "label maps",
             "vtkMRMLModelNode": "models", "vtkMRMLMarkupsFiducialNode": "point lists"}

    def __init__(self, parent=None):
        super().__init__(parent)
        self._types = []
        self.addItem("none checked")

    def getNodeTypes(self):
        return self._types

    def setNodeTypes(self, types):
        self._types = list(types)
        self.setItemText(0, ", ".join(self.KINDS.get(t, t) for t in self._types)
                         + ": none checked")

    nodeTypes = Property("QStringList", getNodeTypes, setNodeTypes)


class qMRMLTableView(QtWidgets.QTableView):
    """Stands in for qMRMLTableView (shows a table node)."""


STANDINS = (qMRMLWidget, ctkCollapsibleButton, ctkPathLineEdit, qMRMLNodeComboBox,
            qMRMLCheckableNodeComboBox, qMRMLTableView)


def application():
    return QtWidgets.QApplication.instance() or QtWidgets.QApplication(["panel"])


def load_panel(path, messages=None):
    """The panel's root widget, loaded from the .ui at ``path`` with the stand-ins registered;
    Qt's messages while loading are appended to ``messages`` (a list) instead of printed."""
    application()
    loader = QtUiTools.QUiLoader()
    for standin in STANDINS:
        loader.registerCustomWidget(standin)
    collected = [] if messages is None else messages
    previous = QtCore.qInstallMessageHandler(lambda kind, context, text: collected.append(text))
    try:
        handle = QtCore.QFile(str(path))
        handle.open(QtCore.QFile.ReadOnly)
        widget = loader.load(handle)
        handle.close()
    finally:
        QtCore.qInstallMessageHandler(previous)
    if widget is None:
        raise RuntimeError(f"{path}: {loader.errorString()}")
    return widget


def parameter_widgets(panel) -> dict:
    """Parameter name -> widget, for every widget with a SlicerParameterName."""
    found = {}
    for widget in panel.findChildren(QtWidgets.QWidget):
        name = widget.property("SlicerParameterName")
        if name:
            found.setdefault(name, []).append(widget)
    return found


def fill(panel, parameter_node_class):
    """Show choices and defaults as the parameter-node wrapper's GUI binding does."""
    from slicer.parameterNodeWrapper import Choice

    hints = typing.get_type_hints(parameter_node_class, include_extras=True)
    for name, widgets in parameter_widgets(panel).items():
        default = parameter_node_class.allParameters[name].default
        for widget in widgets:
            if isinstance(widget, QtWidgets.QComboBox) and not isinstance(widget, qMRMLNodeComboBox):
                extras = typing.get_args(hints[name])[1:]
                choices = next(e.choices for e in extras if isinstance(e, Choice))
                widget.addItems([str(c) for c in choices])
                widget.setCurrentText(str(default))
            elif isinstance(widget, QtWidgets.QCheckBox):
                widget.setChecked(bool(default))
            elif isinstance(widget, (QtWidgets.QSpinBox, QtWidgets.QDoubleSpinBox)):
                widget.setValue(default)
            elif isinstance(widget, QtWidgets.QLineEdit) and str(default) not in ("", "."):
                widget.setText(str(default))


def render(panel, destination, width=420):
    """Draw the panel offscreen to a PNG file."""
    panel.resize(width, panel.sizeHint().height())
    panel.show()
    application().processEvents()
    panel.resize(width, panel.sizeHint().height())
    application().processEvents()
    if not panel.grab().save(str(destination)):
        raise OSError(f"{destination}: could not be written")


def show_only(panel, sections):
    """Expand the sections with these titles and collapse the others."""
    for section in panel.findChildren(ctkCollapsibleButton):
        section.setCollapsed(section.getText() not in sections)


def main(destination, sections=()):
    """Render the panel to ``destination``; with ``sections`` (titles), only those expanded."""
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import harness

    harness.install()
    import MDLShapeModel

    panel = load_panel(MDLShapeModel.resourcePath("UI/MDLShapeModel.ui"))
    fill(panel, MDLShapeModel.MDLShapeModelParameterNode)
    if sections:
        show_only(panel, sections)
    render(panel, destination)


if __name__ == "__main__":
    # python panel.py OUT.png [SECTION ...]: e.g. panel.png, or analysis.png Analysis
    main(sys.argv[1], sys.argv[2:])
