"""An input file's bytes checked against its header before a reader trusts them.

Readers believe headers. SimpleITK fills what a short compressed stream leaves out with zeros (a
.nii.gz cut to half its length reads without an error, and half an object looks like a good case),
takes what a damaged MetaImage stream gives, and allocates whatever size a header claims; VTK's
XML reader allocates what its counts claim (a count of 10^12 aborts the process). The checks here
read a file's data once, in chunks (bounded memory), after its header was found sane:

- compressed streams decompress completely and intact: gzip (.nii.gz, .img.gz, NRRD ``encoding:
  gzip``, attached or in a detached data file) by its CRC-32 and length, bzip2 (NRRD) by its CRC,
  zlib (MetaImage ``CompressedData = True``, LOCAL or in a data file) by its Adler-32;
- the data, decompressed or not, holds as many bytes as the header says (NIfTI and Analyze,
  NRRD, MetaImage);
- the counts of a mesh file's header are within the bounds of :mod:`mdlshapemodel.config` and
  fit the file (VTK XML and legacy VTK files), and the block headers of VTK XML binary data fit
  their data.

Each check raises :class:`InputError` with a one-line reason. Formats are told by their content
(what SimpleITK's readers go by), not by the file name.
"""

from __future__ import annotations

import base64
import binascii
import bz2
import gzip
import re
import struct
import zlib
from pathlib import Path

from ..config import MAX_MESH_POINTS
from ..errors import InputError

CHUNK = 1 << 20
# A stream may decompress to this much more than its header says before it is refused: a
# compression bomb then costs at most this much decompressing.
SLACK = 1 << 20
HEADER_LIMIT = 1 << 16   # the longest text header (NRRD, MetaImage) looked at


def _corrupt(error: Exception) -> InputError:
    detail = str(error).strip() or type(error).__name__
    return InputError(f"compressed data is truncated or corrupt ({detail})")


def _short(what: str, got: int, expected: int) -> InputError:
    return InputError(f"the image data is truncated: the header says {expected:,} bytes, "
                      f"{what} {got:,}")


def _count(read, limit: int, refuse: bool = True) -> int:
    """The number of bytes ``read(CHUNK)`` gives until it gives none; beyond ``limit`` refused
    (or, not ``refuse``, no more read)."""
    total = 0
    while block := read(CHUNK):
        total += len(block)
        if total > limit:
            if not refuse:
                break
            raise InputError(f"the compressed data holds more than the {limit - SLACK:,} "
                             "bytes its header says")
    return total


def gzip_size(handle, limit: int, refuse: bool = True) -> int:
    """The decompressed length of the gzip stream (all members) from ``handle``'s position,
    each member's CRC-32 and length checked (:func:`_count` for ``limit``)."""
    try:
        with gzip.GzipFile(fileobj=handle, mode="rb") as stream:
            return _count(stream.read, limit, refuse)
    except (OSError, EOFError, zlib.error) as error:   # BadGzipFile is an OSError
        raise _corrupt(error) from None


def check_gzip(path, limit: int = 1 << 30):
    """A gzip file decompresses intact as far as ``limit`` bytes (others are not looked at):
    why a reader could not make sense of a damaged .nii.gz."""
    with open(path, "rb") as handle:
        if handle.read(2) == b"\x1f\x8b":
            handle.seek(0)
            gzip_size(handle, limit, refuse=False)


def stream_size(handle, decompressor, limit: int, available: int | None = None) -> int:
    """The decompressed length of one zlib/bzip2 stream from ``handle``'s position (at most
    ``available`` bytes of input), which must end (its check value is then verified). Output
    comes in blocks of CHUNK at most: a bomb never sits in memory."""
    total, left, data, ended = 0, available, b"", False
    try:
        while not decompressor.eof:
            if not data and not ended:
                data = handle.read(CHUNK if left is None else min(CHUNK, left))
                left = None if left is None else left - len(data)
                ended = not data
            out = decompressor.decompress(data, CHUNK)
            data = getattr(decompressor, "unconsumed_tail", b"")   # bzip2 keeps its own
            total += len(out)
            if total > limit:
                raise InputError(f"the compressed data holds more than the "
                                 f"{limit - SLACK:,} bytes its header says")
            if ended and not out and not data:
                raise InputError("compressed data is truncated or corrupt (the stream ends "
                                 "before its end marker)")
    except (OSError, EOFError, ValueError, zlib.error) as error:
        raise _corrupt(error) from None
    return total


