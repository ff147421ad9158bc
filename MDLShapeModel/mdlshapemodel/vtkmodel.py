"""VTK pipeline objects for the model-building half of the chain.

- :class:`ShapeModelBuilder`: any number of sphere-mapped surfaces (outputs of
  :class:`~mdlshapemodel.vtkfilters.SurfaceToSphereMap`) -> output 0, the model as a vtkPolyData
  (the mean shape with every mode as a vector array, see below); output 1, the corresponded
  surfaces (a vtkMultiBlockDataSet, one block per input, named by case);
- :class:`ShapeModelInstance`: a model polydata and weights in standard deviations -> a shape;
- :class:`ShapeModelReader`, :class:`ShapeModelWriter`: a ``model.h5`` file
  (:meth:`~mdlshapemodel.model.shape_model.ShapeModel.load` / ``save``) <-> a model polydata.

The builder takes the steps of ``build`` between the prepared cases and the model, not copies of
them: :func:`~mdlshapemodel.build.correspond` (initial correspondence, optimisation or CPD, and
the model of :func:`~mdlshapemodel.build.shape_model_of`). Cases passed through
``LabelMapToClosedSurface`` and ``SurfaceToSphereMap`` as ``build`` prepares them (see
:mod:`~mdlshapemodel.vtkfilters`) therefore give the model of ``build_model`` with the same
configuration. No baselines are evaluated and no file is written.

The model polydata
------------------
One vtkPolyData holds a :class:`~mdlshapemodel.model.shape_model.ShapeModel` exactly
(:func:`model_to_polydata`, :func:`polydata_to_model`):

- points: the mean shape; polygons: the triangles of the sampling grid (none for a point-set
  model);
- point data ``mode_1``, ``mode_2``, ...: each mode scaled to one standard deviation (3-vectors,
  for a warp by vector), ``UnitModes`` (3 components per mode: the modes as the model holds
  them, orthonormal in the area-weighted inner product; ``mode_k`` is its k-th triple times
  sqrt(``Variances[k-1]``)), ``AreaWeights`` (the weights of that inner product, sum 1) and, when
  the model has them, ``SphereCoordinates`` (each point's sampling position on the unit sphere);
- field data ``Variances`` (one per mode, descending, mm^2), ``Scores`` (a row per case, a
  component per mode), ``CaseNames``, ``PartSizes``, for a multi-part model ``PartNames`` (and
  the cell data ``part``: each triangle's part, 0, 1, ...), for a model built with landmarks
  ``LandmarkLabels`` and ``LandmarkRows`` (each label's point), and ``Metadata`` (JSON: the
  objective, the strategy, the voxel size, the data range and the build configuration of a
  built model). The builder adds ``InitialObjective`` (eq. 14 of the initial correspondence)
  and ``StoppedBy``: why the optimisation ended, "converged" or the limit that came first, "time
  limit" (``MaxTime``) or "sweep limit" (``MaxSweeps``), the model then being of the
  correspondence reached so far; absent when nothing was optimised (strategy ``none``, CPD).

All four follow the conventions of :mod:`~mdlshapemodel.vtkfilters`: Set/Get methods that call
``Modified()`` only when a value changes, an ``executions`` counter, progress through
``UpdateProgress`` and failures through VTK's error output, with the message kept in
``GetErrorText()`` and the outputs left empty.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import time

import numpy as np
import vtk
from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy

from .build import correspond
from .config import BuildConfig
from .errors import BuildError, Cancelled, ConfigError, InputError
from .folders import BuildFolder, physical_shapes
from .model.shape_model import ShapeModel
from .prepare import io, surface
from .prepare.case import PreparedCase, PreparedPart
from .prepare.landmarks import read_landmark_folder
from .prepare.sphere import SphereMap
from .vtkfilters import (MIRRORED, SPHERE_COORDINATES, VOXEL_SIZE, LibraryFilter, accessors,
                         add_field, field_value)

__all__ = ["BUILDER_SETTINGS", "ShapeModelBuilder", "ShapeModelInstance", "ShapeModelReader",
           "ShapeModelWriter", "model_to_polydata", "polydata_to_model"]

MODE = "mode_{}"                  # point data: mode k (from 1) at one standard deviation
UNIT_MODES = "UnitModes"
AREA_WEIGHTS = "AreaWeights"
VARIANCES = "Variances"
SCORES = "Scores"
CASE_NAMES = "CaseNames"
PART_SIZES = "PartSizes"
PART_NAMES = "PartNames"
LANDMARK_LABELS = "LandmarkLabels"    # field data of a guided model: its landmarks' labels
LANDMARK_ROWS = "LandmarkRows"        # and each one's point
PART = "part"
METADATA = "Metadata"
INITIAL_OBJECTIVE = "InitialObjective"
STOPPED_BY = "StoppedBy"          # field data of the builder's model: why the optimisation ended
CASE_NAME = "CaseName"            # field data of a builder input: its case name
# the builder's progress: reading its inputs up to here, the model and its outputs after END
START, END = 0.05, 0.95


def _add_array(data, name: str, values):
    """Add a numeric array to point or field data: a component per column of a 2-D array (a
    2-D array without columns, which VTK cannot hold, is stored flat: no values)."""
    values = np.asarray(values)
    if values.ndim == 2 and values.shape[1] == 0:
        values = values.reshape(-1)
    array = numpy_to_vtk(np.ascontiguousarray(values), deep=True)
    array.SetName(name)
    data.AddArray(array)


def _add_strings(data, name: str, values):
    array = vtk.vtkStringArray()
    array.SetName(name)
    for value in values:
        array.InsertNextValue(str(value))
    data.AddArray(array)


def _missing(what: str, name: str) -> InputError:
    return InputError(f"not a shape model: no {what} data {name} (the output of "
                      "ShapeModelBuilder or ShapeModelReader has it)")


def _array(data, name: str, what: str):
    """A numeric array of point or field data as numpy (a copy); InputError when missing."""
    array = data.GetArray(name)
    if array is None:
        raise _missing(what, name)
    return vtk_to_numpy(array).copy()


def _strings(data, name: str) -> list:
    array = data.GetAbstractArray(name)
    if not isinstance(array, vtk.vtkStringArray):
        raise _missing("field", name)
    return [array.GetValue(i) for i in range(array.GetNumberOfValues())]


def _json_value(value):
    """Metadata values that JSON has no type for: numpy arrays (as lists) and scalars."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"metadata value {value!r} cannot be kept in a model polydata")


