"""The statistical shape model: area-weighted PCA of corresponded, aligned shapes.

Shapes are (n_p, 3) arrays whose point k corresponds across examples. With the area weights w
(sum 1) the inner product of two shape differences is sum_k w_k a_k . b_k (eq. 15), so the mode
variances are mean squared displacements (mm^2). Modes are orthonormal in that inner product and a
shape is ``mean + sum_m b_m mode_m``; training scores have variance lambda_m (divisor n_s, as the
eigenvalues of D' / n_s in the paper).

The model file (``model.h5``)
-----------------------------
:meth:`ShapeModel.save` writes an HDF5 file in the Statismo file format (version 0.9), which
Statismo (C++) and Scalismo (Scala) open as a shape model, plus one group of our own that they
ignore. The layout is the Statismo file format (Luethi et al., "Statismo file format" document)
as the reference implementation writes and reads it (statismo/statismo: ``StatismoIO.h`` and
``StatisticalModel.hxx`` Save/Load, ``HDF5Utils.hxx``, ``ModelInfo.cxx``, ``itk``/
``vtkStandardMeshRepresenter``; ``CommonTypes.h``: float32, row-major matrices) and as Scalismo
reads it (unibas-gravis/scalismo ``io/statisticalmodel/StatismoIO.scala``, ``HDF5Reader.scala``:
float32 arrays, int32 cells, ``/version/*`` int datasets). n = n_p points, m modes, s = n_s cases;
vectors are point-interleaved (x1, y1, z1, x2, ...: ``MapPointIdToInternalIdx = 3 * id + d``)::

    /version/majorVersion        int32 scalar dataset   0
    /version/minorVersion        int32 scalar dataset   9
    /representer                 group, fixed-length string attributes:
        @name = "itkStandardMeshRepresenter", @version = "0.1",
        @datasetType = "POLYGON_MESH" ("POINT_SET" when the model has no triangles,
        "LINE_MESH" for 2-D curves, whose connectivity is segments)
    /representer/points          float32 (3, n)   the mean shape, column i = point i
    /representer/cells           int32   (3, t)   column j = triangle j (only with triangles;
                                 (2, t) segments for curves)
    /model/mean                  float32 (3n,)
    /model/pcaBasis              float32 (3n, m)  orthonormal columns U (Euclidean)
    /model/pcaVariance           float32 (m,)     descending
    /model/noiseVariance         float32 scalar   0
    /modelinfo/build-time        string dataset
    /modelinfo/scores            float32 (m, s)   column i = Statismo coefficients of case i,
                                 alpha = diag(pcaVariance)^(-1/2) U^T (x_i - mean); (1, 1) zero
                                 when there are no cases (Statismo's "no scores" marker)
    /modelinfo/modelBuilder-0/builderName, buildTime      string datasets
    /modelinfo/modelBuilder-0/dataInfo/URI_<i>            string dataset: name of case i
    /modelinfo/modelBuilder-0/parameters/<key>            string dataset: str(metadata[key])
    /mdlshapemodel               our model, float64 and exact (ignored by Statismo/Scalismo):
        @format = "mdlshapemodel", @format_version = 2
        mean (n, 3), modes (m, n, 3), variances (m,), weights (n,), scores (s, m) float64;
        names (s,) UTF-8 strings; part_sizes (parts,) int64; part_names (parts,) UTF-8 strings
        for a multi-part object; triangles (t, 3) and parameters (n, 3) when set;
        landmark_labels (l,) UTF-8 strings and landmark_rows (l,) int64 for a guided build;
        metadata/<key> one scalar (or array) dataset per entry

The Statismo groups hold the same Gaussian as the model: with V the (3n, m) flattened modes
(orthonormal in the weighted inner product) the shape covariance is V diag(lambda) V^T; a thin QR
V = Q R and the eigendecomposition R diag(lambda) R^T = E diag(lambda') E^T give the Euclidean
basis U = Q E with variances lambda' (the same covariance, exactly, before float32 storage).

:meth:`ShapeModel.load` reads the ``/mdlshapemodel`` group when present (bit-exact round trip), the
first version of our own layout, or else any Statismo/Scalismo shape model (versions 0.8, 0.9, 1.x):
uniform weights 1/n, modes sqrt(n) u_m, variances lambda_m / n (the same Gaussian).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ArgumentError, InputError, InternalError
from .space import ROUNDING_VARIANCE, PrincipalAxes, principal_axes

NATIVE_GROUP = "mdlshapemodel"
FORMAT_VERSION = 2
STATISMO_VERSION = (0, 9)
# the representer that Statismo's ITK mesh representer and Scalismo write
REPRESENTER_NAME = "itkStandardMeshRepresenter"
REPRESENTER_VERSION = "0.1"
# A model keeps the modes whose variance is above this share of the total variance. A mode below
# it moves the points by less than a thousandth of the population's RMS deviation from the mean
# (for a hippocampus, about a micrometre): it holds rounding or a case given twice (a pair of
# near-identical cases makes one), not anatomy, and a Mahalanobis distance over it, which
# divides by its variance, would be decided by it alone. The smallest modes of distinct cases
# are orders of magnitude above it (docs/method.md).
NEGLIGIBLE_VARIANCE = 1e-6


def kept_variances(singular: np.ndarray, n_shapes: int,
                   negligible: float = NEGLIGIBLE_VARIANCE) -> np.ndarray:
    """The variances lambda_m = s_m^2 / n_s of a model of n_s shapes whose centred, area-weighted
    coordinates have the singular values s (descending), those above ``negligible`` of the
    total: the model's modes (:meth:`ShapeModel.from_shapes`), and all its evaluation's
    compactness needs (:func:`~.evaluation.evaluate`).

    Examples
    --------
    >>> kept_variances(np.array([2.0, 1.0, 1e-4]), 4).tolist()
    [1.0, 0.25]
    """
    variances = np.asarray(singular, dtype=np.float64) ** 2 / n_shapes
    return variances[variances > negligible * variances.sum()]


@dataclass
class PartMesh:
    """Where one part of a model's points are, and its triangles numbered within the part."""

    name: str            # "" for a one-part object
    rows: slice          # its rows of the model's points
    triangles: np.ndarray