def _file_size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


# --- label maps ----------------------------------------------------------------------------------

_METAIMAGE = rb"\s*(ObjectType|NDims|ObjectSubType|Comment)\s*="   # how MetaImage files begin


def check_image_data(path, nbytes: int):
    """Check the data of the image file ``path`` whose header says (as SimpleITK read it) that
    it holds ``nbytes`` bytes of voxels: NIfTI/Analyze (by its own header), NRRD, MetaImage;
    other files are left to their reader."""
    path = Path(path)
    with open(path, "rb") as handle:
        head = handle.read(HEADER_LIMIT)
    if head[:2] == b"\x1f\x8b" or _nifti_header(head) is not None:
        _check_nifti(path)
    elif head.startswith(b"NRRD"):
        _check_nrrd(path, head, nbytes)
    elif re.match(_METAIMAGE, head):
        _check_metaimage(path, head, nbytes)


def _open_data(path: Path):
    """``path`` opened for reading, decompressed when it is gzip."""
    handle = open(path, "rb")
    if handle.read(2) == b"\x1f\x8b":
        handle.seek(0)
        return gzip.GzipFile(fileobj=handle, mode="rb")
    handle.seek(0)
    return handle


def _nifti_header(head: bytes) -> tuple[int, int] | None:
    """Where the voxels start and how many bytes they take, by a NIfTI-1/Analyze (348-byte) or
    NIfTI-2 (540-byte) header: its own dimensions and bits per voxel (SimpleITK reports the
    rescaled type of a file with a scale slope, not the stored one)."""
    if len(head) < 4:
        return None
    for order in "<>":
        size = struct.unpack(order + "i", head[:4])[0]
        if size == 348 and len(head) >= 112:
            dims = struct.unpack(order + "8h", head[40:56])
            bits = struct.unpack(order + "h", head[72:74])[0]
            offset = struct.unpack(order + "f", head[108:112])[0]
            offset = int(offset) if 0 <= offset < 2**40 else 0    # NaN and nonsense: 0
        elif size == 540 and len(head) >= 176:
            bits = struct.unpack(order + "h", head[14:16])[0]
            dims = struct.unpack(order + "8q", head[16:80])
            offset = max(0, struct.unpack(order + "q", head[168:176])[0])
        else:
            continue
        if not 1 <= dims[0] <= 7:
            return None
        voxels = 1
        for dim in dims[1:dims[0] + 1]:
            voxels *= max(dim, 1)
        return offset, voxels * max(bits, 0) // 8
    return None


def _sibling(path: Path, suffixes) -> Path | None:
    name = path.name
    stem = name[:-3] if name.lower().endswith(".gz") else name
    stem = stem[:stem.rfind(".")] if "." in stem else stem
    return next((p for p in (path.with_name(stem + s) for s in suffixes) if p.is_file()), None)


def _check_nifti(path: Path):
    """A .nii(.gz) holds its header and voxels; an Analyze/NIfTI pair has them in .hdr and
    .img (either may be gzipped)."""
    name = path.name.lower()
    header, data = path, path
    if name.endswith((".hdr", ".hdr.gz")):
        data = _sibling(path, (".img", ".img.gz"))
    elif name.endswith((".img", ".img.gz")):
        header = _sibling(path, (".hdr", ".hdr.gz"))
    if header is None or data is None:
        return                                    # the reader says that a file is missing
    try:
        with _open_data(header) as stream:
            layout = _nifti_header(stream.read(540))
    except (OSError, EOFError, zlib.error) as error:
        raise _corrupt(error) from None
    if layout is None:
        return                                    # not NIfTI after all: the reader's to judge
    expected = sum(layout)
    with open(data, "rb") as handle:
        if handle.read(2) == b"\x1f\x8b":
            handle.seek(0)
            size, what = gzip_size(handle, expected + SLACK), "it decompresses to"
        else:
            size, what = _file_size(data), "the file holds"
    if size < expected:
        raise _short(what, size, expected)


def _text_fields(head: bytes, separator: str) -> tuple[dict, int | None]:
    """``key<separator>value`` lines of a text header (keys lower case, without spaces) and
    where the header ends: after the first empty line (NRRD, ``separator`` ':') or after the
    ElementDataFile line (MetaImage, '='); None when it does not end within ``head``."""
    fields, position = {}, 0
    while True:
        end = head.find(b"\n", position)
        if end < 0:
            return fields, None
        line = head[position:end].decode("latin-1").strip()
        position = end + 1
        if separator == ":" and not line:
            return fields, position
        key, found, value = line.partition(separator)
        if found and not line.startswith("#"):
            key = key.strip().lower().replace(" ", "")
            fields.setdefault(key, value.strip())
            if separator == "=" and key == "elementdatafile":
                return fields, position


