"""VTK filters over the library's rooms, for use in any VTK pipeline.

- :class:`LabelMapToClosedSurface`: vtkImageData (a label map) -> vtkPolyData, the closed genus-0
  surface of the selected labels in world coordinates (the image's origin, spacing and direction);
- :class:`SurfaceToSphereMap`: vtkPolyData (a closed genus-0 triangle mesh) -> output 0, the same
  surface with the point-data array ``SphereCoordinates`` (its bijective map onto the unit sphere) and
  the map's quality in field data; output 1, the sphere itself (same triangles).

Both follow VTK's conventions: ``SetInputConnection``/``GetOutputPort``, Set/Get methods that call
``Modified()`` only when a value changes, so the filter re-executes only when an input or a parameter
changed. Failures (an empty label, a surface that is not a sphere) are reported through VTK's error
output and leave the output empty; the message is also kept in ``GetErrorText()``.
"""

from __future__ import annotations

import numpy as np
import vtk
from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.util.vtkAlgorithm import VTKPythonAlgorithmBase

from .errors import MDLShapeModelError
from .prepare import surface
from .prepare.sphere import MAX_ITERATIONS, sphere_map


def _accessors(attribute: str, cast):
    """A VTK-style Set/Get method pair for ``attribute``; Set calls Modified() only on a change."""
    def setter(self, value):
        self._set(attribute, cast(value))

    def getter(self):
        return getattr(self, attribute)

    return setter, getter


def _labels(values) -> tuple:
    return tuple(int(v) for v in values)


class _Filter(VTKPythonAlgorithmBase):
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
        """The last failure's message, or '' after a successful execution."""
        return self._error_text

    def _fail(self, error: Exception) -> int:
        self._error_text = str(error)
        vtk.vtkOutputWindow.GetInstance().DisplayErrorText(
            f"{type(self).__name__}: {self._error_text}\n")
        return 1


class LabelMapToClosedSurface(_Filter):
    """Label map (vtkImageData with integer scalars) -> closed genus-0 surface (vtkPolyData).

    Parameters (Set/Get): ``Labels`` (tuple of label values whose union is the object; empty = all
    non-zero), ``SurfaceMethod`` ("gaussian" or "slicer"), ``SmoothingFactor`` and ``Decimation``
    (slicer), ``SmoothingSigma`` and ``MaxSmoothingSigma`` (voxels), ``EdgeLength`` (voxels, of the
    isotropic remeshing), ``TargetVertices``.
    """

    def __init__(self):
        super().__init__(nInputPorts=1, inputType="vtkImageData", nOutputPorts=1,
                         outputType="vtkPolyData")
        self._labels = ()
        self._smoothing_sigma = 1.0
        self._max_smoothing_sigma = 2.0
        self._edge_length = 1.0
        self._target_vertices = 20000
        self._surface_method = "gaussian"
        self._smoothing_factor = 0.5
        self._decimation = 0.0

    SetSurfaceMethod, GetSurfaceMethod = _accessors("_surface_method", str)
    SetSmoothingFactor, GetSmoothingFactor = _accessors("_smoothing_factor", float)
    SetDecimation, GetDecimation = _accessors("_decimation", float)
    SetLabels, GetLabels = _accessors("_labels", _labels)
    SetSmoothingSigma, GetSmoothingSigma = _accessors("_smoothing_sigma", float)
    SetMaxSmoothingSigma, GetMaxSmoothingSigma = _accessors("_max_smoothing_sigma", float)
    SetEdgeLength, GetEdgeLength = _accessors("_edge_length", float)
    SetTargetVertices, GetTargetVertices = _accessors("_target_vertices", int)

    def RequestData(self, request, in_info, out_info):
        self.executions += 1
        self._error_text = ""
        image = vtk.vtkImageData.GetData(in_info[0])
        output = vtk.vtkPolyData.GetData(out_info)
        try:
            scalars = image.GetPointData().GetScalars() if image is not None else None
            if scalars is None:
                raise MDLShapeModelError("the input image has no scalars")
            nx, ny, nz = image.GetDimensions()
            labels = vtk_to_numpy(scalars).reshape(nz, ny, nx)
            if self._labels:
                mask = np.isin(labels, self._labels)
                if not mask.any():
                    raise MDLShapeModelError(f"label {', '.join(map(str, self._labels))} not "
                                             "present in the image")
            else:
                mask = labels != 0
                if not mask.any():
                    raise MDLShapeModelError("the label map is empty (no non-zero voxels)")
            mask, _ = surface.mask_components(mask)
            direction = vtk.vtkMatrix3x3()
            direction.DeepCopy(image.GetDirectionMatrix())
            matrix = [direction.GetElement(r, c) for r in range(3) for c in range(3)]
            vertices, faces, _ = surface.mask_to_surface(
                mask, image.GetSpacing(), image.GetOrigin(), matrix,
                smoothing_sigma=self._smoothing_sigma,
                max_smoothing_sigma=max(self._max_smoothing_sigma, self._smoothing_sigma),
                edge_length=self._edge_length, target_vertices=self._target_vertices,
                method=self._surface_method, smoothing_factor=self._smoothing_factor,
                decimation=self._decimation)
        except MDLShapeModelError as error:
            return self._fail(error)
        output.ShallowCopy(surface.arrays_to_polydata(vertices, faces))
        return 1


