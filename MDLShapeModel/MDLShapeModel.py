"""MDLShapeModel: the 3D Slicer module of the mdlshapemodel library.

Segmentations, label-map volumes, models or a folder of files -> a statistical shape model whose
point correspondence minimises the description length of the training set (Davies et al., IEEE
TMI 2010). The module is glue: every step of geometry and statistics is the library's
(``mdlshapemodel.build_model``, ``ShapeModel``, ``fit_case``); this file only moves data between
the MRML scene and the library's files.

- :class:`MDLShapeModelLogic` works without any GUI (scripts, tests, other modules, batch):
  ``buildModel``, ``loadModel``, ``setModeWeights``, ``fitSegmentation``.
- :class:`MDLShapeModelWidget` is the panel: it fills the parameter node, starts the Logic's
  work in a process of its own (:class:`~MDLShapeModelLib.jobs.WorkerJob`: a build, an
  analysis, a fit), polls its progress from a timer and shows the results.

The module's helpers are in ``MDLShapeModelLib/`` beside this file: the nodes (``nodes``), the
worker process and its jobs (``worker``, ``jobs``), the panel's messages (``messages``).

Coordinates: Slicer's world is RAS; the library's physical space is LPS, like the image files
SimpleITK reads. Inputs go to the library as files written by Slicer's own storage nodes (which
write LPS), and the library's meshes say ``SPACE=LPS`` so Slicer's model storage node turns them
into RAS on reading: every corresponded model overlays the segmentation it came from.

Only the light ``mdlshapemodel.config`` is imported here at import time; the library's heavier
dependencies (numba, h5py, scipy, ...) are imported when a build or a model is first used, and
installed (after asking) by the panel if Slicer lacks them (:func:`ensureDependencies`).
"""

from __future__ import annotations

import contextlib
import os
import pathlib
import traceback
import typing
from dataclasses import asdict, replace
from typing import Annotated

import qt
import slicer
from slicer.parameterNodeWrapper import Choice, WithinRange, parameterNodeWrapper
from slicer.ScriptedLoadableModule import (ScriptedLoadableModule, ScriptedLoadableModuleLogic,
                                           ScriptedLoadableModuleTest,
                                           ScriptedLoadableModuleWidget)
from slicer.util import VTKObservationMixin

from mdlshapemodel.config import (CORRESPONDENCES, GUIDED_SMOOTHNESS, PLACEMENTS, SMOOTHNESS,
                                  STRATEGIES, SURFACE_METHODS, AnalysisConfig, BuildConfig,
                                  field_items)
from MDLShapeModelLib.dependencies import ensureDependencies
from MDLShapeModelLib.findings import analysisText
from MDLShapeModelLib.jobs import WorkerJob
from MDLShapeModelLib.messages import ANALYSIS_PARAMETERS, panelLabels, panelMessage
from MDLShapeModelLib.nodes import (INPUT_NODE_TYPES, addModel, addPointArray, caseName,
                                    checkData, colorLegend, colorNode, metricsTable,
                                    placeInFolder, readModel, scoresTable,
                                    segmentNames, subjectHierarchy, tableNode, temporaryFolder,
                                    toRas, uniqueName, writeNode, writeSegmentation)
from MDLShapeModelLib.records import AnalysisNodes, ExportedInputs, ShapeModelResult
from MDLShapeModelLib.resources import resourcePath

# The point arrays of an analysis's effect map that can colour it (effects.vtp): significance
# (-log10 of the family-wise p-value) and the effect along the outward normal (mm).
EFFECT_SCALARS = ("minus_log10_p_fwer", "normal_difference_mm")


# ---------------------------------------------------------------------------------------------
# Module


class MDLShapeModel(ScriptedLoadableModule):
    """The module's description for Slicer's module list."""

    def __init__(self, parent):
        ScriptedLoadableModule.__init__(self, parent)
        self.parent.title = "MDL Shape Model"
        self.parent.categories = ["Shape Analysis"]
        self.parent.dependencies = []
        self.parent.contributors = ["MDLShapeModel developers"]
        self.parent.helpText = (
            "Builds a statistical shape model (mean shape, modes of variation, per-case scores) "
            "of one structure segmented in many subjects. Point correspondence is found by "
            "minimising the description length of the whole training set over homeomorphisms of "
            "the sphere (Davies et al., IEEE TMI 2010), so a correspondence never folds or tears.")
        self.parent.acknowledgementText = (
            "Method: Davies, Twining, Cootes and Taylor, Building 3-D statistical shape models by "
            "direct optimization, IEEE Transactions on Medical Imaging 29(4), 2010.")
        try:
            self.parent.icon = qt.QIcon(str(resourcePath("Icons/MDLShapeModel.png")))
        except FileNotFoundError:
            pass  # Slicer's default icon


# ---------------------------------------------------------------------------------------------
# Parameter node: every setting of the panel, saved with the scene. The build settings are the
# BuildConfig fields of the same names, with BuildConfig's defaults and choices (read from it here:
# one source); list settings are written as text ("1, 2").

MAIN_SETTINGS = ("labels", "surface_method", "points", "strategy", "max_time", "baselines")
ADVANCED_SETTINGS = ("correspondence", "smoothing_sigma", "edge_length", "mirror", "parts", "seed",
                     "evaluation_modes", "specificity_samples", "workers", "strict",
                     "allow_duplicates", "smoothness", "placement")
BUILD_SETTINGS = MAIN_SETTINGS + ADVANCED_SETTINGS
# beside the landmark point lists: settings of a build given landmarks (landmarkConfigOf)
LANDMARK_SETTINGS = ("check_landmarks",)
# the parameters holding several nodes, and the checkable node selectors that show them (the
# Widget keeps the two in step: Slicer's GUI binding has no connector for such selectors)
CHECKED_NODE_PARAMETERS = {"inputNodes": "inputNodesSelector",
                           "landmarkNodes": "landmarkNodesSelector"}

_BUILD_DEFAULTS = BuildConfig()
_ANALYSIS_DEFAULTS = AnalysisConfig()
_COUNT = WithinRange(0, 10**9)   # a count or number entered in a spin box