def _integer(fields: dict, key: str, default: int = 0) -> int:
    try:
        return int(fields.get(key, default))
    except ValueError:
        raise InputError(f"the header's {key} is not a number ({fields[key][:40]!r})") from None


def _data_file(path: Path, name: str) -> Path | None:
    """A detached data file named in a header, None for lists and patterns of files (left to
    the reader)."""
    if not name or name.upper().startswith("LIST") or "%" in name or " " in name.strip():
        return None
    return path.parent / name


def _skip_lines(handle, lines: int):
    for _ in range(lines):
        if not handle.readline(HEADER_LIMIT):
            break


def _check_nrrd(path: Path, head: bytes, nbytes: int):
    fields, offset = _text_fields(head, ":")
    detached = fields.get("datafile") or fields.get("data file")
    if detached is not None:
        data, offset = _data_file(path, detached), 0
        if data is None:
            return
        if not data.is_file():
            raise InputError(f"the data file {detached!r} the header names is missing")
    elif offset is None:
        return                                    # no data after the header: the reader's to say
    else:
        data = path
    encoding = fields.get("encoding", "raw").lower()
    line_skip, byte_skip = _integer(fields, "lineskip"), _integer(fields, "byteskip")
    with open(data, "rb") as handle:
        handle.seek(offset)
        _skip_lines(handle, line_skip)
        start = handle.tell()
        if encoding in ("gzip", "gz"):
            expected = max(byte_skip, 0) + nbytes
            size, what = gzip_size(handle, expected + SLACK), "it decompresses to"
        elif encoding in ("bzip2", "bz2"):
            expected = max(byte_skip, 0) + nbytes
            size = stream_size(handle, bz2.BZ2Decompressor(), expected + SLACK)
            what = "it decompresses to"
        elif encoding == "raw":
            expected = nbytes + (byte_skip if byte_skip > 0 else 0)
            size, what = _file_size(data) - start, "the file holds"
        else:
            return                                # text encodings: the reader counts the values
    if size < expected:
        raise _short(what, size, expected)


def check_image_text_header(path):
    """What SimpleITK's own parsing cannot take: MetaIO crashes the process (a segmentation
    fault or an abort) on a MetaImage header whose NDims is not 1 to 10 (its most)."""
    path = Path(path)
    with open(path, "rb") as handle:
        head = handle.read(HEADER_LIMIT)
    if not (path.name.lower().endswith((".mha", ".mhd")) or re.match(_METAIMAGE, head)):
        return
    for dimensions in re.findall(rb"^[ \t]*NDims[ \t]*[=:](.*)$", head, re.MULTILINE | re.I):
        dimensions = dimensions.decode("latin-1").strip()
        if not (re.fullmatch("[0-9]{1,2}", dimensions) and 1 <= int(dimensions) <= 10):
            raise InputError(f"not a readable image (the MetaImage header's NDims is "
                             f"{dimensions[:40]!r}; 1 to 10 are possible)")


def _check_metaimage(path: Path, head: bytes, nbytes: int):
    fields, offset = _text_fields(head, "=")
    if offset is None:
        return
    name = fields.get("elementdatafile", "")
    if name.upper() == "LOCAL":
        data = path
    else:
        data, offset = _data_file(path, name), 0
        if data is None:
            return
        if not data.is_file():
            raise InputError(f"the data file {name!r} the header names is missing")
    compressed = fields.get("compresseddata", "false").lower() in ("true", "1", "yes")
    with open(data, "rb") as handle:
        if compressed:
            handle.seek(offset)
            available = _integer(fields, "compresseddatasize", -1)
            # MetaIO inflates zlib or gzip streams (window bits 47 detect which)
            size = stream_size(handle, zlib.decompressobj(47), nbytes + SLACK,
                               available if available > 0 else None)
            what = "it decompresses to"
        else:
            header_size = _integer(fields, "headersize")
            start = offset if name.upper() == "LOCAL" else max(header_size, 0)
            size, what = _file_size(data) - start, "the file holds"
    if size < nbytes:
        raise _short(what, size, nbytes)


# --- meshes ----------------------------------------------------------------------------------------

