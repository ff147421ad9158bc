"""VTK filters over the library's rooms, for use in any VTK pipeline.

- :class:`LabelMapToClosedSurface`: vtkImageData (a label map) -> vtkPolyData, the closed genus-0
  surface of the selected labels in world coordinates (the image's origin, spacing and direction);
- :class:`SurfaceToSphereMap`: vtkPolyData (a closed genus-0 triangle mesh) -> output 0, the
  prepared surface with the point-data array ``SphereCoordinates`` (its bijective map onto the
  unit sphere) and the map's quality in field data; output 1, the sphere itself (same triangles).

They take the steps of ``build`` and ``fit`` (:mod:`mdlshapemodel.prepare.case`), not copies of
them: the label selection of :func:`~mdlshapemodel.prepare.io.select_labels`, the surface of
:func:`~mdlshapemodel.prepare.case.surface_of_mask`, and the cleaning, mirroring and sphere map
of :func:`~mdlshapemodel.prepare.case.prepare_surface`; their parameters start at the defaults
of :class:`~mdlshapemodel.config.BuildConfig`. A mesh file read by a VTK reader and passed
through :class:`SurfaceToSphereMap` is therefore prepared bit for bit as ``build`` prepares it,
and so is a label map passed through both filters when the reader gives the image the geometry
SimpleITK reads (``vtkNIFTIImageReader`` keeps a NIfTI file's orientation in its q-form matrix,
not in the image).

Both follow VTK's conventions: ``SetInputConnection``/``GetOutputPort``, Set/Get methods that
call ``Modified()`` only when a value changes, so the filter re-executes only when an input or a
parameter changed, and progress reported through ``UpdateProgress`` (``ProgressEvent``).
Failures (a missing label, a surface that is not a sphere, a bad parameter) are reported through
VTK's error output and leave the output empty; the message, the same line that ``build`` gives,
is kept in ``GetErrorText()``.
"""

from __future__ import annotations

import numpy as np
import vtk
from vtk.util.numpy_support import numpy_to_vtk
from vtkmodules.util.vtkAlgorithm import VTKPythonAlgorithmBase

from .config import BuildConfig
from .errors import InputError, MDLShapeModelError
from .prepare import io, surface
from .prepare.case import prepare_surface, surface_of_mask
from .prepare.sphere import AREA_WEIGHT, MAX_ITERATIONS

# Field data that marks a surface made from a label map (LabelMapToClosedSurface), so that
# SurfaceToSphereMap prepares it as build prepares label maps (not cleaned and remeshed again).
VOXEL_SIZE = "VoxelSize"
# The point data of a prepared surface that holds its sphere map (SurfaceToSphereMap's output).
SPHERE_COORDINATES = "SphereCoordinates"
# Field data of a prepared surface: 1 when it was mirrored (x -> -x), so that the corresponded
# surfaces of ShapeModelBuilder can be reflected back over their inputs, as build's are.
MIRRORED = "Mirrored"


def accessors(attribute: str, cast):
    """A VTK-style Set/Get method pair for ``attribute``; Set calls Modified() only on a change."""
    def setter(self, value):
        self._set(attribute, cast(value))

    def getter(self):
        return getattr(self, attribute)

    return setter, getter


def _switches(attribute: str):
    """VTK-style On/Off methods of a boolean parameter."""
    def on(self):
        self._set(attribute, True)

    def off(self):
        self._set(attribute, False)

    return on, off


def _labels(values) -> tuple:
    return tuple(int(v) for v in values)


def _optional_float(value) -> float | None:
    return None if value is None else float(value)


def add_field(polydata, name: str, value):
    """Add a one-value field-data array (a number, or a string as a vtkStringArray)."""
    if isinstance(value, str):
        array = vtk.vtkStringArray()
        array.InsertNextValue(value)
    else:
        array = numpy_to_vtk(np.array([value], dtype=np.float64), deep=True)
    array.SetName(name)
    polydata.GetFieldData().AddArray(array)