def _defaultText(name: str) -> str:
    """BuildConfig's default of the list setting ``name`` written as the panel's text."""
    return ", ".join(str(v) for v in getattr(_BUILD_DEFAULTS, name))


@parameterNodeWrapper
class MDLShapeModelParameterNode:
    """The MDLShapeModel module's parameters: the inputs, every build setting, the results shown
    and the analysis's choices. Stored in the module's parameter node, so saved with the scene."""

    # -- inputs: checked nodes, a folder of label maps or meshes, the segments of segmentations
    inputNodes: list[slicer.vtkMRMLNode]
    landmarkNodes: list[slicer.vtkMRMLMarkupsFiducialNode]
    inputFolder: pathlib.Path
    segments: str = ""              # segment names (comma separated); empty: all segments
    check_landmarks: bool = _BUILD_DEFAULTS.check_landmarks

    # -- the build's main settings
    labels: str = _defaultText("labels")
    surface_method: Annotated[str, Choice(list(SURFACE_METHODS))] = _BUILD_DEFAULTS.surface_method
    points: Annotated[int, _COUNT] = _BUILD_DEFAULTS.points_for(curves=False)  # the panel's
    strategy: Annotated[str, Choice(list(STRATEGIES))] = _BUILD_DEFAULTS.strategy  # surfaces
    max_time: float = _BUILD_DEFAULTS.max_time
    baselines: str = _defaultText("baselines")
    outputDirectory: pathlib.Path

    # -- advanced settings
    correspondence: Annotated[str, Choice(list(CORRESPONDENCES))] = _BUILD_DEFAULTS.correspondence
    smoothing_sigma: float = _BUILD_DEFAULTS.smoothing_sigma
    edge_length: float = _BUILD_DEFAULTS.edge_length
    mirror: str = _defaultText("mirror")
    parts: str = _defaultText("parts")
    seed: Annotated[int, _COUNT] = _BUILD_DEFAULTS.seed
    evaluation_modes: Annotated[int, _COUNT] = _BUILD_DEFAULTS.evaluation_modes
    specificity_samples: Annotated[int, _COUNT] = _BUILD_DEFAULTS.specificity_samples
    workers: Annotated[int, _COUNT] = _BUILD_DEFAULTS.workers
    strict: bool = _BUILD_DEFAULTS.strict
    allow_duplicates: bool = _BUILD_DEFAULTS.allow_duplicates
    # the prior's weight by BuildConfig's rule (one weight unguided, another where landmarks
    # guide); off: ``smoothness``
    defaultSmoothness: bool = True
    smoothness: float = _BUILD_DEFAULTS.smoothness_for(curves=False)
    placement: Annotated[str, Choice(list(PLACEMENTS))] = _BUILD_DEFAULTS.placement

    # -- results: the model being explored, and the model that new cases are fitted to
    explorerModel: slicer.vtkMRMLModelNode
    modelFile: pathlib.Path

    # -- the analysis: a subjects table (a CSV file or a table node), the columns tested
    analysisTable: pathlib.Path
    analysisTableNode: slicer.vtkMRMLTableNode
    analysisGroup: str = ""
    analysisCovariates: str = ""
    analysisNuisance: str = ""
    analysisPermutations: Annotated[int, WithinRange(1, 10**7)] = _ANALYSIS_DEFAULTS.permutations
    analysisTfce: bool = _ANALYSIS_DEFAULTS.tfce
    # -- the analysis's group classifier (Classification, collapsed)
    analysisFolds: Annotated[int, WithinRange(2, 1000)] = _ANALYSIS_DEFAULTS.folds
    analysisRepeats: Annotated[int, WithinRange(1, 1000)] = _ANALYSIS_DEFAULTS.repeats
    analysisClassificationPermutations: Annotated[int, WithinRange(0, 10**7)] = (
        _ANALYSIS_DEFAULTS.classification_permutations)
    analysisColorBy: Annotated[str, Choice(list(EFFECT_SCALARS))] = EFFECT_SCALARS[0]


def buildConfigOf(parameters) -> BuildConfig:
    """The :class:`BuildConfig` that a parameter node's build settings amount to (validated: a
    bad value raises ``ConfigError`` naming the field)."""
    values = {}
    for name in BUILD_SETTINGS:
        value = getattr(parameters, name)
        if typing.get_origin(typing.get_type_hints(BuildConfig)[name]) is list:
            value = field_items(name, value)
        values[name] = value
    if parameters.defaultSmoothness:
        values["smoothness"] = None
    return BuildConfig(**values).validate()


def analysisConfigOf(parameters) -> AnalysisConfig:
    """The :class:`AnalysisConfig` that a parameter node's analysis settings amount to (its
    fields named in :data:`ANALYSIS_PARAMETERS`; validated: a bad value raises ``ConfigError``
    naming the field)."""
    values = {key: getattr(parameters, name) for key, name in ANALYSIS_PARAMETERS.items()}
    for key in ("covariates", "nuisance"):
        values[key] = segmentNames(values[key])
    return AnalysisConfig(**{**values, "group": values["group"] or None}).validate()


def landmarkConfigOf(config: BuildConfig, parameters, landmarks: bool) -> BuildConfig:
    """``config`` with the parameter node's landmark settings (:data:`LANDMARK_SETTINGS`), for a
    build given landmark point lists (``landmarks``); ValueError where one is set without any
    (the landmarks' folder joins the configuration when they are exported)."""
    values = {name: getattr(parameters, name) for name in LANDMARK_SETTINGS}
    if values["check_landmarks"] and not landmarks:
        raise ValueError("Check landmarks: check the cases' landmark point lists (Landmarks) "
                         "to be checked")
    return replace(config, **values)


# ---------------------------------------------------------------------------------------------
# Logic