def model_to_polydata(model: ShapeModel) -> vtk.vtkPolyData:
    """The model polydata of a shape model (see the module docstring): exact, float64.

    Parameters
    ----------
    model : ShapeModel

    Returns
    -------
    vtkPolyData
        :func:`polydata_to_model` gives the same model back.

    Examples
    --------
    >>> import numpy as np
    >>> from mdlshapemodel.model.shape_model import ShapeModel
    >>> shapes = np.random.default_rng(0).normal(size=(4, 6, 3))
    >>> model = ShapeModel.from_shapes(shapes, np.full(6, 1 / 6))
    >>> polydata = model_to_polydata(model)
    >>> polydata.GetPointData().GetArray("mode_1").GetNumberOfComponents()
    3
    >>> np.array_equal(polydata_to_model(polydata).modes, model.modes)
    True
    """
    mean = np.asarray(model.mean, dtype=np.float64)
    triangles = None if model.triangles is None or len(model.triangles) == 0 else model.triangles
    polydata = surface.arrays_to_polydata(mean, triangles)
    points, fields = polydata.GetPointData(), polydata.GetFieldData()
    modes = np.asarray(model.modes, dtype=np.float64)
    variances = np.asarray(model.variances, dtype=np.float64)
    for k, (mode, variance) in enumerate(zip(modes, variances)):
        _add_array(points, MODE.format(k + 1), mode * np.sqrt(max(variance, 0.0)))
    _add_array(points, UNIT_MODES, modes.transpose(1, 0, 2).reshape(len(mean), -1))
    _add_array(points, AREA_WEIGHTS, np.asarray(model.weights, dtype=np.float64))
    if model.parameters is not None:
        _add_array(points, SPHERE_COORDINATES, np.asarray(model.parameters, dtype=np.float64))
    _add_array(fields, VARIANCES, variances)
    _add_array(fields, SCORES, np.asarray(model.scores, dtype=np.float64))
    _add_strings(fields, CASE_NAMES, model.names)
    _add_array(fields, PART_SIZES, np.asarray(model.part_sizes, dtype=np.int64))
    if model.part_names:
        _add_strings(fields, PART_NAMES, model.part_names)
        if triangles is not None:
            _add_array(polydata.GetCellData(), PART, model.part_of_triangles().astype(np.int32))
    if model.landmarks:
        _add_strings(fields, LANDMARK_LABELS, list(model.landmarks))
        _add_array(fields, LANDMARK_ROWS, np.array(list(model.landmarks.values()), dtype=np.int64))
    add_field(polydata, METADATA, json.dumps(model.metadata, default=_json_value))
    return polydata


