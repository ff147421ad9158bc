"""A PLY mesh reader (ASCII and binary) that checks the file against its header as it reads.

VTK's PLY reader trusts the header and the face lists: a binary file cut short, a face with a
negative vertex index or a list count that is not the file's crashes the process (a segmentation
fault, measured with VTK 9.3-9.5), and a vertex count of 10^11 in a small file too. This reader takes
the vertices' x, y, z and the faces' vertex lists with numpy and raises :class:`InputError`
naming the problem: counts beyond :data:`~mdlshapemodel.config.MAX_MESH_POINTS` or beyond the
file, a file that ends early, indices outside the vertices.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from ..config import MAX_MESH_POINTS
from ..errors import InputError

TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
         "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4",
         "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
FACE_LISTS = ("vertex_indices", "vertex_index")
HEADER_LIMIT = 1 << 16


@dataclass
class Property:
    name: str
    type: str                     # numpy type code (the items' type for a list)
    count_type: str | None = None  # numpy type code of a list's count, None for a scalar


@dataclass
class Element:
    name: str
    count: int
    properties: list = field(default_factory=list)


@dataclass
class PLY:
    """What :func:`read_ply` found: vertices (n, 3), polygons as offsets (m + 1) and
    connectivity, and the comment lines (where 3D Slicer says the coordinate system)."""

    vertices: np.ndarray
    offsets: np.ndarray
    connectivity: np.ndarray
    comments: list


def _fail(message: str):
    raise InputError(f"not a readable PLY file ({message})")


def _header(data: bytes) -> tuple[str, list, list, int]:
    """(format, elements, comments, where the body starts)."""
    end = data.find(b"end_header", 0, HEADER_LIMIT)
    if not data.startswith(b"ply") or end < 0:
        _fail("no 'ply' ... 'end_header' header in the first 64 kB")
    body = data.find(b"\n", end)
    body = len(data) if body < 0 else body + 1
    lines = data[:end].decode("latin-1").splitlines()[1:]
    form, elements, comments = None, [], []
    for line in lines:
        words = line.split()
        if not words:
            continue
        if words[0] in ("comment", "obj_info"):
            comments.append(line.split(None, 1)[1] if len(words) > 1 else "")
        elif words[0] == "format" and len(words) >= 2 and words[1] in FORMATS:
            form = words[1]
        elif words[0] == "element" and len(words) == 3 and re.fullmatch("[0-9]+", words[2]):
            count = int(words[2])
            bound = MAX_MESH_POINTS if words[1] == "vertex" else 2 * MAX_MESH_POINTS
            if count > bound:
                _fail(f"the header claims {count:,} {words[1]} elements; a mesh may have at "
                      f"most {bound:,} (MAX_MESH_POINTS: memory)")
            elements.append(Element(words[1], count))
        elif words[0] == "property" and elements and len(words) == 3 and words[1] in TYPES:
            elements[-1].properties.append(Property(words[2], TYPES[words[1]]))
        elif (words[0] == "property" and elements and len(words) == 5 and words[1] == "list"
              and words[2] in TYPES and words[3] in TYPES and TYPES[words[2]][0] in "iu"):
            elements[-1].properties.append(Property(words[4], TYPES[words[3]], TYPES[words[2]]))
        else:
            _fail(f"header line {line.strip()[:60]!r}")
    if form is None:
        _fail("no 'format ascii|binary_little_endian|binary_big_endian' line")
    return form, elements, comments, body


def read_ply(path) -> PLY:
    """The vertices and polygons of a PLY file, checked: raises :class:`InputError`."""
    with open(path, "rb") as handle:
        data = handle.read()
    form, elements, comments, start = _header(data)
    names = [e.name for e in elements]
    if "vertex" not in names:
        _fail("no vertex element")
    vertex = elements[names.index("vertex")]
    axes = [next((k for k, p in enumerate(vertex.properties) if p.name == axis
                  and p.count_type is None), None) for axis in "xyz"]
    if None in axes:
        _fail("the vertices have no x, y and z")
    body = data[start:]
    if form == "ascii":
        values = _ascii_elements(body, elements)
    else:
        values = _binary_elements(body, elements, FORMATS[form])
    columns = values[names.index("vertex")]
    vertices = np.stack([columns[k] for k in axes], axis=1).astype(np.float64)
    offsets, connectivity = np.zeros(1, np.int64), np.zeros(0, np.int64)
    if "face" in names:
        face = elements[names.index("face")]
        which = next((k for k, p in enumerate(face.properties)
                      if p.name in FACE_LISTS and p.count_type), None)
        if which is None:
            _fail("the faces have no vertex_indices list")
        offsets, connectivity = values[names.index("face")][which]
        if connectivity.size and (connectivity.min() < 0 or connectivity.max() >= len(vertices)):
            bad = connectivity[(connectivity < 0) | (connectivity >= len(vertices))][0]
            _fail(f"a face refers to vertex {bad}, the file has {len(vertices)} vertices")
    return PLY(vertices, offsets, connectivity, comments)


def _lists(counts: np.ndarray, items: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    offsets = np.zeros(len(counts) + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    return offsets, items.astype(np.int64)


def _binary_elements(body: bytes, elements: list, order: str) -> list:
    """Per element, per property: an array (scalars) or (offsets, items) (lists)."""
    position, found = 0, []
    for element in elements:
        types = [np.dtype(order + p.type) for p in element.properties]
        if all(p.count_type is None for p in element.properties):
            record = np.dtype([(f"p{k}", t) for k, t in enumerate(types)])
            needed = record.itemsize * element.count
            if position + needed > len(body):
                _fail(f"the file ends within the {element.name} elements")
            table = np.frombuffer(body, record, element.count, position)
            position += needed
            found.append([table[f"p{k}"] for k in range(len(types))])
            continue
        columns, position = _binary_records(body, position, element, types, order)
        found.append(columns)
    return found


def _binary_records(body: bytes, position: int, element: Element, types: list, order: str):
    """An element with list properties: if every record has the first one's list lengths (as
    triangle meshes do), one strided read; else one record after another."""
    properties = element.properties
    counts = [np.dtype(order + p.count_type) if p.count_type else None for p in properties]

    def record_layout(at: int):
        """The dtype of the record at ``at`` (lists' lengths read there), or None past the end."""
        fields_, offset = [], at
        for k, (prop, kind) in enumerate(zip(properties, types)):
            if counts[k] is None:
                fields_.append((f"p{k}", kind))
                offset += kind.itemsize
                continue
            if offset + counts[k].itemsize > len(body):
                return None
            length = int(np.frombuffer(body, counts[k], 1, offset)[0])
            if length < 0 or length > 1 << 16:
                _fail(f"a {element.name} list of {length} items")
            fields_ += [(f"n{k}", counts[k]), (f"p{k}", kind, (length,))]
            offset += counts[k].itemsize + length * kind.itemsize
        return np.dtype(fields_)

    if element.count == 0:
        return [(np.zeros(1, np.int64), np.zeros(0, np.int64)) if c is not None
                else np.zeros(0) for c in counts], position
    first = record_layout(position)
    if first is not None and position + first.itemsize * element.count <= len(body):
        table = np.frombuffer(body, first, element.count, position)
        if all(np.all(table[f"n{k}"] == first[f"p{k}"].shape[0])
               for k in range(len(properties)) if counts[k] is not None):
            columns = [table[f"p{k}"] if counts[k] is None else
                       _lists(table[f"n{k}"], table[f"p{k}"].reshape(-1))
                       for k in range(len(properties))]
            return columns, position + first.itemsize * element.count
    rows = []
    for _ in range(element.count):
        layout = record_layout(position)
        if layout is None or position + layout.itemsize > len(body):
            _fail(f"the file ends within the {element.name} elements")
        rows.append(np.frombuffer(body, layout, 1, position)[0])
        position += layout.itemsize
    columns = []
    for k in range(len(properties)):
        if counts[k] is None:
            columns.append(np.array([row[f"p{k}"] for row in rows]))
        else:
            columns.append(_lists(np.array([row[f"n{k}"] for row in rows]),
                                  np.concatenate([row[f"p{k}"] for row in rows])))
    return columns, position


def _ascii_elements(body: bytes, elements: list) -> list:
    """Per element, per property, as :func:`_binary_elements`; one line per element."""
    lines = [line for line in body.split(b"\n") if line.strip()]
    position, found = 0, []
    for element in elements:
        if position + element.count > len(lines):
            _fail(f"the file ends within the {element.name} elements")
        try:
            rows = [np.array(line.split(), dtype=np.float64)
                    for line in lines[position:position + element.count]]
        except ValueError:
            _fail(f"a {element.name} line that is not numbers")
        position += element.count
        found.append(_ascii_columns(rows, element))
    return found


def _ascii_layout(row: np.ndarray, element: Element) -> list:
    """Where each property's values are in one line: (start, None) for a scalar, (start,
    length) for a list."""
    at, layout = 0, []
    for prop in element.properties:
        if prop.count_type is None:
            layout.append((at, None))
            at += 1
            continue
        if at >= len(row) or row[at] != int(row[at]) or not 0 <= row[at] <= 1 << 16:
            _fail(f"a {element.name} line with a bad list length")
        layout.append((at + 1, int(row[at])))
        at += 1 + int(row[at])
    if at != len(row):
        _fail(f"a {element.name} line with {len(row)} values where its lists say {at}")
    return layout


def _ascii_columns(rows: list, element: Element) -> list:
    if rows and len({len(row) for row in rows}) == 1:       # every line alike: one table
        table = np.array(rows)
        layout = _ascii_layout(table[0], element)
        if all(np.all(table[:, start - 1] == length) for start, length in layout
               if length is not None):
            return [table[:, start] if length is None else
                    _lists(np.full(len(table), length), _indices(table[:, start:start + length]))
                    for start, length in layout]
    layouts = [_ascii_layout(row, element) for row in rows]
    columns = []
    for k, prop in enumerate(element.properties):
        if prop.count_type is None:
            columns.append(np.array([row[layout[k][0]] for row, layout in zip(rows, layouts)]))
            continue
        pieces = [row[layout[k][0]:layout[k][0] + layout[k][1]]
                  for row, layout in zip(rows, layouts)]
        columns.append(_lists(np.array([len(p) for p in pieces], np.int64),
                              _indices(np.concatenate(pieces) if pieces else np.zeros(0))))
    return columns


def _indices(values: np.ndarray) -> np.ndarray:
    if values.size and (np.any(values != np.round(values)) or np.abs(values).max() > 2**62):
        _fail("a face list with values that are not vertex indices")
    return values.astype(np.int64).reshape(-1)
