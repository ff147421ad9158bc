"""Landmark files: named points of a case, in the case's physical coordinates (mm, LPS).

Three formats are read, one file per case:

- 3D Slicer markups JSON (``.mrk.json``, or ``.json`` holding a ``markups`` list): every control
  point of every markup in the file, its ``label`` and ``position``, in the markup's
  ``coordinateSystem`` (LPS or RAS; LPS when absent). Points whose ``positionStatus`` is
  ``undefined`` (placed in a list but never put anywhere) are left out.
- 3D Slicer's older markups CSV (``.fcsv``): a ``# columns =`` comment names the columns (``x``,
  ``y``, ``z``, ``label``; Slicer's default order when absent) and a ``# CoordinateSystem =``
  comment the frame (``LPS``/``1`` or ``RAS``/``0``; RAS when absent, as older Slicer wrote it).
- A plain table (``.csv``): a header ``label,x,y,z`` (any order, more columns allowed); LPS, or
  RAS where a ``# CoordinateSystem = RAS`` comment line says so.

RAS points are turned into LPS (x and y negated). A label may appear once per file; a case may
lack labels that other cases have.

Examples
--------
>>> from pathlib import Path
>>> import tempfile
>>> folder = Path(tempfile.mkdtemp())
>>> _ = (folder / "case1.csv").write_text("label,x,y,z\\ntip,1.5,-2,30\\n")
>>> landmarks = read_landmarks(folder / "case1.csv")
>>> landmarks.labels, landmarks.points.tolist()
(('tip',), [[1.5, -2.0, 30.0]])
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ArgumentError, InputError

#: the suffixes of landmark files, in the order a case's file is looked for
SUFFIXES = (".mrk.json", ".fcsv", ".csv", ".json")
#: Slicer's column order of a ``.fcsv`` without a ``# columns`` line
FCSV_COLUMNS = ("id", "x", "y", "z", "ow", "ox", "oy", "oz", "vis", "sel", "lock", "label",
                "desc", "associatedNodeID")


@dataclass(frozen=True)
class Landmarks:
    """Named points of one case: ``labels`` (unique strings) and ``points`` (k, 3), mm, LPS;
    ``path``: the file they were read from ("" when not from a file)."""

    labels: tuple
    points: np.ndarray
    path: str = ""

    def __post_init__(self):
        if len(self.labels) != len(self.points):
            raise ArgumentError("one label per point")

    def __len__(self) -> int:
        return len(self.labels)

    def get(self, label: str) -> np.ndarray | None:
        """The point of ``label``, or None where the case lacks it."""
        try:
            return self.points[self.labels.index(label)]
        except ValueError:
            return None


def read_landmarks(path) -> Landmarks:
    """Read one landmark file (see the module docstring for the formats).

    Raises :class:`~mdlshapemodel.errors.InputError`, naming the file, where it cannot be read,
    holds no point, a coordinate is not a finite number, a label is empty or repeated, or the
    coordinate system is neither LPS nor RAS.
    """
    path = Path(path)
    name = path.name.lower()
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: cannot read the landmark file ({error})") from None
    if name.endswith(".json"):
        rows = _json_rows(path, text)
    elif name.endswith(".fcsv"):
        rows = _table_rows(path, text, default_system="RAS", default_columns=FCSV_COLUMNS)
    elif name.endswith(".csv"):
        rows = _table_rows(path, text, default_system="LPS", default_columns=None)
    else:
        raise InputError(f"{path}: not a landmark file (.mrk.json, .fcsv or .csv)")
    return _landmarks(path, rows)


def find_landmark_file(folder, case: str) -> Path | None:
    """The landmark file of ``case`` in ``folder`` (``<case><suffix>`` for a suffix of
    :data:`SUFFIXES`), or None. Raises InputError where there are several."""
    found = [Path(folder) / f"{case}{suffix}" for suffix in SUFFIXES
             if (Path(folder) / f"{case}{suffix}").is_file()]
    if len(found) > 1:
        raise InputError(f"{folder}: several landmark files for case {case!r}: "
                         f"{', '.join(p.name for p in found)}")
    return found[0] if found else None


def read_landmark_folder(folder, cases) -> dict:
    """The landmarks of every case of ``cases`` (names) that has a file in ``folder``
    (:func:`find_landmark_file`): case name -> :class:`Landmarks`.

    Raises :class:`~mdlshapemodel.errors.InputError` where the folder is missing, no case has a
    file there, or a file cannot be read (naming it).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: no such landmark folder")
    found = {}
    for case in cases:
        path = find_landmark_file(folder, case)
        if path is not None:
            found[case] = read_landmarks(path)
    if not found:
        raise InputError(f"{folder}: no landmark file named after a case (e.g. "
                         f"{next(iter(cases), 'case')}.mrk.json, .fcsv or .csv)")
    return found