def polydata_to_model(polydata) -> ShapeModel:
    """The shape model that a model polydata holds (the output of :class:`ShapeModelBuilder` or
    :class:`ShapeModelReader`, or :func:`model_to_polydata`).

    Raises :class:`~mdlshapemodel.errors.InputError` naming what is missing when ``polydata`` is
    not a model polydata. Metadata arrays come back as numpy arrays.

    Examples
    --------
    ::

        builder.Update()
        model = polydata_to_model(builder.GetOutput())
        model.metadata["objective"], model.instance([1.0, -0.5])
    """
    if polydata is None or polydata.GetNumberOfPoints() == 0:
        raise InputError("the model is empty (did the filter before it fail?)")
    try:
        return _model_of(polydata)
    except (ValueError, InputError) as error:   # a model's arrays of other sizes, bad metadata
        raise InputError(f"not a shape model: {error}") from None


def _segments(polydata) -> np.ndarray:
    """The two-point lines of a model of 2-D curves, (m, 2)."""
    lines = polydata.GetLines()
    if not np.all(np.diff(vtk_to_numpy(lines.GetOffsetsArray())) == 2):
        raise InputError("its lines are not segments of two points")
    return vtk_to_numpy(lines.GetConnectivityArray()).reshape(-1, 2).astype(np.int64)


def _model_of(polydata) -> ShapeModel:
    point_data, fields = polydata.GetPointData(), polydata.GetFieldData()
    mean = vtk_to_numpy(polydata.GetPoints().GetData()).astype(np.float64)
    variances = _array(fields, VARIANCES, "field")
    names = _strings(fields, CASE_NAMES)
    n_points, n_modes = len(mean), len(variances)
    modes = _array(point_data, UNIT_MODES, "point") if n_modes else np.zeros((n_points, 0))
    metadata = json.loads(field_value(polydata, METADATA) or "{}")
    parameters = point_data.GetArray(SPHERE_COORDINATES)
    return ShapeModel(
        mean=mean,
        modes=np.ascontiguousarray(modes.reshape(n_points, n_modes, 3).transpose(1, 0, 2)),
        variances=variances, weights=_array(point_data, AREA_WEIGHTS, "point"),
        scores=_array(fields, SCORES, "field").reshape(len(names), n_modes), names=names,
        triangles=(surface.polydata_to_arrays(polydata)[1] if polydata.GetNumberOfPolys()
                   else _segments(polydata) if polydata.GetNumberOfLines() else None),
        part_sizes=[int(size) for size in _array(fields, PART_SIZES, "field")],
        part_names=_strings(fields, PART_NAMES) if fields.GetAbstractArray(PART_NAMES) else [],
        metadata={key: np.asarray(value) if isinstance(value, list) else value
                  for key, value in metadata.items()},
        parameters=None if parameters is None else vtk_to_numpy(parameters).astype(np.float64),
        landmarks=dict(zip(_strings(fields, LANDMARK_LABELS),
                           (int(row) for row in _array(fields, LANDMARK_ROWS, "field"))))
        if fields.GetAbstractArray(LANDMARK_LABELS) else {}
    ).check()