# The most a mesh header may claim, per kind of count: a closed triangle mesh has about twice as
# many triangles as points, three indices per triangle and a few values per point.
MESH_BOUNDS = {"points": MAX_MESH_POINTS, "cells": 2 * MAX_MESH_POINTS,
               "cell indices": 8 * MAX_MESH_POINTS, "array values": 16 * MAX_MESH_POINTS}


def check_mesh_file(path):
    """The counts a VTK XML (.vtp) or legacy VTK (.vtk) header claims are within
    :data:`MESH_BOUNDS` (from :data:`~mdlshapemodel.config.MAX_MESH_POINTS`) and, but for array
    values (which may be compressed), fit the file: each takes a byte at least. In VTK XML files
    the headers of the binary data too (:func:`_check_binary_arrays`)."""
    path = Path(path)
    size = _file_size(path)
    with open(path, "rb") as handle:
        head = handle.read(HEADER_LIMIT)
    if head.lstrip().startswith(b"<"):
        counts = _xml_counts(path)
    elif head.startswith(b"# vtk DataFile"):
        counts = _legacy_counts(path)
    else:
        return
    for what, count in counts:
        if count < 0:
            raise InputError(f"the header claims {count:,} {what}")
        if count > MESH_BOUNDS[what]:
            raise InputError(f"the header claims {count:,} {what}; a mesh may have at most "
                             f"{MESH_BOUNDS[what]:,} (MAX_MESH_POINTS: memory)")
        if what != "array values" and count > size:
            raise InputError(f"the header claims {count:,} {what} in a file of {size:,} bytes")


_LEGACY_COUNT = re.compile(rb"^[ \t]*(POINTS|VERTICES|LINES|POLYGONS|TRIANGLE_STRIPS|POINT_DATA"
                           rb"|CELL_DATA)[ \t]+(-?\d+)(?:[ \t]+(-?\d+))?", re.MULTILINE)


def _legacy_counts(path: Path) -> list:
    """(what, count) of every section of a legacy VTK file: points, cells (and their index
    lists) and values."""
    counts = []
    with open(path, "rb") as handle:
        text = handle.read()
    for match in _LEGACY_COUNT.finditer(text):
        keyword, count = match.group(1), int(match.group(2))
        what = "points" if keyword in (b"POINTS", b"POINT_DATA") else "cells"
        counts.append((what, count))
        if match.group(3):
            counts.append(("cell indices", int(match.group(3))))
    return counts


def _position(path: Path, marker: bytes) -> int | None:
    """Where ``marker`` first occurs in a file, read in chunks."""
    with open(path, "rb") as handle:
        offset, tail = 0, b""
        while block := handle.read(CHUNK):
            found = (tail + block).find(marker)
            if found >= 0:
                return offset - len(tail) + found
            offset += len(block)
            tail = block[-len(marker):]
    return None


def _xml_counts(path: Path) -> list:
    """(what, count) from a VTK XML file's elements before its appended data (which need not
    be XML): the points and cells of every piece, tuples times components of every array; and
    the binary data's block headers checked (:func:`_check_binary_arrays`)."""
    import xml.etree.ElementTree as ElementTree

    parser = ElementTree.XMLPullParser(events=("start", "end"))
    counts, points, cells, root, arrays = [], 0, 0, {}, []
    end = _position(path, b"<AppendedData")
    with open(path, "rb") as handle:
        left = end if end is not None else _file_size(path)
        while left > 0 and (block := handle.read(min(CHUNK, left))):
            left -= len(block)
            parser.feed(block)
            try:
                for event, element in parser.read_events():
                    if event == "end":
                        if element.tag in ("DataArray", "Array"):
                            arrays.append((dict(element.attrib), element.text or ""))
                        element.clear()
                        continue
                    counts += _element_counts(element, points, cells)
                    if element.tag == "VTKFile":
                        root = dict(element.attrib)
                    if element.tag == "Piece":
                        points = _attribute(element, "NumberOfPoints")
                        cells = sum(_attribute(element, f"NumberOf{kind}")
                                    for kind in ("Verts", "Lines", "Strips", "Polys", "Cells"))
                        counts += [("points", points), ("cells", cells)]
            except ElementTree.ParseError as error:
                raise InputError(f"not a readable VTK XML file ({error})") from None
    _check_binary_arrays(path, root, arrays, end)
    return counts