def _system(path: Path, value: str) -> str:
    """"LPS" or "RAS" from a file's coordinate-system entry (Slicer also wrote 0 and 1)."""
    system = {"lps": "LPS", "1": "LPS", "ras": "RAS", "0": "RAS"}.get(str(value).strip().lower())
    if system is None:
        raise InputError(f"{path}: coordinate system {value!r} is neither LPS nor RAS")
    return system


def _json_rows(path: Path, text: str) -> list:
    """(label, (x, y, z) text or numbers, system) of every control point of a markups JSON."""
    try:
        document = json.loads(text)
    except json.JSONDecodeError as error:
        raise InputError(f"{path}: not valid JSON ({error})") from None
    markups = document.get("markups") if isinstance(document, dict) else None
    if not isinstance(markups, list):
        raise InputError(f"{path}: no 'markups' list (a 3D Slicer markups file is expected)")
    rows = []
    for markup in markups:
        if not isinstance(markup, dict):
            raise InputError(f"{path}: a markup is not an object")
        system = _system(path, markup.get("coordinateSystem", "LPS"))
        for point in markup.get("controlPoints") or []:
            if not isinstance(point, dict):
                raise InputError(f"{path}: a control point is not an object")
            if point.get("positionStatus") == "undefined":
                continue
            position = point.get("position")
            if not isinstance(position, list) or len(position) != 3:
                raise InputError(f"{path}: control point {point.get('label', '?')!r} has no "
                                 "position [x, y, z]")
            rows.append((point.get("label", ""), position, system))
    return rows


def _table_rows(path: Path, text: str, default_system: str, default_columns) -> list:
    """(label, (x, y, z) text, system) of every row of a .fcsv or .csv table."""
    system, columns, data = default_system, default_columns, []
    for line in text.splitlines():
        stripped = line.strip()
        if not stripped:
            continue
        if stripped.startswith("#"):
            key, _, value = stripped.lstrip("#").partition("=")
            key = key.strip().lower()
            if key == "coordinatesystem":
                system = _system(path, value)
            elif key == "columns":
                columns = tuple(c.strip() for c in value.split(","))
            continue
        data.append(line)
    rows = list(csv.reader(data))
    if columns is None:          # a plain table: its first row is the header
        if not rows:
            raise InputError(f"{path}: empty landmark table (a header label,x,y,z is expected)")
        columns, rows = tuple(c.strip() for c in rows[0]), rows[1:]
    index = {c.lower(): k for k, c in enumerate(columns)}
    missing = [c for c in ("label", "x", "y", "z") if c not in index]
    if missing:
        raise InputError(f"{path}: no column {', '.join(missing)} (the header has "
                         f"{', '.join(columns)})")
    result = []
    for number, row in enumerate(rows, start=1):
        if len(row) <= max(index[c] for c in ("label", "x", "y", "z")):
            raise InputError(f"{path}: landmark row {number} has {len(row)} fields, fewer than "
                             "the header's")
        result.append((row[index["label"]], [row[index[c]] for c in "xyz"], system))
    return result


def _landmarks(path: Path, rows: list) -> Landmarks:
    """Check the rows and make the record (LPS)."""
    if not rows:
        raise InputError(f"{path}: no landmark in the file")
    labels, points = [], []
    for label, position, system in rows:
        label = str(label).strip()
        if not label:
            raise InputError(f"{path}: a landmark has no label")
        if label in labels:
            raise InputError(f"{path}: label {label!r} appears twice")
        try:
            point = [float(value) for value in position]
        except (TypeError, ValueError):
            raise InputError(f"{path}: landmark {label!r}: coordinates {position!r} are not "
                             "numbers") from None
        if not all(math.isfinite(value) for value in point):
            raise InputError(f"{path}: landmark {label!r}: coordinates {point} are not finite")
        if system == "RAS":
            point = [-point[0], -point[1], point[2]]
        labels.append(label)
        points.append(point)
    return Landmarks(tuple(labels), np.array(points, dtype=np.float64), str(path))