def _prepared_case(polydata, name: str, config: BuildConfig) -> PreparedCase:
    """A sphere-mapped surface (an output of SurfaceToSphereMap) as the prepared case of build.

    Its cells and its ``SphereCoordinates`` are checked against its points first: the
    correspondence's compiled loops index both by point and would read past a shorter array.
    """
    try:
        if polydata is not None:
            io.require_valid_cells(polydata)
        sphere = io.point_values(polydata, SPHERE_COORDINATES, 3)
    except InputError as error:
        raise InputError(f"{name}: {error}") from None
    if sphere is None:
        raise InputError(f"{name}: no point data {SPHERE_COORDINATES} (connect the output of "
                         "SurfaceToSphereMap; an empty one means that it failed)")
    sphere = sphere.astype(np.float64)
    if not np.all(np.isfinite(sphere)) or np.max(np.abs(np.linalg.norm(sphere, axis=1) - 1)) > 1e-6:
        raise InputError(f"{name}: point data {SPHERE_COORDINATES} are not unit vectors")
    vertices, faces = surface.polydata_to_arrays(polydata)
    voxel_size = field_value(polydata, VOXEL_SIZE) or config.voxel_size
    if voxel_size is None:
        raise InputError(f"{name}: no field data {VOXEL_SIZE} and no BuildConfig.voxel_size")
    mapped = SphereMap(vertices, faces, sphere)
    part = PreparedPart("", "", mapped, repair=str(field_value(polydata, "Repair") or ""))
    return PreparedCase(name, [part], float(voxel_size), bool(field_value(polydata, MIRRORED)))


class _PipelineProgress:
    """The library's progress callback (:mod:`mdlshapemodel.progress`) on a VTK algorithm: each
    report is a ProgressEvent between ``START`` and ``END`` (a report without a fraction, as the
    optimisation's, counts the share of ``max_time`` spent) with its message as the progress
    text, and the algorithm's abort flag is the answer that cancels."""

    def __init__(self, algorithm, max_time: float):
        self.algorithm, self.max_time = algorithm, max_time
        self.started = time.perf_counter()
        self.done = 0.0

    def __call__(self, fraction, message):
        if fraction is None:
            spent = time.perf_counter() - self.started
            fraction = min(1.0, spent / self.max_time) if self.max_time > 0 else 1.0
        self.done = max(self.done, fraction)
        self.algorithm.SetProgressText(message)
        self.algorithm.UpdateProgress(START + (END - START) * self.done)
        return not self.algorithm.CheckAbort()


def _setting(name: str, cast):
    """VTK-style Set/Get methods of one field of the builder's BuildConfig; Set calls
    Modified() only on a change."""
    def setter(self, value):
        self.SetConfig(dataclasses.replace(self._config, **{name: cast(value)}))

    def getter(self):
        return getattr(self._config, name)

    setter.__doc__ = f"Set ``BuildConfig.{name}``."
    getter.__doc__ = f"``BuildConfig.{name}``."
    return setter, getter


def _names(values) -> tuple:
    return tuple(str(v) for v in (values or ()))


