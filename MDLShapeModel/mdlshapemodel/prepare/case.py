"""One input file -> one prepared case: its closed genus-0 surface and bijective sphere map, or
its closed 2-D curve and arc-length map on the circle.

:func:`prepare_case` is the single code path from a file to a prepared case, used by ``build``,
``fit`` and (for the steps after reading) the VTK filters. An input that cannot be used is
*rejected* with a one-line reason; only problems of the input are rejections (our own input errors,
I/O errors, running out of memory). Any other exception is a bug in this package: it propagates,
and :func:`~mdlshapemodel.prepare.batch.preprocess` stops with an
:class:`~mdlshapemodel.errors.InternalError` that names the case.
"""

from __future__ import annotations

import fnmatch
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import BuildConfig
from ..errors import ArgumentError, InputError, MDLShapeModelError
from . import curve, curve_io, io, surface
from .sphere import AREA_WEIGHT, MAX_ITERATIONS, SphereMap, sphere_map


@dataclass
class PreparedPart:
    """One closed surface of a case (a part of a multi-part object, or the whole object) and its
    bijective sphere map, with what was done to make it."""

    name: str                             # the part's name; "" for a one-part object
    path: str                             # the file it was made from
    map: SphereMap                        # or a curve.CurveMap: a 2-D curve on the circle
    repair: str = ""                      # what was repaired in the input ('' when nothing)
    smoothing_sigma: float | None = None  # label maps: the blur that gave a genus-0 surface
    labels: tuple | None = None           # label maps: the non-zero labels of the file

    def record(self) -> dict:
        """The preprocessing facts as a JSON-ready dict (cache entries, cases.csv)."""
        return {"repair": self.repair, "smoothing_sigma": self.smoothing_sigma,
                "labels": None if self.labels is None else list(self.labels)}


def joined_mesh(meshes: list) -> tuple[np.ndarray, np.ndarray]:
    """One mesh of several, (vertices, triangles) each: their vertices in order, each one's
    triangles renumbered after the vertices before it."""
    offsets = np.cumsum([0] + [len(vertices) for vertices, _ in meshes[:-1]])
    return (np.concatenate([vertices for vertices, _ in meshes]),
            np.concatenate([faces + offset for (_, faces), offset in zip(meshes, offsets)]))


@dataclass
class PreparedCase:
    """One case after preprocessing: the surface and sphere map of each of its parts (one for a
    one-part object), and what was done.

    A one-part case (what :func:`prepare_case` makes from one file) offers its part's ``map``,
    ``repair`` and ``smoothing_sigma`` directly; :func:`~.parts.joined` makes a multi-part case
    from one prepared case per part.
    """

    name: str
    parts: list                           # of PreparedPart, in the object's part order
    voxel_size: float                     # mm per voxel (mesh inputs: see BuildConfig.voxel_size)
    mirrored: bool = False                # reflected x -> -x (BuildConfig.mirror)

    @property
    def path(self) -> str:
        """The input file (of several parts: the first part's)."""
        return self.parts[0].path

    @property
    def paths(self) -> list:
        """The distinct input files, in part order."""
        return list(dict.fromkeys(part.path for part in self.parts))

    @property
    def part_names(self) -> list:
        return [part.name for part in self.parts]

    @property
    def map(self) -> SphereMap:
        """The sphere map of a one-part case."""
        if len(self.parts) != 1:
            raise ArgumentError(f"{self.name} has {len(self.parts)} parts: use parts[j].map")
        return self.parts[0].map

    @property
    def repair(self) -> str:
        """What was repaired, part by part ("head: ..." for named parts)."""
        return "; ".join(f"{p.name}: {p.repair}" if p.name else p.repair
                         for p in self.parts if p.repair)

    @property
    def smoothing_sigma(self) -> float | None:
        """The largest blur that a part needed (None: no part came from a label map)."""
        sigmas = [p.smoothing_sigma for p in self.parts if p.smoothing_sigma is not None]
        return max(sigmas) if sigmas else None

    @property
    def is_curve(self) -> bool:
        """Whether the case is of 2-D curves (its parts mapped to the circle)."""
        return isinstance(self.parts[0].map, curve.CurveMap)

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        """The vertices and triangles of every part's surface, as one mesh (new arrays)."""
        return joined_mesh(self.meshes())

    def meshes(self) -> list:
        """Each part's surface, (vertices, triangles): the sphere maps' own arrays, not copies
        (read-only by convention); :func:`joined_mesh` of them is :meth:`surface`."""
        return [(p.map.vertices, p.map.faces) for p in self.parts]

    @property
    def labels(self) -> tuple | None:
        """The non-zero label values of the case's label maps (None: not from label maps)."""
        known = [p.labels for p in self.parts if p.labels is not None]
        return tuple(sorted(set().union(*known))) if known else None

    def record(self) -> dict:
        """The preprocessing facts as a JSON-ready dict (cache entries, cases.csv)."""
        return {"mirrored": self.mirrored, "repair": self.repair,
                "smoothing_sigma": self.smoothing_sigma,
                "labels": None if self.labels is None else list(self.labels)}