@dataclass
class ShapeModel:
    """Mean, modes, variances and training scores of a point distribution model."""

    mean: np.ndarray                 # (n_p, 3)
    modes: np.ndarray                # (n_modes, n_p, 3), orthonormal in the weighted inner product
    variances: np.ndarray            # (n_modes,) lambda_m, descending
    weights: np.ndarray              # (n_p,) area weights, sum 1
    scores: np.ndarray               # (n_s, n_modes)
    names: list = field(default_factory=list)
    triangles: np.ndarray | None = None      # (m, 3) connectivity of the points (all parts);
    #                                          (m, 2) segments for a model of 2-D curves
    part_sizes: list = field(default_factory=list)
    metadata: dict = field(default_factory=dict)
    parameters: np.ndarray | None = None     # (n_p, 3) sampling positions on the unit sphere;
    #                                          (n_p,) angles on the circle for 2-D curves
    part_names: list = field(default_factory=list)  # one per part_sizes entry; [] for one part
    landmarks: dict = field(default_factory=dict)   # label -> the row of the points that is
    #                                                 the landmark (a build with --landmarks)

    def landmark_points(self, points: np.ndarray | None = None) -> dict:
        """The landmarks of a shape of the model (its points (n_p, 3); default the mean): label
        -> (3,) point.

        Examples
        --------
        >>> import numpy as np
        >>> model = ShapeModel.from_shapes(np.arange(18.0).reshape(2, 3, 3), np.full(3, 1 / 3))
        >>> model.landmarks = {"tip": 2}
        >>> model.landmark_points()["tip"].tolist()
        [10.5, 11.5, 12.5]
        """
        points = self.mean if points is None else np.asarray(points)
        return {label: points[row] for label, row in self.landmarks.items()}

    def part_slices(self) -> list:
        """The rows of the points of each part (``part_sizes`` in order)."""
        ends = np.cumsum(self.part_sizes or [len(self.mean)])
        return [slice(int(end - size), int(end))
                for end, size in zip(ends, self.part_sizes or [len(self.mean)])]

    @property
    def of_curves(self) -> bool:
        """Whether the model is of 2-D curves: its connectivity is segments (m, 2)."""
        return self.triangles is not None and np.shape(self.triangles)[1:] == (2,)

    def part_meshes(self) -> list:
        """Each part's rows of the points and its own triangles (:class:`PartMesh`; one part:
        all of them). A part's name is also the sub-folder of its files in a build's output."""
        slices = self.part_slices()
        if len(slices) == 1:
            return [PartMesh("", slices[0], self.triangles)]
        owner = self.part_of_triangles()
        names = self.part_names or [f"part_{j}" for j in range(len(slices))]
        return [PartMesh(name, rows, self.triangles[owner == j] - rows.start)
                for j, (name, rows) in enumerate(zip(names, slices))]

    def part_of_triangles(self) -> np.ndarray:
        """The part index of each triangle (a triangle lies within one part)."""
        if self.triangles is None:
            return np.zeros(0, dtype=np.int64)
        starts = np.cumsum([0] + list(self.part_sizes or [len(self.mean)]))[1:-1]
        return np.searchsorted(starts, np.asarray(self.triangles)[:, 0], side="right")

    @classmethod
    def from_shapes(cls, shapes: np.ndarray, weights: np.ndarray, names=None, triangles=None,
                    part_sizes=None, negligible: float = NEGLIGIBLE_VARIANCE, parameters=None,
                    part_names=None, **metadata):
        """Area-weighted PCA of aligned shapes (n_s, n_p, 3) (eq. 1-3 with the inner product of
        eq. 15), keeping the modes whose variance is above ``negligible`` of the total
        (:func:`kept_variances`): at most n_s - 1, fewer when shapes nearly coincide. The model
        :meth:`from_axes` of their :func:`~.space.principal_axes`."""
        return cls.from_axes(principal_axes(shapes, weights), weights, names, triangles,
                             part_sizes, negligible, parameters, part_names, **metadata)

    @classmethod
    def from_axes(cls, axes: PrincipalAxes, weights: np.ndarray, names=None, triangles=None,
                  part_sizes=None, negligible: float = NEGLIGIBLE_VARIANCE, parameters=None,
                  part_names=None, **metadata):
        """The model of :meth:`from_shapes` from the shapes' :func:`~.space.principal_axes`
        (computed once for the model and its evaluation, :func:`~.evaluation.evaluate`).

        Its modes and scores are views of the leading rows of ``axes.space.to_points`` and
        columns of ``axes.space.coordinates`` (in the SVD's column-major order, as
        :meth:`from_shapes` always made them); ``negligible`` must be at least
        :data:`~.space.ROUNDING_VARIANCE`, below which the model space holds no direction."""
        if not negligible >= ROUNDING_VARIANCE:
            raise ArgumentError(f"negligible variance share {negligible} below the rounding "
                                f"share {ROUNDING_VARIANCE}: the model space holds no such mode")
        space = axes.space
        n_s, n_p = len(space.coordinates), len(axes.mean)
        if np.shape(weights) != (n_p,):
            raise ArgumentError(f"weights of shape {np.shape(weights)} for {n_p} points")
        variances = kept_variances(axes.singular, n_s, negligible)
        m = len(variances)
        if m > space.coordinates.shape[1]:     # negligible >= ROUNDING_VARIANCE rules it out
            raise InternalError(f"the model keeps {m} modes, its model space only "
                                f"{space.coordinates.shape[1]}")
        return cls(mean=axes.mean, modes=space.to_points[:m].reshape(m, n_p, 3),
                   variances=variances, weights=np.asarray(weights),
                   scores=space.coordinates[:, :m],
                   names=list(names or [f"case_{i}" for i in range(n_s)]),
                   triangles=triangles, part_sizes=list(part_sizes or [n_p]), metadata=metadata,
                   parameters=parameters, part_names=list(part_names or []))

    @property
    def n_modes(self) -> int:
        return len(self.variances)

    def check(self) -> "ShapeModel":
        """Raise ValueError naming the first array that does not fit the others; else self.

        The readers (:meth:`load`, :func:`mdlshapemodel.vtkmodel.polydata_to_model`) check what
        they read, so that a damaged or hand-made model is refused before VTK draws triangles
        that index missing points or an array of another length is indexed by point.
        """
        mean = np.asarray(self.mean)
        if mean.ndim != 2 or mean.shape[1] != 3 or len(mean) == 0:
            raise ArgumentError(f"mean has shape {mean.shape}, not (points, 3)")
        n_p, m = len(mean), len(np.ravel(self.variances))
        expected = {"modes": (m, n_p, 3), "variances": (m,), "weights": (n_p,),
                    "scores": (len(self.names), m) if self.names else (len(self.scores), m)}
        for name, shape in expected.items():
            if np.shape(getattr(self, name)) != shape:
                raise ArgumentError(f"{name} has shape {np.shape(getattr(self, name))}, not {shape} "
                                 f"for {n_p} points and {m} modes")
        for name in ("mean", "modes", "variances", "weights", "scores"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise ArgumentError(f"{name} has values that are not finite")
        if self.parameters is not None and np.shape(self.parameters) not in ((n_p, 3), (n_p,)):
            raise ArgumentError(f"parameters have shape {np.shape(self.parameters)}, not ({n_p}, 3)")
        if self.triangles is not None and len(self.triangles):
            cells = np.asarray(self.triangles)
            if (cells.ndim != 2 or cells.shape[1] not in (2, 3)
                    or not np.issubdtype(cells.dtype, np.integer)):
                raise ArgumentError(f"triangles have shape {cells.shape} of {cells.dtype}")
            if cells.min() < 0 or cells.max() >= n_p:
                raise ArgumentError(f"triangles index points outside 0..{n_p - 1}")
        if self.part_sizes and (sum(self.part_sizes) != n_p or min(self.part_sizes) <= 0):
            raise ArgumentError(f"part sizes {list(self.part_sizes)} do not add up to {n_p} points")
        if self.part_names and len(self.part_names) != len(self.part_sizes):
            raise ArgumentError(f"{len(self.part_names)} part names for "
                             f"{len(self.part_sizes)} parts")
        if any(not 0 <= int(row) < n_p for row in self.landmarks.values()):
            raise ArgumentError(f"landmark rows outside 0..{n_p - 1}")
        return self

    def instance(self, scores: np.ndarray | None = None, *,
                 standard_deviations: np.ndarray | None = None) -> np.ndarray:
        """The shape ``mean + sum_m b_m mode_m`` on the first modes.

        Give either ``scores`` b (raw, in the model's units: ``model.scores`` rows are these) or
        ``standard_deviations`` s, in standard deviations of each mode (b_m = s_m sqrt(lambda_m)),
        the unit of the VTK ``ShapeModelInstance`` and of the Slicer module's sliders. (m,) ->
        (n_p, 3); a batch (k, m) -> (k, n_p, 3) (``instance(model.scores)`` gives back the
        training shapes).

        Examples
        --------
        >>> shapes = np.random.default_rng(0).normal(size=(5, 8, 3))
        >>> model = ShapeModel.from_shapes(shapes, np.full(8, 1 / 8))
        >>> plus_two = model.instance(standard_deviations=[2.0])
        >>> bool(np.allclose(plus_two, model.instance([2.0 * np.sqrt(model.variances[0])])))
        True
        """
        if (scores is None) == (standard_deviations is None):
            raise ArgumentError("give either scores or standard_deviations")
        if standard_deviations is not None:
            weights = np.asarray(standard_deviations, dtype=np.float64)
            if weights.shape[-1] > self.n_modes:
                raise ArgumentError(f"{weights.shape[-1]} standard deviations for a model of "
                                 f"{self.n_modes} mode(s)")
            scores = weights * np.sqrt(np.maximum(self.variances[:weights.shape[-1]], 0.0))
        scores = np.asarray(scores, dtype=np.float64)
        return self.mean + np.tensordot(scores, self.modes[:scores.shape[-1]], axes=1)

    def save_shape(self, path, points: np.ndarray | None = None):
        """Write a shape of the model (``points`` (n_p, 3), default the mean) with the model's
        triangles (or segments, for 2-D curves) as a mesh file: .vtp, .vtk, .stl or .ply
        (points in the model's frame; the .vtp and .vtk say LPS for 3D Slicer).

        Examples
        --------
        ::

            model = ShapeModel.load("out/model.h5")
            model.save_shape("plus2.vtp", model.instance(standard_deviations=[2.0]))
        """
        from ..prepare import io

        points = self.mean if points is None else np.asarray(points, dtype=np.float64)
        if points.shape != self.mean.shape:
            raise ArgumentError(f"points of shape {points.shape}; the model's are {self.mean.shape}")
        cells = None if self.triangles is None or len(self.triangles) == 0 else self.triangles
        io.write_polydata(path, points, cells)

    def project(self, shape: np.ndarray, n_modes: int | None = None) -> np.ndarray:
        """Scores of a corresponded, aligned shape (weighted least squares = projection)."""
        modes = self.modes[:n_modes]
        return np.einsum("mkd,kd->m", modes, (shape - self.mean) * self.weights[:, None])

    def euclidean_pca(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The model's Gaussian in a Euclidean-orthonormal basis, as Statismo stores it.

        Returns ``(basis, variances, coefficients)``: basis U (3 n_p, n_modes) with orthonormal
        columns (point-interleaved rows), variances lambda' descending with
        U diag(lambda') U^T = V diag(lambda) V^T (V: the flattened modes), and the
        (n_modes, n_modes) matrix T taking our scores b to Statismo's standardized coefficients,
        alpha = T b = diag(lambda')^(-1/2) U^T (x - mean).
        """
        n_dims = self.mean.size
        m = self.n_modes
        if m == 0:
            return np.zeros((n_dims, 0)), np.zeros(0), np.zeros((0, 0))
        flat = np.asarray(self.modes, dtype=np.float64).reshape(m, n_dims).T     # V (3n, m)
        q, r = np.linalg.qr(flat)
        small = (r * np.asarray(self.variances, dtype=np.float64)) @ r.T     # R diag(lambda) R^T
        values, vectors = np.linalg.eigh((small + small.T) / 2)
        values, vectors = np.clip(values[::-1], 0.0, None), vectors[:, ::-1]
        basis = q @ vectors
        inverse_sd = np.divide(1.0, np.sqrt(values), out=np.zeros_like(values), where=values > 0)
        return basis, values, inverse_sd[:, None] * (vectors.T @ r)

    def save(self, path):
        """Write the model to an HDF5 file in the Statismo layout (see the module docstring),
        whole or not at all (:func:`~mdlshapemodel.prepare.io.written_whole`)."""
        import h5py

        from ..prepare.io import written_whole

        keys = [_checked_key(key) for key in self.metadata]      # before the file is touched
        basis, pca_variance, to_statismo = self.euclidean_pca()
        coefficients = to_statismo @ np.asarray(self.scores, dtype=np.float64).T    # (m, n_s)
        build_time = time.asctime()
        with written_whole(path) as temporary, h5py.File(temporary, "w") as f:
            version = f.create_group("version")
            version.create_dataset("majorVersion", data=np.int32(STATISMO_VERSION[0]))
            version.create_dataset("minorVersion", data=np.int32(STATISMO_VERSION[1]))

            representer = f.create_group("representer")
            _string_attribute(representer, "name", REPRESENTER_NAME)
            _string_attribute(representer, "version", REPRESENTER_VERSION)
            kind = ("POINT_SET" if self.triangles is None else
                    "LINE_MESH" if np.shape(self.triangles)[1:] == (2,) else "POLYGON_MESH")
            _string_attribute(representer, "datasetType", kind)
            representer.create_dataset("points", data=np.asarray(self.mean, np.float32).T)
            if self.triangles is not None:
                representer.create_dataset("cells", data=np.asarray(self.triangles, np.int32).T)

            model = f.create_group("model")
            model.create_dataset("mean", data=np.asarray(self.mean, np.float32).ravel())
            model.create_dataset("pcaBasis", data=basis.astype(np.float32))
            model.create_dataset("pcaVariance", data=pca_variance.astype(np.float32))
            model.create_dataset("noiseVariance", data=np.float32(0.0))

            info = f.create_group("modelinfo")
            _string_dataset(info, "build-time", build_time)
            if coefficients.size:
                info.create_dataset("scores", data=coefficients.astype(np.float32))
            else:
                info.create_dataset("scores", data=np.zeros((1, 1), np.float32))
            builder = info.create_group("modelBuilder-0")
            _string_dataset(builder, "builderName", "mdlshapemodel area-weighted PCA")
            _string_dataset(builder, "buildTime", build_time)
            data_info = builder.create_group("dataInfo")
            for i, name in enumerate(self.names):
                _string_dataset(data_info, f"URI_{i}", str(name))
            parameters = builder.create_group("parameters")
            for key, value in zip(keys, self.metadata.values()):
                _string_dataset(parameters, key, str(value))

            self._write_native(f.create_group(NATIVE_GROUP))

    def _write_native(self, group):
        """Every field exactly (float64 as given) in ``group``."""
        import h5py

        group.attrs["format"] = "mdlshapemodel"
        group.attrs["format_version"] = FORMAT_VERSION
        for key in ("mean", "modes", "variances", "weights", "scores"):
            group.create_dataset(key, data=np.asarray(getattr(self, key)))
        group.create_dataset("names", data=np.array([str(n) for n in self.names], dtype=object),
                             dtype=h5py.string_dtype())
        group.create_dataset("part_sizes", data=np.asarray(self.part_sizes, dtype=np.int64))
        if self.part_names:
            group.create_dataset("part_names", data=np.array([str(n) for n in self.part_names],
                                                             dtype=object),
                                 dtype=h5py.string_dtype())
        if self.triangles is not None:
            group.create_dataset("triangles", data=np.asarray(self.triangles))
        if self.parameters is not None:
            group.create_dataset("parameters", data=np.asarray(self.parameters))
        if self.landmarks:
            group.create_dataset("landmark_labels", data=np.array(list(self.landmarks),
                                                                  dtype=object),
                                 dtype=h5py.string_dtype())
            group.create_dataset("landmark_rows", data=np.array(list(self.landmarks.values()),
                                                                dtype=np.int64))
        metadata = group.create_group("metadata", track_order=True)   # keeps the dict order
        for key, value in self.metadata.items():
            key = _checked_key(key)
            if value is None:
                metadata.create_dataset(key, data=h5py.Empty("f8"))
            elif isinstance(value, str):
                metadata.create_dataset(key, data=value, dtype=h5py.string_dtype())
            else:
                metadata.create_dataset(key, data=value)

    @classmethod
    def load(cls, path) -> "ShapeModel":
        """Read a model written by :meth:`save`, or a Statismo/Scalismo shape model file."""
        import h5py

        path = Path(path)
        if not path.is_file():
            raise InputError(f"{path}: no such model file")
        try:
            f = h5py.File(path, "r")
        except OSError:
            raise InputError(f"{path}: not an HDF5 file (expected a model file written by "
                             "mdlshapemodel, Statismo or Scalismo)") from None
        with f:
            try:
                if isinstance(f.get(NATIVE_GROUP), h5py.Group):
                    return cls._read_native(f[NATIVE_GROUP], f[NATIVE_GROUP]["metadata"].items())
                if f.attrs.get("format") == "mdlshapemodel" and "modes" in f:   # first layout
                    return cls._read_native(f, [(k, v) for k, v in f.attrs.items()
                                                if k not in ("format", "format_version")])
                if isinstance(f.get("model"), h5py.Group) and "representer" in f:
                    return cls._read_statismo(f, path)
            except (KeyError, ValueError, TypeError, IndexError, OSError) as error:
                raise InputError(f"{path}: damaged or incomplete model file ({error})") from None
            raise InputError(f"{path}: neither an mdlshapemodel model nor a Statismo/Scalismo "
                             "model (no /mdlshapemodel group, no /model and /representer groups)")

    @classmethod
    def _read_native(cls, group, metadata_items) -> "ShapeModel":
        metadata = {}
        for key, item in metadata_items:
            metadata[key] = _plain(item[()] if hasattr(item, "shape") else item)
        return cls(mean=group["mean"][()], modes=group["modes"][()],
                   variances=group["variances"][()], weights=group["weights"][()],
                   scores=group["scores"][()], names=[_text(n) for n in group["names"][()]],
                   triangles=group["triangles"][()] if "triangles" in group else None,
                   part_sizes=[int(s) for s in group["part_sizes"][()]], metadata=metadata,
                   parameters=group["parameters"][()] if "parameters" in group else None,
                   part_names=[_text(n) for n in group["part_names"][()]]
                   if "part_names" in group else [],
                   landmarks={_text(label): int(row) for label, row in
                              zip(group["landmark_labels"][()], group["landmark_rows"][()])}
                   if "landmark_labels" in group else {}).check()

    @classmethod
    def _read_statismo(cls, f, path) -> "ShapeModel":
        """A plain Statismo/Scalismo shape model: uniform weights, modes sqrt(n_p) u_m."""
        major, minor = 0, 8          # Statismo: files without /version predate 0.9
        if "version" in f:
            major = _read_int(f["version"], "majorVersion")
            minor = _read_int(f["version"], "minorVersion")
        if not ((major, minor) in ((0, 8), (0, 9)) or major == 1):
            raise InputError(f"{path}: unsupported Statismo file version {major}.{minor}")
        mean = np.asarray(f["model/mean"][()], np.float64).ravel()
        basis = np.asarray(f["model/pcaBasis"][()], np.float64)
        variance = np.asarray(f["model/pcaVariance"][()], np.float64).ravel()
        if mean.size % 3 or basis.ndim != 2 or basis.shape[0] != mean.size \
                or basis.shape[1] != variance.size:
            raise InputError(f"{path}: not a 3-D shape model (mean {mean.shape}, pcaBasis "
                             f"{basis.shape}, pcaVariance {variance.shape})")
        n_p, m = mean.size // 3, variance.size
        if (major, minor) == (0, 8):            # stored U diag(sqrt(lambda))
            sd = np.sqrt(np.clip(variance, 0.0, None))
            basis = basis * np.divide(1.0, sd, out=np.zeros_like(sd), where=sd > 1e-8)
        representer = f["representer"]
        if "points" in representer and representer["points"].shape != (3, n_p):
            raise InputError(f"{path}: representer points {representer['points'].shape} do not "
                             f"match the {n_p} points of the mean")
        triangles = None
        if "cells" in representer and representer["cells"].shape[:1] in ((3,), (2,)):
            triangles = np.asarray(representer["cells"][()], np.int64).T
            if triangles.size and (triangles.min() < 0 or triangles.max() >= n_p):
                raise InputError(f"{path}: representer cells index points outside 0..{n_p - 1}")

        variances = variance / n_p
        modes = np.sqrt(n_p) * basis.T.reshape(m, n_p, 3)
        coefficients = None
        info = f.get("modelinfo")
        if info is not None and "scores" in info:
            coefficients = np.asarray(info["scores"][()], np.float64)
            if coefficients.shape == (1, 1) and coefficients[0, 0] == 0.0:
                coefficients = None         # Statismo's marker for "no scores"
            elif coefficients.ndim != 2 or coefficients.shape[0] != m:
                raise InputError(f"{path}: modelinfo/scores {coefficients.shape} do not match "
                                 f"the {m} modes")
        if coefficients is None:
            scores = np.zeros((0, m))
        else:
            scores = (coefficients * np.sqrt(np.clip(variances, 0.0, None))[:, None]).T
        order = np.argsort(-variances, kind="stable")
        metadata = {}
        noise = _read_float(f["model"], "noiseVariance")
        if noise:
            metadata["statismo_noise_variance"] = noise
        return cls(mean=mean.reshape(n_p, 3), modes=modes[order], variances=variances[order],
                   weights=np.full(n_p, 1.0 / n_p), scores=scores[:, order],
                   names=_statismo_names(info, len(scores)), triangles=triangles,
                   part_sizes=[n_p], metadata=metadata)


def _checked_key(key) -> str:
    key = str(key)
    if not key or "/" in key or key == ".":
        raise ArgumentError(f"metadata key {key!r} cannot be an HDF5 name")
    return key


def _string_type(text: str):
    """Statismo's string type: fixed length, null-terminated (UTF-8 when not ASCII)."""
    import h5py

    data = text.encode("utf-8")
    string_type = h5py.h5t.C_S1.copy()
    string_type.set_size(len(data) + 1)
    string_type.set_strpad(h5py.h5t.STR_NULLTERM)
    if not text.isascii():
        string_type.set_cset(h5py.h5t.CSET_UTF8)
    return np.array(data, dtype=f"S{len(data) + 1}"), string_type


def _string_attribute(obj, name: str, text: str):
    import h5py

    data, string_type = _string_type(text)
    attribute = h5py.h5a.create(obj.id, name.encode(), string_type,
                                h5py.h5s.create(h5py.h5s.SCALAR))
    attribute.write(data, mtype=string_type)


def _string_dataset(group, name: str, text: str):
    import h5py

    data, string_type = _string_type(text)
    dataset = h5py.h5d.create(group.id, name.encode(), string_type,
                              h5py.h5s.create(h5py.h5s.SCALAR))
    dataset.write(h5py.h5s.ALL, h5py.h5s.ALL, data, mtype=string_type)


def _text(value) -> str:
    return value.decode("utf-8") if isinstance(value, bytes) else str(value)


def _plain(value):
    """A metadata value as stored: str, Python scalar, None or array."""
    import h5py

    if isinstance(value, h5py.Empty):
        return None
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.generic):
        return value.item()
    return value


def _read_int(group, name: str) -> int:
    """An int stored as a dataset (Statismo, Scalismo) or, leniently, as an attribute."""
    value = group[name][()] if name in group else group.attrs[name]
    return int(np.asarray(value).ravel()[0])


def _read_float(group, name: str) -> float:
    if name not in group:
        return 0.0
    value = np.asarray(group[name][()], np.float64).ravel()
    return float(value[0]) if value.size else 0.0


def _statismo_names(info, n_s: int) -> list:
    """Case names from modelinfo/modelBuilder-0/dataInfo/URI_<i>, else case_<i>."""
    names = {}
    builder = info.get("modelBuilder-0") if info is not None else None
    data_info = builder.get("dataInfo") if builder is not None else None
    for key, item in (data_info.items() if data_info is not None else []):
        if key.startswith("URI_") and key[4:].isdigit() and hasattr(item, "shape"):
            names[int(key[4:])] = _text(item[()])
    if n_s and sorted(names) == list(range(n_s)):
        return [names[i] for i in range(n_s)]
    return [f"case_{i}" for i in range(n_s)]


def score_outliers(model: ShapeModel, explained: float | None = None,
                   alpha: float | None = None) -> dict:
    """Mahalanobis distance of each training case over the modes that explain ``explained`` of
    the variance, its p-value against the empirical null of the training cases
    (:func:`~.outliers.training_distances`), and whether it is below ``alpha``.

    Returns a dict with ``modes``, ``threshold`` (per case, the distance at which its p =
    alpha), ``null``
    (the :class:`~.outliers.EmpiricalNull`, None without a distance), ``distance``, ``p``,
    ``p_normal`` (against the scaled Beta, which assumes normality) and ``outlier`` (one per
    case)."""
    from .outliers import ALPHA, EXPLAINED, modes_explaining, training_distances

    n = len(model.scores)
    if n < 3 or model.n_modes == 0:
        return {"modes": 0, "threshold": np.full(n, np.nan), "null": None,
                "distance": np.full(n, np.nan), "p": np.full(n, np.nan),
                "p_normal": np.full(n, np.nan), "outlier": np.zeros(n, dtype=bool)}
    k = modes_explaining(model.variances, EXPLAINED if explained is None else explained, n)
    result = training_distances(model.scores, model.variances, k,
                                ALPHA if alpha is None else alpha)
    return {"modes": result.modes, "threshold": result.threshold, "null": result.null,
            "distance": result.distance, "p": result.p, "p_normal": result.p_normal,
            "outlier": result.outlier}