class ShapeModelBuilder(LibraryFilter):
    """Sphere-mapped surfaces -> an optimised statistical shape model and the corresponded surfaces.

    Input: one repeatable port (``AddInputConnection``, ``AddInputData``), at least three outputs
    of :class:`~mdlshapemodel.vtkfilters.SurfaceToSphereMap` (point data ``SphereCoordinates``;
    field data ``VoxelSize``, and ``Mirrored`` and ``Repair`` when present), in the model's order.
    Case names: ``SetCaseNames``, else each input's field data ``CaseName`` (a string), else
    ``case_0``, ``case_1``, ...

    Output 0: the model polydata (see :mod:`mdlshapemodel.vtkmodel`): the mean shape with
    ``mode_1``, ``mode_2``, ... at one standard deviation, ``Variances`` and the rest of the model,
    plus ``InitialObjective`` and ``StoppedBy`` ("converged", "time limit" or "sweep limit").
    Output 1 (``GetCorrespondenceOutputPort``): a vtkMultiBlockDataSet
    with the corresponded surface of each input, in input order, named by case
    (``vtkCompositeDataSet.NAME()``), all with the triangles of output 0, in the inputs'
    physical space (mirrored cases reflected back), as ``build`` writes ``correspondence/*.vtp``.

    Settings: ``SetConfig(BuildConfig)`` / ``GetConfig()`` (every setting; those of
    preprocessing, evaluation and baselines are not used here), and Set/Get for ``Points``,
    ``Strategy``, ``Correspondence``, ``MaxTime``, ``MaxSweeps`` and ``Seed``
    (:data:`BUILDER_SETTINGS`), all starting at the defaults of
    :class:`~mdlshapemodel.config.BuildConfig`. ``Workers`` of the configuration
    is used only by the CPD correspondence (``SetCorrespondence("cpd")``). Its ``landmarks``
    (a folder with a landmark file per case name, as ``build --landmarks`` takes) guide the
    correspondence (unless ``landmark_weight`` is 0); the model then holds ``LandmarkLabels``
    and ``LandmarkRows``. ``check_landmarks`` is a build's (its report): not done here.

    Progress: ProgressEvents while the optimisation runs (its share of ``MaxTime``), the message
    in ``GetProgressText()``. ``AbortExecuteOn()`` (e.g. in a progress observer) stops the
    optimisation at its next report; the outputs are then left empty and ``GetErrorText()``
    says that the build was cancelled (call ``AbortExecuteOff()`` before the next update).

    Examples
    --------
    ::

        builder = ShapeModelBuilder()
        for to_sphere in sphere_maps:           # SurfaceToSphereMap filters, one per case
            builder.AddInputConnection(to_sphere.GetOutputPort())
        builder.SetCaseNames(["a", "b", "c", "d"])
        builder.SetPoints(642)
        builder.Update()
        mean = builder.GetOutput(0)             # point data mode_1, mode_2, ...
        corresponded = builder.GetOutput(1)     # a block per case
    """

    def __init__(self):
        super().__init__(nInputPorts=1, inputType="vtkPolyData", nOutputPorts=2,
                         outputType="vtkPolyData")
        self._config = BuildConfig()
        self._case_names = ()

    def FillInputPortInformation(self, port, info):
        info.Set(vtk.vtkAlgorithm.INPUT_REQUIRED_DATA_TYPE(), "vtkPolyData")
        info.Set(vtk.vtkAlgorithm.INPUT_IS_REPEATABLE(), 1)
        return 1

    def FillOutputPortInformation(self, port, info):
        info.Set(vtk.vtkDataObject.DATA_TYPE_NAME(),
                 "vtkPolyData" if port == 0 else "vtkMultiBlockDataSet")
        return 1

    def AddInputData(self, data):
        """Add a data object as one more input, without a pipeline connection."""
        self.AddInputDataObject(0, data)

    def GetCorrespondenceOutputPort(self):
        """The port of the corresponded surfaces (1)."""
        return self.GetOutputPort(1)

    def SetConfig(self, config: BuildConfig):
        """Use every setting of ``config`` (a copy; checked when the builder executes)."""
        self._set("_config", copy.deepcopy(config))

    def GetConfig(self) -> BuildConfig:
        """A copy of the configuration, validated (a bad value raises
        :class:`~mdlshapemodel.errors.ConfigError` naming the field)."""
        return copy.deepcopy(self._config).validate()

    SetCaseNames, GetCaseNames = accessors("_case_names", _names)

    def _case_names_of(self, inputs: list) -> list:
        if self._case_names:
            if len(self._case_names) != len(inputs):
                raise ConfigError(f"CaseNames: {len(self._case_names)} names for "
                                  f"{len(inputs)} inputs")
            return list(self._case_names)
        return [str(field_value(data, CASE_NAME) or f"case_{i}") for i, data in enumerate(inputs)]

    def _execute(self, in_info, out_info):
        config = self.GetConfig()
        inputs = [vtk.vtkPolyData.GetData(in_info[0], i)
                  for i in range(in_info[0].GetNumberOfInformationObjects())]
        names = self._case_names_of(inputs)
        landmarks = (None if config.landmarks is None
                     else read_landmark_folder(config.landmarks, names))
        prepared = [_prepared_case(data, name, config) for data, name in zip(inputs, names)]
        self.SetProgressText("the initial correspondence")
        self.UpdateProgress(START)
        try:
            corresponded = correspond(prepared, config, _PipelineProgress(self, config.max_time),
                                      landmarks=landmarks)
        except Cancelled:
            corresponded = None
        if corresponded is None or corresponded.interrupted:
            raise BuildError("cancelled (AbortExecute): no model")
        self.SetProgressText("the model and the corresponded surfaces")
        self.UpdateProgress(END)
        model = corresponded.model
        result = model_to_polydata(model)
        add_field(result, INITIAL_OBJECTIVE, corresponded.initial_objective)
        stopped_by = corresponded.optimisation.stopped_by
        if stopped_by is not None:
            add_field(result, STOPPED_BY, stopped_by.value)
        blocks = vtk.vtkMultiBlockDataSet()
        shapes = physical_shapes(corresponded.state.raw_shapes(),
                                 [case.mirrored for case in prepared])
        for i, (name, points) in enumerate(zip(names, shapes)):
            blocks.SetBlock(i, surface.arrays_to_polydata(points, model.triangles))
            blocks.GetMetaData(i).Set(vtk.vtkCompositeDataSet.NAME(), name)
        vtk.vtkPolyData.GetData(out_info.GetInformationObject(0)).ShallowCopy(result)
        vtk.vtkMultiBlockDataSet.GetData(out_info.GetInformationObject(1)).ShallowCopy(blocks)