class SurfaceToSphereMap(_Filter):
    """Closed genus-0 surface -> the same surface with its bijective sphere map.

    Output 0: the input surface (cleaned to triangles) with point data ``SphereCoordinates`` (3
    components, unit vectors) and field data ``FlippedTriangles``, ``MeanAbsLogAreaRatio``,
    ``P95AbsLogAreaRatio``. Output 1: the unit sphere with the same triangles.
    Parameters (Set/Get): ``AreaWeight``, ``MaxIterations``.
    """

    def __init__(self):
        super().__init__(nInputPorts=1, inputType="vtkPolyData", nOutputPorts=2,
                         outputType="vtkPolyData")
        self._area_weight = 4.0
        self._max_iterations = MAX_ITERATIONS

    SetAreaWeight, GetAreaWeight = _accessors("_area_weight", float)
    SetMaxIterations, GetMaxIterations = _accessors("_max_iterations", int)

    def GetSphereOutputPort(self):
        """The port of the sphere output (1)."""
        return self.GetOutputPort(1)

    def RequestData(self, request, in_info, out_info):
        self.executions += 1
        self._error_text = ""
        polydata = vtk.vtkPolyData.GetData(in_info[0])
        surface_output = vtk.vtkPolyData.GetData(out_info.GetInformationObject(0))
        sphere_output = vtk.vtkPolyData.GetData(out_info.GetInformationObject(1))
        try:
            triangles = vtk.vtkTriangleFilter()
            triangles.SetInputData(polydata)
            triangles.Update()
            vertices, faces = surface.polydata_to_arrays(triangles.GetOutput())
            surface.require_sphere_like(vertices, faces)
            faces = surface.orient_outwards(vertices, faces)
            mapped = sphere_map(vertices, faces, area_weight=self._area_weight,
                                max_iterations=self._max_iterations)
        except MDLShapeModelError as error:
            return self._fail(error)
        result = surface.arrays_to_polydata(mapped.vertices, mapped.faces)
        coordinates = numpy_to_vtk(np.ascontiguousarray(mapped.sphere), deep=True)
        coordinates.SetName("SphereCoordinates")
        result.GetPointData().AddArray(coordinates)
        for name, key in (("FlippedTriangles", "flipped_triangles"),
                          ("MeanAbsLogAreaRatio", "mean_abs_log_area_ratio"),
                          ("P95AbsLogAreaRatio", "p95_abs_log_area_ratio")):
            array = numpy_to_vtk(np.array([mapped.quality[key]], dtype=np.float64), deep=True)
            array.SetName(name)
            result.GetFieldData().AddArray(array)
        surface_output.ShallowCopy(result)
        sphere_output.ShallowCopy(surface.arrays_to_polydata(mapped.sphere, mapped.faces))
        return 1