@dataclass
class Rejection:
    """An input that cannot be used, and why (one line)."""

    name: str
    path: str
    reason: str


def is_mirrored(path, config: BuildConfig) -> bool:
    """Whether the file name matches one of the ``mirror`` patterns (shell-style, e.g. ``*_r*``)."""
    name = Path(path).name
    return any(fnmatch.fnmatch(name, pattern) for pattern in config.mirror)


_BLAS_CONTROLLER = []      # the process's threadpoolctl controller, made on first use


@contextmanager
def one_blas_thread():
    """One BLAS thread while preparing a case: the same arithmetic, bit for bit, in a worker
    process, in the main process and in a VTK pipeline.

    The BLAS libraries are looked up once per process (a look-up lists every loaded shared
    library, several milliseconds), after loading SciPy's, so that the controller knows both
    NumPy's and SciPy's.
    """
    if not _BLAS_CONTROLLER:
        import scipy.linalg  # noqa: F401  (loads SciPy's BLAS)
        from threadpoolctl import ThreadpoolController

        _BLAS_CONTROLLER.append(ThreadpoolController())
    with _BLAS_CONTROLLER[0].limit(limits=1, user_api="blas"):
        yield


def surface_of_mask(mask: np.ndarray, spacing, origin, direction, config: BuildConfig
                    ) -> tuple[np.ndarray, np.ndarray, float, str]:
    """The closed genus-0 surface of a binary mask with the build's settings: cavities filled and
    debris dropped (:func:`surface.mask_components`), then :func:`surface.mask_to_surface`.
    Returns vertices, faces (physical coordinates), the blur that was needed and a repair note."""
    with one_blas_thread():
        mask, note = surface.mask_components(mask)
        vertices, faces, info = surface.mask_to_surface(
            mask, spacing, origin, direction, smoothing_sigma=config.smoothing_sigma,
            max_smoothing_sigma=config.max_smoothing_sigma, edge_length=config.edge_length,
            target_vertices=config.target_vertices, method=config.surface_method,
            smoothing_factor=config.smoothing_factor, decimation=config.decimation)
    return vertices, faces, info["smoothing_sigma"], note


def prepare_surface(vertices: np.ndarray, faces: np.ndarray, name: str, path: str,
                    voxel_size: float | None, config: BuildConfig, mirrored: bool = False,
                    repair: str = "", smoothing_sigma: float | None = None,
                    area_weight: float = AREA_WEIGHT, max_iterations: int = MAX_ITERATIONS,
                    labels: tuple | None = None) -> PreparedCase:
    """A prepared case from a closed genus-0 surface: mirrored if asked, then sphere-mapped.

    ``voxel_size`` None: the surface is a mesh input, cleaned and remeshed first
    (:func:`surface.clean_mesh`, above ``config.target_vertices`` decimated) and given
    ``config.voxel_size`` or its mean edge length. Otherwise it is a surface of a label map
    (:func:`surface_of_mask`), only checked and oriented outwards. ``area_weight`` and
    ``max_iterations`` are passed to :func:`~.sphere.sphere_map`.
    """
    with one_blas_thread():
        if voxel_size is None:
            vertices, faces, mean_edge, note = surface.clean_mesh(vertices, faces,
                                                                  config.target_vertices)
            repair = "; ".join(filter(None, [repair, note]))
            voxel_size = config.voxel_size or mean_edge
        else:
            surface.require_sphere_like(vertices, faces)
            faces = surface.orient_outwards(vertices, faces)
    return _mapped_case(vertices, faces, name, path, voxel_size, mirrored, repair,
                        smoothing_sigma, labels, area_weight, max_iterations)