# The builder's settings with Set/Get methods of their own (e.g. SetPoints, GetPoints): method
# name -> the BuildConfig field and its type; every other field through SetConfig.
BUILDER_SETTINGS = {"Points": ("points", int), "Strategy": ("strategy", str),
                    "Correspondence": ("correspondence", str), "MaxTime": ("max_time", float),
                    "MaxSweeps": ("max_sweeps", int), "Seed": ("seed", int)}
for _method, (_name, _cast) in BUILDER_SETTINGS.items():
    for _prefix, _function in zip(("Set", "Get"), _setting(_name, _cast)):
        _function.__name__ = _prefix + _method
        _function.__qualname__ = f"ShapeModelBuilder.{_prefix}{_method}"
        setattr(ShapeModelBuilder, _prefix + _method, _function)
del _method, _name, _cast, _prefix, _function


def _weights(values) -> tuple:
    return tuple(float(v) for v in (values or ()))


def _file_name(value) -> str | None:
    return None if value is None else str(value)


class ShapeModelInstance(LibraryFilter):
    """A model polydata -> the shape ``mean + sum_k Weights[k] * mode_k`` (same triangles).

    ``Weights`` (Set/Get; default none: the mean) are in standard deviations of the first modes,
    so that the weights (2, -1) give the mean plus two standard deviations of mode 1 and minus
    one of mode 2. More weights than the model has modes is an error. The output has the points
    and triangles of the shape only.

    Examples
    --------
    ::

        instance = ShapeModelInstance()
        instance.SetInputConnection(builder.GetOutputPort(0))   # or a ShapeModelReader
        instance.SetWeights([2.0, -1.0])
        instance.Update()
        shape = instance.GetOutput()
    """

    def __init__(self):
        super().__init__(nInputPorts=1, inputType="vtkPolyData", nOutputPorts=1,
                         outputType="vtkPolyData")
        self._weights = ()

    SetWeights, GetWeights = accessors("_weights", _weights)

    def _execute(self, in_info, out_info):
        model = polydata_to_model(vtk.vtkPolyData.GetData(in_info[0]))
        weights = np.array(self._weights, dtype=np.float64)
        if len(weights) > model.n_modes:
            raise ConfigError(f"Weights: {len(weights)} weights, but the model has "
                              f"{model.n_modes} mode(s)")
        points = model.instance(standard_deviations=weights)
        vtk.vtkPolyData.GetData(out_info).ShallowCopy(
            surface.arrays_to_polydata(points, model.triangles))