@dataclass(frozen=True)
class SurfaceLandmarks:
    """Landmarks put on a surface with a sphere map: for each point, the closest surface point
    (``surface``, (k, 3)), the triangle (``face``) and barycentric coordinates (``coords``) it
    lies at, its image on the sphere (``sphere``, (k, 3) unit vectors) and its distance from the
    given point (``distance``, (k,), mm)."""

    surface: np.ndarray
    face: np.ndarray
    coords: np.ndarray
    sphere: np.ndarray
    distance: np.ndarray

    def on_sphere(self, sphere: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """The points' images under another sphere map of the same mesh (e.g. rotated)."""
        return _sphere_image(self.coords, self.face, sphere, faces)


def _sphere_image(coords: np.ndarray, face: np.ndarray, sphere: np.ndarray,
                  faces: np.ndarray) -> np.ndarray:
    """Unit vectors: the barycentric points ``coords`` of triangles ``face`` on a sphere map."""
    image = np.einsum("kc,kcd->kd", coords, np.asarray(sphere)[np.asarray(faces)[face]])
    return image / np.linalg.norm(image, axis=1, keepdims=True)


def on_surface(vertices: np.ndarray, faces: np.ndarray, sphere: np.ndarray,
               points: np.ndarray) -> SurfaceLandmarks:
    """Put points on a triangulated surface and on its sphere map (:class:`SurfaceLandmarks`).

    Parameters
    ----------
    vertices, faces : ndarray (n, 3), (m, 3)
        The surface.
    sphere : ndarray (n, 3)
        Its bijective map onto the unit sphere (one unit vector per vertex).
    points : ndarray (k, 3)
        Points in the surface's coordinates.

    Examples
    --------
    >>> import numpy as np
    >>> from mdlshapemodel.correspondence.sampling import icosphere
    >>> vertices, faces = icosphere(2)
    >>> placed = on_surface(2.0 * vertices, faces, vertices, np.array([[0.0, 0.0, 3.0]]))
    >>> placed.sphere.round(6).tolist(), placed.distance.round(3).tolist()
    ([[0.0, 0.0, 1.0]], [1.0])
    """
    from .nearest import TriangleGrid

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    closest, squared, face = TriangleGrid(vertices, faces).closest(points)
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)[face]]     # (k, 3, 3)
    coords = barycentric(closest, corners)
    return SurfaceLandmarks(closest, face, coords, _sphere_image(coords, face, sphere, faces),
                            np.sqrt(squared))


def barycentric(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (k, 3) of points (k, 3) in triangles (k, 3, 3).

    The points are taken to lie in their triangles (closest points): the coordinates are
    clipped to [0, 1] and renormalised. A degenerate triangle gives its vertex nearest the point.
    """
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    v0, v1, v2 = b - a, c - a, points - a
    d00, d01, d11 = (np.einsum("kd,kd->k", x, y) for x, y in ((v0, v0), (v0, v1), (v1, v1)))
    d20, d21 = np.einsum("kd,kd->k", v2, v0), np.einsum("kd,kd->k", v2, v1)
    denominator = d00 * d11 - d01 ** 2
    regular = denominator > 1e-12 * np.maximum(d00 * d11, 1e-300)
    safe = np.where(regular, denominator, 1.0)
    beta = (d11 * d20 - d01 * d21) / safe
    gamma = (d00 * d21 - d01 * d20) / safe
    weights = np.clip(np.stack([1.0 - beta - gamma, beta, gamma], axis=1), 0.0, 1.0)
    if not regular.all():
        nearest = np.argmin(np.linalg.norm(corners[~regular] - points[~regular, None], axis=2),
                            axis=1)
        weights[~regular] = np.eye(3)[nearest]
    return weights / weights.sum(axis=1, keepdims=True)