def _mapped_case(vertices: np.ndarray, faces: np.ndarray, name: str, path: str,
                 voxel_size: float, mirrored: bool, repair: str, smoothing_sigma: float | None,
                 labels: tuple | None, area_weight: float = AREA_WEIGHT,
                 max_iterations: int = MAX_ITERATIONS) -> PreparedCase:
    """The prepared case of a checked closed genus-0 surface with outward normals: mirrored if
    asked, then sphere-mapped."""
    with one_blas_thread():
        if mirrored:
            vertices, faces = surface.mirror(vertices, faces)
        mapped = sphere_map(vertices, faces, area_weight=area_weight,
                            max_iterations=max_iterations)
    return PreparedCase(name, [PreparedPart("", str(path), mapped, repair, smoothing_sigma,
                                            labels)], float(voxel_size), mirrored)


def prepare_curve(path, config: BuildConfig) -> PreparedCase:
    """A prepared case from a 2-D curve file: the clean closed curve (:func:`.curve_io.read_curve`),
    reflected x -> -x if ``config.mirror`` says so, and its arc-length parameterization on the
    circle. Its voxel size (the unit of the coding accuracy) is ``config.voxel_size``, else a
    label image's pixel size, else the curve's mean segment length."""
    notes = []
    points = curve_io.read_curve(path, config.labels, notes)
    mirrored = is_mirrored(path, config)
    if mirrored:
        points = curve.check_curve(points * [-1.0, 1.0])      # counter-clockwise again
    voxel = config.voxel_size or curve_io.pixel_size(path) or float(
        np.mean(curve.segment_lengths(points)))
    part = PreparedPart("", str(path), curve.curve_map(points), "; ".join(notes))
    return PreparedCase(io.case_name(path), [part], float(voxel), mirrored)


def _prepare(path, config: BuildConfig) -> PreparedCase:
    if curve_io.is_curve_file(path):
        return prepare_curve(path, config)
    name = io.case_name(path)
    mirrored = is_mirrored(path, config)
    if io.is_image(path):
        label_map = io.read_label_map(path, config.labels)
        vertices, faces, sigma, note = surface_of_mask(
            label_map.mask, label_map.spacing, label_map.origin, label_map.direction, config)
        # surface_of_mask's surface is checked and oriented outwards already
        return _mapped_case(vertices, faces, name, path, label_map.voxel_size, mirrored, note,
                            sigma, label_map.labels)
    if io.is_mesh(path):
        vertices, faces = io.read_mesh(path)
        return prepare_surface(vertices, faces, name, path, None, config, mirrored)
    raise InputError("not a label map or mesh (unknown file type)")


def prepare_case(path, config: BuildConfig) -> PreparedCase | Rejection:
    """Read one input and make its closed genus-0 surface and bijective sphere map.

    Parameters
    ----------
    path : str or Path
        A label map (the union of ``config.labels``), a closed triangle mesh, or a 2-D curve
        file (:func:`.curve_io.is_curve_file`: point lists, polylines, one-slice label images).
    config : BuildConfig
        The preprocessing settings (surface, remeshing, mirroring).

    Returns
    -------
    PreparedCase or Rejection
        A rejection when the input cannot be used (its reason in one line). A bug in this package
        raises instead.

    Examples
    --------
    >>> from mdlshapemodel import BuildConfig
    >>> from mdlshapemodel.prepare import prepare_case
    >>> prepare_case("missing.nii.gz", BuildConfig()).reason
    'no such file'
    """
    try:
        return _prepare(path, config)
    except MDLShapeModelError as error:
        reason = str(error)
    except OSError as error:
        reason = f"could not be read ({error})"
    except MemoryError:
        reason = "not enough memory to prepare it"
    # one line: a reason may quote a damaged file's bytes
    return Rejection(io.case_name(path), str(path), io.printable(reason))