class MDLShapeModelLogic(ScriptedLoadableModuleLogic):
    """Everything the module does, without any GUI.

    Examples
    --------
    ::

        logic = MDLShapeModelLogic()
        result = logic.buildModel([segmentationNode1, segmentationNode2, segmentationNode3],
                                  "/data/model", BuildConfig(labels=[1, 2]))
        result.meanModelNode, result.correspondenceModelNodes, result.rejected
        logic.setModeWeights(result.explorerModelNode, [2.0, -1.0])   # SDs of modes 1 and 2
    """

    def __init__(self):
        ScriptedLoadableModuleLogic.__init__(self)

    def getParameterNode(self):
        return MDLShapeModelParameterNode(super().getParameterNode())

    # -- inputs -> files -------------------------------------------------------------------

    def exportInputs(self, inputs, folder, config: BuildConfig | None = None,
                     segments=None, landmarks=None) -> ExportedInputs:
        """Write node inputs as files the library reads; file paths pass through.

        ``landmarks``: one markups node (or None) per input, written by Slicer's markups storage
        node as ``landmarks/<case>.mrk.json`` beside the inputs; the returned ``config`` then
        names that folder (``BuildConfig.landmarks``), so that they guide the build.

        Segmentation nodes: the union of ``segments`` (names; None or empty: all segments) as a
        label map in the segmentation's reference geometry, with the value ``config.labels[0]``
        (1 when no labels are set) so that the build's label selection keeps it. Label-map
        volumes as .nrrd, models as .vtp, through Slicer's storage nodes (which write LPS). A node
        that cannot be exported is rejected with its reason; the others go on.
        """
        config = config or BuildConfig()
        folder = pathlib.Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        paths, rejected, used = [], [], set()
        markups = list(landmarks) if landmarks is not None else [None] * len(inputs)
        if len(markups) != len(inputs):
            raise ValueError(f"{len(markups)} landmark nodes for {len(inputs)} inputs")
        marks = folder / "landmarks"
        if any(node is not None for node in markups):
            marks.mkdir(exist_ok=True)
            config = replace(config, landmarks=str(marks))
        for item, node in zip(inputs, markups):
            name = caseName(item)
            if isinstance(item, (str, os.PathLike)):
                paths.append(pathlib.Path(item))
            else:
                name = uniqueName(name, used)
            if node is not None:     # named after the case, as the build looks for it
                writeNode(node, marks / f"{name}.mrk.json", "vtkMRMLMarkupsJsonStorageNode")
            if isinstance(item, (str, os.PathLike)):
                continue
            try:
                if item.IsA("vtkMRMLSegmentationNode"):
                    value = config.labels[0] if config.labels else 1
                    paths.append(writeSegmentation(item, segments, value, folder / f"{name}.nrrd"))
                elif item.IsA("vtkMRMLLabelMapVolumeNode"):
                    checkData(item)
                    paths.append(writeNode(item, folder / f"{name}.nrrd",
                                            "vtkMRMLVolumeArchetypeStorageNode"))
                elif item.IsA("vtkMRMLModelNode"):
                    checkData(item)
                    paths.append(writeNode(item, folder / f"{name}.vtp", "vtkMRMLModelStorageNode"))
                else:
                    raise ValueError(f"a {item.GetClassName()} is not an input (use "
                                     f"{', '.join(INPUT_NODE_TYPES)})")
            except ValueError as error:
                rejected.append((item.GetName(), str(error)))
        return ExportedInputs(paths, rejected, config)

    @staticmethod
    def landmarksOf(inputs, markupsNodes) -> list:
        """The markups node of each input (None where it has none): the one named after the
        input's case (a node's name; a file's name without its suffix), or that name followed
        by "_landmarks". Raises ValueError where a markups node matches no input."""
        names = [caseName(item) for item in inputs]
        byName = {}
        for node in markupsNodes:
            name = node.GetName().removesuffix("_landmarks")
            if name not in names:
                raise ValueError(f"landmarks {node.GetName()!r}: no input is named "
                                 f"{name!r} (name a point list after its case)")
            byName[name] = node
        return [byName.get(name) for name in names]

    # -- the build ---------------------------------------------------------------------------

    def buildModel(self, inputs, outputDirectory, config: BuildConfig | None = None,
                   progress=None, segments=None, overwrite: bool = False,
                   landmarks=None, resume: bool = False) -> ShapeModelResult:
        """Build a model of ``inputs`` and load it into the scene, waiting for the build's
        process (:meth:`startBuild`): the headless way, for scripts and batch use.

        Parameters
        ----------
        inputs : list
            vtkMRMLSegmentationNode, vtkMRMLLabelMapVolumeNode, vtkMRMLModelNode objects or file
            and folder paths, in any mix.
        outputDirectory : path
            The build's output folder (the library's layout); node inputs are written to its
            ``inputs/`` subfolder first.
        config : BuildConfig, optional
            Every setting (None: the defaults), as the command line fills it.
        progress : callable(fraction or None, message), optional
            The library's progress protocol; returning False cancels (the model of the state
            reached is still written and loaded when the optimisation was running).
        segments : list of str, optional
            Names of the segments whose union is the object (default: all).
        overwrite : bool
            Replace an earlier build in ``outputDirectory`` (else it is refused).
        landmarks : list, optional
            One vtkMRMLMarkupsFiducialNode (or None) per input: its control points, matched
            across the cases by label, guide the correspondence (``build --landmarks``).
        resume : bool
            Carry on an interrupted build in ``outputDirectory`` from its checkpoint (cancelled,
            its process ended, or stopped by its time budget).

        Returns
        -------
        ShapeModelResult
            With ``rejected`` holding every input that could not be used and why.
        """
        job = self.startBuild(inputs, outputDirectory, config, segments, overwrite, landmarks,
                              resume)
        job.wait(progress=progress)
        return job.finish()

    def startBuild(self, inputs, outputDirectory, config: BuildConfig | None = None,
                   segments=None, overwrite: bool = False, landmarks=None,
                   resume: bool = False) -> WorkerJob:
        """Export the inputs (here: they are nodes of the scene), then start the build in a
        process of its own (:class:`~MDLShapeModelLib.jobs.WorkerJob`); ``job.poll()`` gives its
        progress, ``job.finish()`` loads its results once ``job.done``. ``job.exported`` holds
        the inputs written and those rejected."""
        outputDirectory = pathlib.Path(outputDirectory)
        exported = self.exportInputs(inputs, outputDirectory / "inputs", config, segments,
                                     landmarks)
        config = (exported.config or BuildConfig()).validate()
        job = WorkerJob({"command": "build", "inputs": [str(p) for p in exported.paths],
                         "output": str(outputDirectory), "config": config.to_dict(),
                         "overwrite": overwrite, "resume": resume}, "build",
                        lambda end: self.loadResults(outputDirectory, exported.rejected,
                                                     end["interrupted"]),
                        temporaryFolder())
        job.exported = exported
        return job

    # -- results -> scene --------------------------------------------------------------------

    def loadResults(self, outputDirectory, rejected=(), interrupted: bool = False
                    ) -> ShapeModelResult:
        """The nodes of a build's output folder: the model (:meth:`loadModel`) and every case's
        corresponded model, in the build's case order, and for a build guided by landmarks
        every case's corresponded landmarks (``landmarks.csv``) as a point list."""
        from mdlshapemodel.folders import BuildFolder

        build = BuildFolder(outputDirectory)
        result = self.loadModel(build.model_file)
        for name in result.caseNames:
            for part in result.partNames or [""]:   # several parts: a node per part
                node = readModel(build.case_mesh(part, name), f"{name} {part}".strip())
                placeInFolder(node, result.folderItemID)
                result.correspondenceModelNodes.append(node)
        marks = {}
        for landmark in build.landmarks():
            marks.setdefault(landmark.case, []).append((landmark.label, landmark.point))
        for name, points in marks.items():
            node = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode",
                                                      f"{name} landmarks")
            for label, point in points:
                node.AddControlPoint(list(toRas([point])[0]), label)
            placeInFolder(node, result.folderItemID)
            result.landmarkNodes.append(node)
        result.rejected = list(rejected) + [(r.name, r.reason) for r in build.rejected()]
        result.interrupted = interrupted
        result.reportFile = build.report_file if build.report_file.exists() else None
        written = build.metrics()
        if written is not None:
            result.warnings = list(written.get("warnings", []))
            result.converged = written.get("optimisation", {}).get("converged")
        return result

    def loadModel(self, path) -> ShapeModelResult:
        """A model.h5 (or a build's folder) as nodes: the mean, a shape explorer and, when the
        build's tables are next to it, the metrics and scores tables. No correspondence nodes."""
        from mdlshapemodel.folders import BuildFolder

        build = BuildFolder(path)
        model, modelFile = build.model(), build.model_file
        folderName = modelFile.parent.name or "model"
        hierarchy = subjectHierarchy()
        folder = hierarchy.CreateFolderItem(hierarchy.GetSceneItemID(),
                                            f"MDL shape model {folderName}")
        mean = addModel(f"{folderName} mean", toRas(model.mean), model.triangles)
        explorer = addModel(f"{folderName} shape explorer", toRas(model.mean), model.triangles)
        polydata = explorer.GetPolyData()
        addPointArray(polydata, "MeanPoints", toRas(model.mean))
        for k in range(model.n_modes):
            standardDeviation = float(model.variances[k]) ** 0.5
            addPointArray(polydata, f"mode_{k + 1}", toRas(model.modes[k] * standardDeviation))
        addPointArray(polydata, "Displacement", [0.0] * len(model.mean))
        polydata.GetPointData().SetActiveScalars("Displacement")
        explorer.GetDisplayNode().SetActiveScalarName("Displacement")
        explorer.GetDisplayNode().SetScalarVisibility(True)
        mean.GetDisplayNode().SetVisibility(False)
        metrics = metricsTable(build, folderName)
        scores = scoresTable(build, folderName)
        for node in filter(None, (mean, explorer, metrics, scores)):
            placeInFolder(node, folder)
        return ShapeModelResult(build.path if build.is_build_model else None,
                                modelFile, folder, mean, explorer, metrics, scores,
                                caseNames=list(model.names), partNames=list(model.part_names))

    # -- analysis ----------------------------------------------------------------------------

    def analysisConfig(self, group=None, covariates=(), nuisance=(), **settings
                       ) -> AnalysisConfig:
        """The library's :class:`AnalysisConfig` of these choices (validated)."""
        return AnalysisConfig(group=group or None, covariates=list(covariates),
                              nuisance=list(nuisance), **settings).validate()

    def exportTable(self, table, folder) -> pathlib.Path:
        """A subjects table as a CSV file: a path passes through, a table node is written (its
        columns as they are, one row per case) to ``folder/subjects.csv``."""
        if isinstance(table, (str, os.PathLike)):
            return pathlib.Path(table)
        if not table.IsA("vtkMRMLTableNode"):
            raise ValueError(f"a {table.GetClassName()} is not a subjects table")
        import csv

        folder = pathlib.Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        data = table.GetTable()
        columns = [data.GetColumn(c) for c in range(data.GetNumberOfColumns())]
        path = folder / "subjects.csv"
        with open(path, "w", newline="", encoding="utf-8") as handle:
            writer = csv.writer(handle)
            writer.writerow([column.GetName() for column in columns])
            for row in range(data.GetNumberOfRows()):
                writer.writerow([data.GetValue(row, c).ToString()
                                 for c in range(len(columns))])
        return path

    def startAnalysis(self, buildDirectory, table, group=None, covariates=(), nuisance=(),
                      outputDirectory=None, **settings) -> WorkerJob:
        """Export the table (here: it may be a node), then start the analysis in a process of
        its own; ``job.finish()`` loads its nodes once ``job.done`` (see :meth:`startBuild`)."""
        buildDirectory = pathlib.Path(buildDirectory)
        outputDirectory = pathlib.Path(outputDirectory or buildDirectory / "analysis")
        config = self.analysisConfig(group, covariates, nuisance, **settings)
        path = self.exportTable(table, temporaryFolder())
        return WorkerJob({"command": "analyze", "build": str(buildDirectory), "table": str(path),
                          "output": str(outputDirectory), "config": asdict(config)},
                         "analysis", lambda end: self.loadAnalysis(outputDirectory),
                         temporaryFolder())

    def analyzeModel(self, buildDirectory, table, group=None, covariates=(), nuisance=(),
                     outputDirectory=None, progress=None, **settings) -> AnalysisNodes:
        """Test a build's shapes against a subjects table and load the findings, waiting for
        the analysis's process (:meth:`startAnalysis`).

        Parameters
        ----------
        buildDirectory : path
            A build's output folder.
        table : path or vtkMRMLTableNode
            The subjects table: a ``case`` column with the build's case names, other columns
            variables.
        group : str, optional
            The categorical column whose groups are compared.
        covariates, nuisance : sequence of str
            Numeric columns tested (adjusted for, with a group), and columns adjusted for.
        outputDirectory : path, optional
            The analysis's folder (default ``buildDirectory/analysis``; an earlier analysis
            there is replaced).
        progress : callable(fraction or None, message), optional
            The library's progress protocol; returning False cancels.
        settings
            Other :class:`AnalysisConfig` fields (``permutations``, ``size``, ``alpha``, ...).

        Returns
        -------
        AnalysisNodes
            The effect map (coloured by -log10 p, family-wise) and the per-point table.
        """
        job = self.startAnalysis(buildDirectory, table, group, covariates, nuisance,
                                 outputDirectory, **settings)
        job.wait(progress=progress)
        return job.finish()

    def loadAnalysis(self, outputDirectory) -> AnalysisNodes:
        """The nodes of an analysis's output folder: the effect map of each part (one part: one
        node, with every point array of the file) coloured by significance with a colour
        legend, the effect's shapes (shapes/*.vtp: group means, predicted shapes; hidden),
        points.csv as a table, and the findings as text (:func:`analysisText`)."""
        from mdlshapemodel.analyze import AnalysisFolder

        outputDirectory = pathlib.Path(outputDirectory)
        analysis = AnalysisFolder(outputDirectory)
        folder = subjectHierarchy().CreateFolderItem(
            subjectHierarchy().GetSceneItemID(), f"{outputDirectory.name} analysis")
        nodes = [readModel(path, f"{outputDirectory.name} effect {path.stem}")
                 for path in analysis.effect_meshes()]
        for node in nodes:
            self.colorEffectMap(node, EFFECT_SCALARS[0])
            placeInFolder(node, folder)
        shapes = [readModel(path, f"{outputDirectory.name} shape {path.stem}")
                  for path in analysis.shape_meshes()]
        for node in shapes:
            # beside the effect map, hidden until chosen in the folder
            node.GetDisplayNode().SetVisibility(False)
            placeInFolder(node, folder)
        points = tableNode(f"{outputDirectory.name} points", analysis.points())
        placeInFolder(points, folder)
        summary = analysis.summary()
        return AnalysisNodes(outputDirectory, folder, nodes[0], points, summary,
                             analysis.page_file, shapeModelNodes=shapes,
                             text=analysisText(summary))

    def colorEffectMap(self, effectModelNode, scalars: str) -> None:
        """Colour an effect map by one of :data:`EFFECT_SCALARS`: significance (-log10 of the
        family-wise p, from 0 to its largest value) or the effect along the normal (a diverging
        scale symmetric about 0, blue inwards); a colour legend shows the scale."""
        if scalars not in EFFECT_SCALARS:
            raise ValueError(f"colour by one of {', '.join(EFFECT_SCALARS)}, not {scalars!r}")
        display = effectModelNode.GetDisplayNode()
        array = effectModelNode.GetPolyData().GetPointData().GetArray(scalars)
        low, high = array.GetRange()
        if scalars == EFFECT_SCALARS[0]:
            colors, low = "viridis", 0.0
        else:
            colors, high = "coolwarm", max(abs(low), abs(high), 1e-9)
            low = -high
        display.SetActiveScalarName(scalars)
        display.SetAndObserveColorNodeID(colorNode(colors).GetID())
        display.SetScalarRangeFlag(display.UseManualScalarRange)
        display.SetScalarRange(low, high)
        display.SetScalarVisibility(True)
        colorLegend(display, "-log10 p (FWER)" if scalars == EFFECT_SCALARS[0]
                     else "effect along the normal [mm]")

    def setModeWeights(self, explorerModelNode, weights) -> None:
        """Deform a shape explorer node (:meth:`loadModel`) to the mean plus ``weights[k]``
        standard deviations of mode k+1; its ``Displacement`` array (mm from the mean) colours it.
        """
        import numpy as np
        from vtk.util.numpy_support import vtk_to_numpy

        polydata = explorerModelNode.GetPolyData()
        data = polydata.GetPointData()
        points = vtk_to_numpy(data.GetArray("MeanPoints")).copy()
        for k, weight in enumerate(weights):
            mode = data.GetArray(f"mode_{k + 1}")
            if mode is None:
                raise ValueError(f"the model has {k} modes; {len(weights)} weights given")
            points += float(weight) * vtk_to_numpy(mode)
        displacement = np.linalg.norm(points - vtk_to_numpy(data.GetArray("MeanPoints")), axis=1)
        vtk_to_numpy(polydata.GetPoints().GetData())[:] = points
        vtk_to_numpy(data.GetArray("Displacement"))[:] = displacement
        polydata.GetPoints().Modified()
        data.GetArray("Displacement").Modified()
        explorerModelNode.SetAttribute("MDLShapeModel.ModeWeights",
                                       " ".join(f"{float(w):g}" for w in weights))
        explorerModelNode.Modified()

    def startFit(self, inputNode, modelPath, outputDirectory, segments=None,
                 maxTime: float = 60.0) -> WorkerJob:
        """Export one new segmentation (or label map, model, file) and start fitting it to a
        model in a process of its own, as the command line's ``fit`` does (its folder is
        ``outputDirectory``); ``job.finish()`` gives (corresponded model node, reconstruction
        model node, the fit's summary of the case from fit.json)."""
        from mdlshapemodel.folders import BuildFolder, FitFolder
        from mdlshapemodel.model.fitting import build_config_of

        config = build_config_of(BuildFolder(modelPath).model())
        outputDirectory = pathlib.Path(outputDirectory)
        exported = self.exportInputs([inputNode], temporaryFolder(), config, segments)
        if exported.rejected:
            raise ValueError(f"{exported.rejected[0][0]}: {exported.rejected[0][1]}")

        def load(end):
            if not end["cases"]:
                raise ValueError(f"{end['rejected'][0][0]}: {end['rejected'][0][1]}")
            name = end["cases"][0]
            fit = FitFolder(outputDirectory)
            return (readModel(fit.case_mesh("", name), f"{name} fitted"),
                    readModel(fit.case_mesh("", name, reconstruction=True),
                              f"{name} reconstruction"),
                    fit.summary()[name])

        return WorkerJob({"command": "fit", "model": str(modelPath),
                          "inputs": [str(p) for p in exported.paths],
                          "output": str(outputDirectory), "max_time": maxTime}, "fit", load,
                         temporaryFolder())

    def fitSegmentation(self, inputNode, modelPath, outputDirectory, segments=None,
                        maxTime: float = 60.0):
        """:meth:`startFit`, waiting for its process: (corresponded model node, reconstruction
        model node, the fit's summary of the case)."""
        job = self.startFit(inputNode, modelPath, outputDirectory, segments, maxTime)
        job.wait()
        return job.finish()