class ShapeModelReader(LibraryFilter):
    """A model file -> the model polydata (the output 0 of :class:`ShapeModelBuilder`).

    ``SetFileName``: a build's output folder or its ``model.h5``
    (:meth:`~mdlshapemodel.folders.BuildFolder.model`), a model file written by
    :class:`ShapeModelWriter` or :meth:`ShapeModel.save
    <mdlshapemodel.model.shape_model.ShapeModel.save>`, or any Statismo/Scalismo shape model
    (:meth:`ShapeModel.load <mdlshapemodel.model.shape_model.ShapeModel.load>`). A missing or
    unreadable file is an error that names it.

    Examples
    --------
    ::

        reader = ShapeModelReader()
        reader.SetFileName("out/model.h5")
        reader.Update()
        mean = reader.GetOutput()   # point data mode_1, mode_2, ...; field data Variances
    """

    def __init__(self):
        super().__init__(nInputPorts=0, nOutputPorts=1, outputType="vtkPolyData")
        self._file_name = None

    SetFileName, GetFileName = accessors("_file_name", _file_name)

    def _execute(self, in_info, out_info):
        if not self._file_name:
            raise InputError("no model file (SetFileName)")
        model = BuildFolder(self._file_name).model()
        vtk.vtkPolyData.GetData(out_info).ShallowCopy(model_to_polydata(model))


class ShapeModelWriter(LibraryFilter):
    """A model polydata -> a model file (``model.h5``, the Statismo layout of
    :meth:`ShapeModel.save <mdlshapemodel.model.shape_model.ShapeModel.save>`).

    ``SetFileName``, then ``Write()`` (1 when written, else 0 and the reason in
    ``GetErrorText()``). The model written is the one the input holds, exactly.

    Examples
    --------
    ::

        writer = ShapeModelWriter()
        writer.SetInputConnection(builder.GetOutputPort(0))
        writer.SetFileName("model.h5")
        writer.Write()
    """

    def __init__(self):
        super().__init__(nInputPorts=1, inputType="vtkPolyData", nOutputPorts=0)
        self._file_name = None

    SetFileName, GetFileName = accessors("_file_name", _file_name)

    def Write(self) -> int:
        """Write the input's model to the file: 1 on success, 0 on a failure."""
        # stays when the writer does not execute (no input connected: VTK reports that)
        self._error_text = "nothing written (is the input connected?)"
        self.Modified()
        self.Update()
        return 0 if self._error_text else 1

    def _execute(self, in_info, out_info):
        if not self._file_name:
            raise InputError("no model file (SetFileName)")
        model = polydata_to_model(vtk.vtkPolyData.GetData(in_info[0]))
        try:
            model.save(self._file_name)
        except OSError as error:
            raise InputError(f"{self._file_name}: could not be written ({error})") from None
