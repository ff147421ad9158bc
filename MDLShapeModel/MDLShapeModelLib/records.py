"""The records the module's Logic returns: the nodes of a model, of an analysis, and the inputs
written as files."""

from __future__ import annotations

import pathlib
from dataclasses import dataclass, field

from mdlshapemodel.config import BuildConfig


@dataclass
class ShapeModelResult:
    """The MRML nodes of a built or loaded model."""

    outputDirectory: pathlib.Path | None
    modelFile: pathlib.Path
    folderItemID: int                       # subject-hierarchy folder holding the nodes
    meanModelNode: object                   # vtkMRMLModelNode, the mean shape (model frame)
    explorerModelNode: object               # vtkMRMLModelNode deformed by setModeWeights
    metricsTableNode: object | None         # vtkMRMLTableNode: C, G, S per mode with SEs
    scoresTableNode: object | None          # vtkMRMLTableNode: the cases' scores per mode
    # input order, rejected left out; several parts: each case's parts in turn ("case part")
    correspondenceModelNodes: list = field(default_factory=list)
    caseNames: list = field(default_factory=list)
    partNames: list = field(default_factory=list)     # [] for a one-part object
    rejected: list = field(default_factory=list)  # (name, reason)
    # a build guided by landmarks: each case's corresponded landmarks, a point list per case
    landmarkNodes: list = field(default_factory=list)
    interrupted: bool = False
    reportFile: pathlib.Path | None = None
    warnings: list = field(default_factory=list)  # the build's (metrics.json), e.g. absent labels
    # the optimisation ended by its stopping rule (None: nothing was optimised); when False, a
    # warning says what stopped it and how to carry it on
    converged: bool | None = None


@dataclass
class AnalysisNodes:
    """The MRML nodes of an analysis (:meth:`MDLShapeModelLogic.analyzeModel`)."""

    outputDirectory: pathlib.Path
    folderItemID: int
    effectModelNode: object           # vtkMRMLModelNode: the mean surface with the effect arrays
    pointsTableNode: object           # vtkMRMLTableNode: points.csv
    summary: dict                     # analysis.json
    pageFile: pathlib.Path            # analysis.html
    shapeModelNodes: list = field(default_factory=list)  # shapes/*.vtp, each named by its file
    text: str = ""                    # the findings in a few lines (analysisText)


@dataclass
class ExportedInputs:
    """Inputs written as files for the library, and those that could not be."""

    paths: list
    rejected: list                          # (name, reason)
    config: BuildConfig | None = None       # the build's settings, with the landmarks' folder