def field_value(polydata, name: str):
    """The first value of a field-data array, or None when there is none."""
    array = polydata.GetFieldData().GetAbstractArray(name) if polydata is not None else None
    if array is None or array.GetNumberOfValues() == 0:
        return None
    if isinstance(array, vtk.vtkStringArray):
        return array.GetValue(0)
    return float(array.GetTuple1(0))


class LibraryFilter(VTKPythonAlgorithmBase):
    """Shared parameter handling: every parameter is set through :meth:`_set`."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self._error_text = ""
        self.executions = 0  # how many times RequestData ran (pipelines should not re-run us)

    def _set(self, name: str, value):
        if getattr(self, name) != value:
            setattr(self, name, value)
            self.Modified()

    def SetInputData(self, data):
        """Use a data object as input, without a pipeline connection."""
        self.SetInputDataObject(0, data)

    def GetOutput(self, port: int = 0):
        """The output data object of ``port`` (as vtkPolyDataAlgorithm.GetOutput)."""
        return self.GetOutputDataObject(port)

    def GetErrorText(self) -> str:
        """The last failure's message, or '' after a successful execution. A reader that
        failed before this filter could run (VTK then does not run it) is named here too."""
        return self._error_text or self._input_failure()

    def _input_failure(self) -> str:
        """Why the input's source, a reader, failed ('' when it did not or is no reader): it
        reports an error code, or it cannot read its file (VTK's MetaImage reader, given a
        missing or damaged file, reports nothing and gives a one-voxel image)."""
        if self.GetNumberOfInputPorts() == 0 or self.GetNumberOfInputConnections(0) == 0:
            return ""      # a source, or a filter not connected yet
        source = self.GetInputAlgorithm(0, 0)
        file = source.GetFileName() if hasattr(source, "GetFileName") else None
        code = source.GetErrorCode()
        if code:
            reason = vtk.vtkErrorCode.GetStringFromErrorCode(code)
        elif file and hasattr(source, "CanReadFile") and not source.CanReadFile(file):
            reason = "missing, or not a file of its format"
        else:
            return ""
        return (f"{io.printable(file) + ': ' if file else ''}the input could not be read "
                f"({source.GetClassName()}: {reason})")

    def RequestData(self, request, in_info, out_info):
        """Count the execution, run :meth:`_execute`; a failure (the input's reader's too)
        goes through :meth:`_fail`."""
        self.executions += 1
        self._error_text = ""
        self.UpdateProgress(0.0)
        try:
            failure = self._input_failure()
            if failure:
                raise InputError(failure)
            self._execute(in_info, out_info)
        except MDLShapeModelError as error:
            return self._fail(error)
        self.UpdateProgress(1.0)
        return 1

    def _execute(self, in_info, out_info):
        """Fill the outputs from the inputs; raise :class:`MDLShapeModelError` on a failure
        (before touching the outputs, which then stay empty)."""
        raise NotImplementedError

    def _fail(self, error: Exception) -> int:
        self._error_text = str(error)
        vtk.vtkOutputWindow.GetInstance().DisplayErrorText(
            f"{type(self).__name__}: {self._error_text}\n")
        self.UpdateProgress(1.0)
        return 1


class LabelMapToClosedSurface(LibraryFilter):
    """Label map (vtkImageData with integer scalars) -> closed genus-0 surface (vtkPolyData).

    The steps of ``build`` for a label map: the union of the labels
    (:func:`~mdlshapemodel.prepare.io.select_labels`, with build's messages), cavities filled and
    debris dropped, contoured, remeshed and placed in world coordinates
    (:func:`~mdlshapemodel.prepare.case.surface_of_mask`).

    Parameters (Set/Get), with the defaults of :class:`~mdlshapemodel.config.BuildConfig`:
    ``Labels`` (tuple of label values whose union is the object; empty = all non-zero),
    ``SurfaceMethod`` ("gaussian" or "slicer"), ``SmoothingFactor`` and ``Decimation`` (slicer),
    ``SmoothingSigma`` and ``MaxSmoothingSigma`` (voxels; the latter is raised to the former when
    smaller), ``EdgeLength`` (voxels, of the isotropic remeshing), ``TargetVertices``.

    The output's field data: ``VoxelSize`` (mm, the geometric mean of the spacing; it also tells
    :class:`SurfaceToSphereMap` that the surface comes from a label map), ``SmoothingSigma`` (the
    blur that gave a genus-0 surface) and ``Repair`` (what was repaired in the mask, or '').
    """

    def __init__(self):
        super().__init__(nInputPorts=1, inputType="vtkImageData", nOutputPorts=1,
                         outputType="vtkPolyData")
        defaults = BuildConfig()
        self._labels = _labels(defaults.labels)
        self._surface_method = defaults.surface_method
        self._smoothing_factor = defaults.smoothing_factor
        self._decimation = defaults.decimation
        self._smoothing_sigma = defaults.smoothing_sigma
        self._max_smoothing_sigma = defaults.max_smoothing_sigma
        self._edge_length = defaults.edge_length
        self._target_vertices = defaults.target_vertices

    SetSurfaceMethod, GetSurfaceMethod = accessors("_surface_method", str)
    SetSmoothingFactor, GetSmoothingFactor = accessors("_smoothing_factor", float)
    SetDecimation, GetDecimation = accessors("_decimation", float)
    SetLabels, GetLabels = accessors("_labels", _labels)
    SetSmoothingSigma, GetSmoothingSigma = accessors("_smoothing_sigma", float)
    SetMaxSmoothingSigma, GetMaxSmoothingSigma = accessors("_max_smoothing_sigma", float)
    SetEdgeLength, GetEdgeLength = accessors("_edge_length", float)
    SetTargetVertices, GetTargetVertices = accessors("_target_vertices", int)

    def RequestUpdateExtent(self, request, in_info, out_info):
        """Ask the source for the whole image, as VTK's image-to-surface filters do.

        Without this the pipeline's default hands each source an update extent taken from
        elsewhere in the pipeline (with one branch per case: another case's image), and a reader
        asked for an extent outside its own fills the image with garbage or writes past it.
        """
        info = in_info[0].GetInformationObject(0)
        executive = vtk.vtkStreamingDemandDrivenPipeline
        if info.Has(executive.WHOLE_EXTENT()):
            info.Set(executive.UPDATE_EXTENT(), info.Get(executive.WHOLE_EXTENT()), 6)
        return 1

    def GetConfig(self) -> BuildConfig:
        """The build configuration that these parameters amount to (validated: a bad value
        raises :class:`~mdlshapemodel.errors.ConfigError` naming the field)."""
        return BuildConfig(labels=list(self._labels), surface_method=self._surface_method,
                           smoothing_factor=self._smoothing_factor, decimation=self._decimation,
                           smoothing_sigma=self._smoothing_sigma,
                           max_smoothing_sigma=max(self._max_smoothing_sigma,
                                                   self._smoothing_sigma),
                           edge_length=self._edge_length,
                           target_vertices=self._target_vertices).validate()

    def _execute(self, in_info, out_info):
        config = self.GetConfig()
        label_map = io.label_map_of_image_data(vtk.vtkImageData.GetData(in_info[0]),
                                               config.labels)
        self.UpdateProgress(0.1)
        vertices, faces, sigma, note = surface_of_mask(
            label_map.mask, label_map.spacing, label_map.origin, label_map.direction, config)
        result = surface.arrays_to_polydata(vertices, faces)
        add_field(result, VOXEL_SIZE, label_map.voxel_size)
        add_field(result, "SmoothingSigma", sigma)
        add_field(result, "Repair", note)
        vtk.vtkPolyData.GetData(out_info).ShallowCopy(result)


class SurfaceToSphereMap(LibraryFilter):
    """Closed genus-0 surface -> the prepared surface with its bijective sphere map.

    The steps of ``build`` after reading (:func:`~mdlshapemodel.prepare.case.prepare_surface`):
    a mesh is cleaned as build cleans mesh files (duplicate points merged, degenerate faces
    dropped, orientation made consistent, decimated above ``TargetVertices``, remeshed at its
    mean edge length); a surface from :class:`LabelMapToClosedSurface` (field data
    ``VoxelSize``) is only checked, as build treats label maps. Then it is mirrored (x -> -x) when
    ``Mirrored`` is on, and mapped onto the sphere.

    Output 0: the prepared surface with point data ``SphereCoordinates`` (3 components, unit
    vectors) and field data ``FlippedTriangles``, ``MeanAbsLogAreaRatio``,
    ``P95AbsLogAreaRatio``, ``VoxelSize`` (mm per voxel: the input's ``VoxelSize`` when it is a
    label-map surface, else the ``VoxelSize`` parameter, else the mesh's mean edge length before
    remeshing), ``Repair`` (what was repaired, or '') and ``Mirrored`` (1 when it was mirrored,
    else 0). Output 1: the unit sphere with the same triangles.

    Parameters (Set/Get), with the defaults of :class:`~mdlshapemodel.config.BuildConfig`:
    ``TargetVertices``, ``VoxelSize`` (mm per voxel of mesh inputs; None: their mean edge
    length), ``Mirrored`` (also ``MirroredOn``/``MirroredOff``; build mirrors the files whose
    names match ``BuildConfig.mirror``, a pipeline says it here); and those of
    :func:`~mdlshapemodel.prepare.sphere.sphere_map`: ``AreaWeight``, ``MaxIterations``.
    """

    def __init__(self):
        super().__init__(nInputPorts=1, inputType="vtkPolyData", nOutputPorts=2,
                         outputType="vtkPolyData")
        defaults = BuildConfig()
        self._target_vertices = defaults.target_vertices
        self._voxel_size = defaults.voxel_size
        self._mirrored = False  # build's default: BuildConfig.mirror matches no file name
        self._area_weight = AREA_WEIGHT
        self._max_iterations = MAX_ITERATIONS

    SetTargetVertices, GetTargetVertices = accessors("_target_vertices", int)
    SetVoxelSize, GetVoxelSize = accessors("_voxel_size", _optional_float)
    SetMirrored, GetMirrored = accessors("_mirrored", bool)
    MirroredOn, MirroredOff = _switches("_mirrored")
    SetAreaWeight, GetAreaWeight = accessors("_area_weight", float)
    SetMaxIterations, GetMaxIterations = accessors("_max_iterations", int)

    def GetConfig(self) -> BuildConfig:
        """The build configuration that these parameters amount to (validated)."""
        return BuildConfig(target_vertices=self._target_vertices,
                           voxel_size=self._voxel_size).validate()

    def GetSphereOutputPort(self):
        """The port of the sphere output (1)."""
        return self.GetOutputPort(1)

    def _execute(self, in_info, out_info):
        config = self.GetConfig()
        polydata = vtk.vtkPolyData.GetData(in_info[0])
        vertices, faces = io.mesh_arrays(polydata)
        voxel_size = field_value(polydata, VOXEL_SIZE)  # None: a mesh, cleaned as build does
        facts = {}
        if voxel_size is not None:
            facts = {"repair": str(field_value(polydata, "Repair") or ""),
                     "smoothing_sigma": field_value(polydata, "SmoothingSigma")}
        case = prepare_surface(vertices, faces, "", "", voxel_size, config,
                               mirrored=self._mirrored, area_weight=self._area_weight,
                               max_iterations=self._max_iterations, **facts)
        mapped = case.map
        result = surface.arrays_to_polydata(mapped.vertices, mapped.faces)
        coordinates = numpy_to_vtk(np.ascontiguousarray(mapped.sphere), deep=True)
        coordinates.SetName(SPHERE_COORDINATES)
        result.GetPointData().AddArray(coordinates)
        for name, key in (("FlippedTriangles", "flipped_triangles"),
                          ("MeanAbsLogAreaRatio", "mean_abs_log_area_ratio"),
                          ("P95AbsLogAreaRatio", "p95_abs_log_area_ratio")):
            add_field(result, name, mapped.quality[key])
        add_field(result, VOXEL_SIZE, case.voxel_size)
        add_field(result, "Repair", case.repair)
        add_field(result, MIRRORED, int(case.mirrored))
        vtk.vtkPolyData.GetData(out_info.GetInformationObject(0)).ShallowCopy(result)
        vtk.vtkPolyData.GetData(out_info.GetInformationObject(1)).ShallowCopy(
            surface.arrays_to_polydata(mapped.sphere, mapped.faces))
