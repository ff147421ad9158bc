"""The library's messages as the panel says them: a setting at fault named by its field's label.

The library's :class:`~mdlshapemodel.errors.ConfigError` carries the name of the setting at fault
(``setting``) and the message without it (``problem``); the command line names the setting by its
flag, the panel by the label of the field bound to it in the .ui (the one source of the labels).
Other messages that advise a setting name it by the command line's flag (``--allow-duplicates``:
the field's name with hyphens), which the panel says as its field's label.
"""

from __future__ import annotations

import pathlib
import re
import xml.etree.ElementTree as ElementTree

# The parameter-node names of the analysis's settings (AnalysisConfig field -> parameter).
ANALYSIS_PARAMETERS = {"group": "analysisGroup", "covariates": "analysisCovariates",
                       "nuisance": "analysisNuisance", "permutations": "analysisPermutations",
                       "tfce": "analysisTfce", "folds": "analysisFolds",
                       "repeats": "analysisRepeats",
                       "classification_permutations": "analysisClassificationPermutations"}


def panelLabels(uiFile) -> dict:
    """Parameter name -> the label of its field in the .ui (without the colon): the text of the
    label beside the widget bound to the parameter (``SlicerParameterName``), or beside the
    widget that holds it."""
    root = ElementTree.parse(pathlib.Path(uiFile)).getroot()
    labels = {}
    for layout in root.iter("layout"):
        rows = {}
        for item in layout.findall("item"):
            widget = item.find("widget")
            if widget is not None:
                rows.setdefault(item.get("row"), {})[item.get("column")] = widget
        for columns in rows.values():
            label, field = columns.get("0"), columns.get("1")
            if label is None or field is None or label.get("class") != "QLabel":
                continue
            text = label.find("property[@name='text']/string")
            if text is None or not text.text:
                continue
            for bound in field.iter("property"):
                if bound.get("name") == "SlicerParameterName":
                    labels[bound.find("string").text] = text.text.strip().rstrip(":")
    return labels


def panelMessage(error: Exception, labels: dict) -> str:
    """The message of ``error`` for the panel: a setting at fault (``error.setting``, a build
    setting or an AnalysisConfig field) named by its field's label in ``labels``
    (:func:`panelLabels`), and a flag of the command line that stands for a field of the panel
    (``--allow-duplicates``) by that field's label; the rest as it is."""
    setting = getattr(error, "setting", None)
    setting = ANALYSIS_PARAMETERS.get(setting, setting)
    message = f"{labels[setting]}: {error.problem}" if setting in labels else str(error)

    def label(flag):
        name = flag.group(1).replace("-", "_")
        name = ANALYSIS_PARAMETERS.get(name, name)
        return f"'{labels[name]}'" if name in labels else flag.group(0)

    return re.sub(r"--([a-z][a-z0-9-]*)", label, message)