# ---------------------------------------------------------------------------------------------
# Widget: the panel (thin: it fills the parameter node and calls the Logic)


class MDLShapeModelWidget(ScriptedLoadableModuleWidget, VTKObservationMixin):
    """The panel: Inputs, Parameters (Advanced collapsed), Run, Results, Analysis (collapsed)."""

    def __init__(self, parent=None):
        ScriptedLoadableModuleWidget.__init__(self, parent)
        VTKObservationMixin.__init__(self)
        self.logic = None
        self._parameterNode = None
        self._parameterNodeGuiTag = None
        self._job = None            # the build's WorkerJob while it runs
        self._analysisJob = None
        self._fitJob = None
        self._timer = None          # polls the running jobs (the main thread never waits)
        self._result = None
        self._sliders = []
        self._analysis = None
        self._labels = {}           # parameter -> its field's label (messages name fields)

    def setup(self):
        ScriptedLoadableModuleWidget.setup(self)
        uiWidget = slicer.util.loadUI(str(resourcePath("UI/MDLShapeModel.ui")))
        self.layout.addWidget(uiWidget)
        self.ui = slicer.util.childWidgetVariables(uiWidget)
        uiWidget.setMRMLScene(slicer.mrmlScene)
        self._labels = panelLabels(resourcePath("UI/MDLShapeModel.ui"))
        self.logic = MDLShapeModelLogic()
        self.ui.inputNodesSelector.nodeTypes = list(INPUT_NODE_TYPES)
        self.ui.applyButton.clicked.connect(self.onApply)
        self.ui.cancelButton.clicked.connect(self.onCancel)
        self.ui.openReportButton.clicked.connect(self.onOpenReport)
        self.ui.loadModelButton.clicked.connect(self.onLoadModel)
        self.ui.fitButton.clicked.connect(self.onFit)
        self.ui.analyzeButton.clicked.connect(self.onAnalyze)
        self.ui.cancelAnalysisButton.clicked.connect(self.onCancelAnalysis)
        self.ui.openAnalysisButton.clicked.connect(self.onOpenAnalysis)
        self.ui.analysisColorByComboBox.currentTextChanged.connect(self.onColorBy)
        self.ui.defaultSmoothnessCheckBox.toolTip = (
            f"The default weight: {SMOOTHNESS:g}, or {GUIDED_SMOOTHNESS:g} where landmarks guide "
            "the correspondence")
        self.ui.defaultSmoothnessCheckBox.toggled.connect(
            lambda on: self.ui.smoothnessSpinBox.setEnabled(not on))
        self.ui.inputNodesSelector.checkedNodesChanged.connect(self.onCheckedNodesChanged)
        self.ui.landmarkNodesSelector.checkedNodesChanged.connect(self.onCheckedNodesChanged)
        self.ui.inputFolderSelector.currentPathChanged.connect(self.updateCaseList)
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.StartCloseEvent, self.onSceneStartClose)
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.EndCloseEvent, self.onSceneEndClose)
        self._timer = qt.QTimer()
        self._timer.setInterval(200)
        self._timer.timeout.connect(self.onPoll)
        self.initializeParameterNode()

    def cleanup(self):
        self.removeObservers()
        self._timer.stop()
        for job in (self._job, self._analysisJob, self._fitJob):
            if job is not None:
                job.terminate()

    def enter(self):
        self.initializeParameterNode()

    def exit(self):
        if self._parameterNode and self._parameterNodeGuiTag is not None:
            self._parameterNode.disconnectGui(self._parameterNodeGuiTag)
            self._parameterNodeGuiTag = None

    def onSceneStartClose(self, caller, event):
        self.exit()
        self._parameterNode = None

    def onSceneEndClose(self, caller, event):
        if self.parent.isEntered:
            self.initializeParameterNode()

    def initializeParameterNode(self):
        self._parameterNode = self.logic.getParameterNode()
        if self._parameterNodeGuiTag is None:
            self._parameterNodeGuiTag = self._parameterNode.connectGui(self.ui)
        self._showCheckedNodes()
        self.updateCaseList()

    def _showCheckedNodes(self):
        """Check in the node selectors the nodes that the parameter node holds
        (:data:`CHECKED_NODE_PARAMETERS`), e.g. after a scene is loaded."""
        for name, selectorName in CHECKED_NODE_PARAMETERS.items():
            selector = getattr(self.ui, selectorName)
            chosen = {node.GetID() for node in getattr(self._parameterNode, name) if node}
            wasBlocked = selector.blockSignals(True)
            for node in selector.nodes():
                selector.setCheckState(node, qt.Qt.Checked if node.GetID() in chosen
                                       else qt.Qt.Unchecked)
            selector.blockSignals(wasBlocked)

    def onCheckedNodesChanged(self, *unused):
        """The checked nodes into the parameter node (so they are saved with the scene)."""
        if self._parameterNode is not None:
            for name, selectorName in CHECKED_NODE_PARAMETERS.items():
                setattr(self._parameterNode, name,
                        list(getattr(self.ui, selectorName).checkedNodes()))
        self.updateCaseList()

    def inputs(self) -> list:
        nodes = [node for node in self._parameterNode.inputNodes if node is not None]
        folder = str(self._parameterNode.inputFolder)
        if folder not in ("", "."):
            try:
                from mdlshapemodel.folders import find_inputs
            except ImportError:      # the library's packages are not installed yet: Apply asks
                return nodes + [folder]
            nodes += find_inputs([folder])
        return nodes

    def updateCaseList(self, *unused):
        self.ui.caseList.clear()
        for item in self.inputs():
            self.ui.caseList.addItem(item.GetName() if hasattr(item, "GetName")
                                     else pathlib.Path(item).name)
        self.ui.applyButton.enabled = self.ui.caseList.count >= 3 and self._job is None

    def _segments(self) -> list:
        return segmentNames(self._parameterNode.segments)

    @contextlib.contextmanager
    def _errorsShown(self, title: str):
        """Errors of the block shown in a message box, a setting at fault named by its field's
        label (:func:`~MDLShapeModelLib.messages.panelMessage`); the panel goes on."""
        try:
            yield
        except Exception as error:
            slicer.util.errorDisplay(f"{title}\n{panelMessage(error, self._labels)}",
                                     detailedText=traceback.format_exc())

    def onApply(self):
        if not ensureDependencies(ask=True):
            return
        from mdlshapemodel.folders import BuildFolder

        with self._errorsShown("Could not start the build."):
            markups = [node for node in self._parameterNode.landmarkNodes if node is not None]
            config = landmarkConfigOf(buildConfigOf(self._parameterNode), self._parameterNode,
                                      bool(markups))
            output = pathlib.Path(str(self._parameterNode.outputDirectory))
            build = BuildFolder(output)
            resume = build.unfinished() and slicer.util.confirmYesNoDisplay(
                f"{output} holds an unfinished build. Carry it on (No: start again)?")
            overwrite = not resume and bool(build.earlier_build())
            if overwrite and not slicer.util.confirmYesNoDisplay(
                    f"{output} holds an earlier build. Replace it?"):
                return
            self.ui.logText.clear()
            inputs = self.inputs()
            self._job = self.logic.startBuild(
                inputs, output, config, self._segments(), overwrite,
                self.logic.landmarksOf(inputs, markups) if markups else None, resume)
            for name, reason in self._job.exported.rejected:
                self.ui.logText.appendPlainText(f"rejected {name}: {reason}")
            self.ui.applyButton.enabled = False
            self.ui.cancelButton.enabled = True
            self._timer.start()

    def onCancel(self):
        """The first Cancel stops the build at its next report (the state reached is kept);
        a second one ends its process at once (the build resumes from its checkpoint)."""
        if self._job is None:
            return
        if self._job.cancelled:
            self._job.terminate()
            self.ui.logText.appendPlainText("stopped: Apply carries the build on")
        else:
            self._job.cancel()
            self.ui.logText.appendPlainText("cancelling: the state reached will be kept "
                                            "(Cancel again to stop at once)")

    @staticmethod
    def _showReports(job, progressBar, logText=None):
        """A job's new reports on a progress bar (and its warnings and reports in a log)."""
        for report in job.poll():
            if report.warning:
                if logText is not None:
                    logText.appendPlainText(f"warning: {report.message}")
                continue
            if report.fraction is not None:
                progressBar.value = int(100 * report.fraction)
            progressBar.format = report.message
            if logText is not None:
                logText.appendPlainText(report.message)

    def onPoll(self):
        """The timer's tick: every running job's reports shown, those that ended finished."""
        # each job's end is seen before its last reports are read, so that none is left unread
        if self._job is not None:
            ended = self._job.done
            self._showReports(self._job, self.ui.progressBar, self.ui.logText)
            if ended:
                job, self._job = self._job, None
                self.ui.cancelButton.enabled = False
                self.updateCaseList()
                with self._errorsShown("The build did not finish."):
                    self.showResult(job.finish())
        if self._analysisJob is not None:
            ended = self._analysisJob.done
            self._showReports(self._analysisJob, self.ui.analysisProgressBar)
            if ended:
                job, self._analysisJob = self._analysisJob, None
                self.ui.analyzeButton.enabled = True
                self.ui.cancelAnalysisButton.enabled = False
                with self._errorsShown("The analysis did not finish."):
                    self._analysis = job.finish()
                    self.ui.analysisTableView.setMRMLTableNode(self._analysis.pointsTableNode)
                    self.ui.analysisResultText.setPlainText(self._analysis.text)
                    self.ui.openAnalysisButton.enabled = True
                    self.onColorBy()
        if self._fitJob is not None and self._fitJob.done:
            job, self._fitJob = self._fitJob, None
            self.ui.fitButton.enabled = True
            with self._errorsShown("The fit did not finish."):
                job.finish()
        if self._job is None and self._analysisJob is None and self._fitJob is None:
            self._timer.stop()

    def showResult(self, result: ShapeModelResult):
        self._result = result
        self._parameterNode.explorerModel = result.explorerModelNode
        self.ui.openReportButton.enabled = result.reportFile is not None
        for name, reason in result.rejected:
            self.ui.logText.appendPlainText(f"rejected {name}: {reason}")
        for warning in result.warnings:
            self.ui.logText.appendPlainText(f"warning: {warning}")
        if result.metricsTableNode is not None:
            self.ui.metricsTableView.setMRMLTableNode(result.metricsTableNode)
        layout = self.ui.modeSlidersFrame.layout()
        for slider in self._sliders:
            layout.removeWidget(slider)
            slider.deleteLater()
        self._sliders = []
        polydata = result.explorerModelNode.GetPolyData()
        k = 1
        while polydata.GetPointData().GetArray(f"mode_{k}") is not None and k <= 10:
            slider = slicer.qMRMLSliderWidget()
            slider.minimum, slider.maximum, slider.singleStep, slider.value = -3.0, 3.0, 0.1, 0.0
            slider.toolTip = f"mode {k}, in standard deviations"
            slider.valueChanged.connect(self.onModeWeights)
            layout.addRow(f"Mode {k}:", slider)
            self._sliders.append(slider)
            k += 1

    def onModeWeights(self, *unused):
        if self._result is not None:
            self.logic.setModeWeights(self._result.explorerModelNode,
                                      [s.value for s in self._sliders])

    def onOpenReport(self):
        if self._result is not None and self._result.reportFile is not None:
            qt.QDesktopServices.openUrl(qt.QUrl.fromLocalFile(str(self._result.reportFile)))

    def onLoadModel(self):
        if not ensureDependencies(ask=True):
            return
        with self._errorsShown("Could not load the model."):
            self.showResult(self.logic.loadModel(str(self._parameterNode.modelFile)))

    def onFit(self):
        if not ensureDependencies(ask=True):
            return
        with self._errorsShown("Could not start the fit."):
            node = self.ui.fitInputSelector.currentNode()
            output = pathlib.Path(str(self._parameterNode.outputDirectory)) / "fitted"
            self._fitJob = self.logic.startFit(node, str(self._parameterNode.modelFile), output,
                                               self._segments())
            self.ui.fitButton.enabled = False
            self._timer.start()

    def onAnalyze(self):
        if not ensureDependencies(ask=True):
            return
        with self._errorsShown("Could not start the analysis."):
            parameters = self._parameterNode
            table = parameters.analysisTableNode or str(parameters.analysisTable)
            if table in ("", "."):
                raise ValueError("choose a subjects table (a CSV file or a table node)")
            self._analysisJob = self.logic.startAnalysis(
                str(parameters.outputDirectory), table, **asdict(analysisConfigOf(parameters)))
            self.ui.analyzeButton.enabled = False
            self.ui.cancelAnalysisButton.enabled = True
            self._timer.start()

    def onCancelAnalysis(self):
        if self._analysisJob is not None:
            self._analysisJob.cancel()

    def onColorBy(self, *unused):
        if self._analysis is not None:
            self.logic.colorEffectMap(self._analysis.effectModelNode,
                                      self._parameterNode.analysisColorBy)

    def onOpenAnalysis(self):
        if self._analysis is not None:
            qt.QDesktopServices.openUrl(qt.QUrl.fromLocalFile(str(self._analysis.pageFile)))