def _check_binary_arrays(path: Path, root: dict, arrays: list, appended: int | None):
    """The headers of a VTK XML file's binary arrays (inline base64, or appended raw or base64)
    against the data they describe: VTK's reader divided by a block size of 0 (SIGFPE) and
    allocates what a header says. Compressed: [blocks][block size][last block size][compressed
    size of each block], the block size not 0 when there are blocks, the last not larger, the
    compressed sizes within the data; uncompressed: [bytes] within the data."""
    order = ">" if root.get("byte_order") == "BigEndian" else "<"
    word = "Q" if root.get("header_type") == "UInt64" else "I"
    chunks = [(attributes, re.sub(rb"\s+", b"", text.encode("latin-1")), True)
              for attributes, text in arrays if attributes.get("format") == "binary"]
    appended_arrays = [a for a, _ in arrays if a.get("format") == "appended"]
    if appended is not None and appended_arrays:
        with open(path, "rb") as handle:
            handle.seek(appended)
            data = handle.read()
        tag = re.match(rb"<AppendedData[^>]*>\s*_", data)
        if tag is None:
            raise InputError("not a readable VTK XML file (no '_' opens its appended data)")
        encoded = b'encoding="base64"' in tag.group(0)
        data = data[tag.end():]
        closing = data.rfind(b"</AppendedData>")
        data = data[:closing] if closing >= 0 else data
        starts = sorted({_attribute_of(a, "offset") for a in appended_arrays} | {len(data)})
        for attributes in appended_arrays:
            start = _attribute_of(attributes, "offset")
            if start > len(data):
                raise InputError(f"not a readable VTK XML file (an array's offset {start:,} is "
                                 "beyond its appended data)")
            stop = starts[starts.index(start) + 1] if start < len(data) else start
            piece = data[start:stop]
            chunks.append((attributes, re.sub(rb"\s+", b"", piece) if encoded else piece,
                           encoded))
    size = struct.calcsize(word)
    bound = 8 * MESH_BOUNDS["array values"]
    for attributes, chunk, encoded in chunks:
        name = attributes.get("Name", "an array")
        try:
            _check_binary_array(chunk, encoded, "compressor" in root, order + word, size, bound)
        except (binascii.Error, ValueError, struct.error, InputError) as error:
            raise InputError(f"not a readable VTK XML file (the data of {name[:40]!r}: "
                             f"{error})") from None


def _check_binary_array(chunk: bytes, encoded: bool, compressed: bool, word: str, size: int,
                        bound: int):
    def words(data: bytes, n: int) -> tuple:
        if len(data) < n * size:
            raise InputError("its header is cut short")
        return struct.unpack(f"{word[0]}{n}{word[1]}", data[:n * size])

    def decoded(text: bytes) -> bytes:
        return base64.b64decode(text, validate=True) if encoded else text

    if not compressed:
        data = decoded(chunk)
        (length,) = words(data, 1)
        if length > len(data) - size:
            raise InputError(f"its header says {length:,} bytes, it holds {len(data) - size:,}")
        return
    def characters(n: int) -> int:
        """The length in the file of a header of ``n`` words (base64: encoded on its own)."""
        return 4 * -(-n * size // 3) if encoded else n * size

    blocks, block, last = words(decoded(chunk[:characters(3)]), 3)
    if blocks and (block == 0 or last > block):
        raise InputError(f"blocks of {block} bytes, the last of {last}")
    if blocks * block > bound:
        raise InputError(f"{blocks:,} blocks of {block:,} bytes")
    header = characters(3 + blocks)
    compressed_sizes = words(decoded(chunk[:header]), 3 + blocks)[3:]
    held = len(decoded(chunk[header:]))
    if sum(compressed_sizes) > held:
        raise InputError(f"its blocks take {sum(compressed_sizes):,} bytes, it holds {held:,}")


def _attribute_of(attributes: dict, name: str) -> int:
    value = attributes.get(name, "0")
    if not re.fullmatch("[0-9]+", value):
        raise InputError(f"not a readable VTK XML file ({name}={value[:40]!r})")
    return int(value)


def _attribute(element, name: str) -> int:
    value = element.get(name, "0")
    try:
        return int(value)
    except ValueError:
        raise InputError(f"{element.tag} {name}={value[:40]!r} is not a whole number") from None


def _element_counts(element, points: int, cells: int) -> list:
    if element.tag not in ("DataArray", "Array"):
        return []
    components = _attribute(element, "NumberOfComponents") or 1
    tuples = _attribute(element, "NumberOfTuples") or max(points, cells, 1)
    return [("array values", components * tuples)]