# ---------------------------------------------------------------------------------------------
# Test: the whole module on generated data, in a real Slicer (Developer mode: "Reload and Test")


class MDLShapeModelTest(ScriptedLoadableModuleTest):
    """Builds a model of generated ellipsoids through the Logic and checks the nodes."""

    def setUp(self):
        slicer.mrmlScene.Clear(0)

    def runTest(self):
        self.setUp()
        self.test_build_from_label_map_volumes()

    def test_build_from_label_map_volumes(self):
        import tempfile

        import numpy as np

        self.delayDisplay("Generating five ellipsoid label maps")
        volumes = []
        grid = np.mgrid[0:40, 0:40, 0:40].astype(float)
        for k in range(5):
            axes = np.array([12.0 + k, 9.0, 7.0 + 0.5 * k])
            inside = sum(((g - 20.0) / a) ** 2 for g, a in zip(grid, axes)) <= 1.0
            volume = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode",
                                                        f"ellipsoid_{k}")
            slicer.util.updateVolumeFromArray(volume, inside.astype(np.uint8))
            volumes.append(volume)
        config = BuildConfig(points=162, max_time=30, baselines=[], workers=1,
                             evaluation_modes=2, specificity_samples=50)
        self.delayDisplay("Building the model")
        result = MDLShapeModelLogic().buildModel(volumes, tempfile.mkdtemp(), config)
        from mdlshapemodel import ShapeModel

        model = ShapeModel.load(result.modelFile)
        names = [f"ellipsoid_{k}" for k in range(5)]
        self.assertEqual(result.caseNames, names)
        self.assertEqual(list(model.names), names)
        self.assertEqual(result.rejected, [])
        self.assertEqual(len(result.correspondenceModelNodes), 5)
        counts = {n.GetPolyData().GetNumberOfPoints() for n in result.correspondenceModelNodes}
        self.assertEqual(counts, {162})
        # the measures table: one row per mode, compactness the model's cumulative variances
        table = result.metricsTableNode.GetTable()
        self.assertEqual(table.GetNumberOfRows(), 2)
        compactness = [table.GetColumnByName("C").GetValue(m) for m in range(2)]
        np.testing.assert_allclose(compactness, np.cumsum(model.variances[:2]), rtol=1e-6)
        for title in ("G", "S", "G SE", "S SE"):
            column = table.GetColumnByName(title)
            self.assertTrue(all(column.GetValue(m) > 0 for m in range(2)), title)
        # two standard deviations of mode 1 move each point by 2 sqrt(lambda_1) |mode_1 there|
        before = slicer.util.arrayFromModelPoints(result.explorerModelNode).copy()
        MDLShapeModelLogic().setModeWeights(result.explorerModelNode, [2.0])
        after = slicer.util.arrayFromModelPoints(result.explorerModelNode)
        moved = np.linalg.norm(after - before, axis=1)
        expected = np.linalg.norm(model.instance(standard_deviations=np.array([2.0]))
                                  - model.instance(standard_deviations=np.array([0.0])), axis=1)
        self.assertGreater(float(expected.max()), 0.0)
        np.testing.assert_allclose(moved, expected, rtol=1e-5, atol=1e-6)
        displacement = slicer.util.arrayFromModelPointData(result.explorerModelNode,
                                                           "Displacement")
        np.testing.assert_allclose(displacement, expected, rtol=1e-5, atol=1e-6)
        self.delayDisplay("Test passed")

