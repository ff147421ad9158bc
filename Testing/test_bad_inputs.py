"""A batch with every kind of bad input: each gets one clear line, the rest of the batch goes on."""

from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from mdlshapemodel.prepare.io import read_csv, read_label_map, write_polydata
from mdlshapemodel.correspondence.sampling import icosphere

from common import run_cli_quietly as run
from files import write_label_map
from synthetic import small_mask, torus


GOOD = ["good_0", "good_1", "gööd 2 ✓"]       # unicode and spaces are fine in a name


def test_every_bad_input_gets_one_line_and_the_build_goes_on(tmp_path):
    """Through the command line: exit 0, a model of the good cases, one line on stderr and one
    row in rejected.csv per bad file naming its problem, no traceback, nothing written outside
    OUT (the inputs' folder unchanged)."""
    folder = tmp_path / "inputs"
    folder.mkdir()
    for name, position in zip(GOOD, (-0.5, 0.0, 0.5)):
        write_label_map(folder / f"{name}.nii.gz", small_mask(position))
    sphere, faces = icosphere(2)
    sphere = sphere * 10.0
    expected = {}

    write_label_map(folder / "empty.nii.gz", np.zeros((12, 12, 12)))
    expected["empty"] = "empty"
    write_label_map(folder / "other_label.nii.gz", small_mask(0.0) * 5)
    expected["other_label"] = "label 1 not present (labels found: 5)"
    (folder / "not_an_image.nii.gz").write_bytes(b"plain text, not gzip")
    expected["not_an_image"] = "not a readable image"
    write_polydata(folder / "with_holes.vtp", sphere, faces[5:])
    expected["with_holes"] = "boundary edges (holes)"
    extra = np.vstack([sphere, [[30.0, 0.0, 0.0]]])
    write_polydata(folder / "non_manifold.ply", extra,
                   np.vstack([faces, [[faces[0, 0], faces[0, 1], len(sphere)]]]))
    expected["non_manifold"] = "non-manifold edges"
    write_polydata(folder / "torus.vtk", *torus())
    expected["torus"] = "genus 1"
    nan_points = sphere.copy()
    nan_points[7] = np.nan
    write_polydata(folder / "nan_points.vtp", nan_points, faces)
    expected["nan_points"] = "non-finite"
    write_polydata(folder / "two_spheres.stl", np.vstack([sphere, sphere + 50.0]),
                   np.vstack([faces, faces + len(sphere)]))
    expected["two_spheres"] = "2 disconnected components"
    two_blobs = np.zeros((20, 20, 40), bool)
    two_blobs[5:15, 5:15, 3:15] = True
    two_blobs[5:15, 5:15, 25:37] = True
    write_label_map(folder / "two_objects.nii.gz", two_blobs)
    expected["two_objects"] = "2 disjoint objects"
    whole = (folder / "good_0.nii.gz").read_bytes()
    (folder / "half.nii.gz").write_bytes(whole[:len(whole) // 2])     # read as good before
    expected["half"] = "compressed data is truncated or corrupt"
    write_label_map(folder / "short.nii", small_mask(0.0))
    (folder / "short.nii").write_bytes((folder / "short.nii").read_bytes()[:-500])
    expected["short"] = "the image data is truncated"
    for name in ("huge.nrrd", "zero.mha", "many.mha"):
        (folder / name).write_bytes(LYING_HEADERS[name][0])
    expected["huge"] = "1,000,000,000,000,000 voxels"
    # a 2-D image is a 2-D curve's input (its region's outline): here an empty one
    sitk.WriteImage(sitk.Image(8, 8, sitk.sitkUInt8), str(folder / "flat.mha"))
    expected["flat"] = "the label map is empty"
    expected["zero"] = "zero or negative"
    expected["many"] = "NDims is '1000000'"
    for name, phrase in (("negative.ply", "a face refers to vertex"),
                         ("huge.vtp", "1,000,000,000,000 cells"), ("index.vtk", "point 99")):
        (folder / f"mesh_{name}").write_bytes(MESHES[name][0])
        expected["mesh_" + name.split(".")[0]] = phrase
    inputs = {p: p.read_bytes() for p in folder.iterdir()}

    out = tmp_path / "out"
    result = run("build", folder, "-o", out, "--label", 1, "--points", 42, "--max-sweeps", 1,
                 "--workers", 2, "--specificity-samples", 50, "--evaluation-modes", 1)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    rejected = {row["case"]: row["reason"] for row in read_csv(out / "rejected.csv")}
    assert set(rejected) == set(expected)
    for name, phrase in expected.items():
        lines = [line for line in result.stderr.splitlines() if f"/{name}." in line]
        assert len(lines) == 1, (name, lines)
        assert phrase in lines[0] and phrase in rejected[name], (name, lines[0])
    assert sorted(p.stem for p in (out / "correspondence").iterdir()) == sorted(GOOD)
    assert {p: p.read_bytes() for p in folder.iterdir()} == inputs
    assert {p.name for p in tmp_path.iterdir()} == {"inputs", "out"}
    strict = run("build", folder, "-o", tmp_path / "strict", "--label", 1, "--points", 42,
                 "--workers", 2, "--strict")
    assert strict.returncode == 2 and "strict" in strict.stderr


def intensity_image(path, k: int, kind=np.int16):
    """A CT-like image written by SimpleITK: a smooth ramp of grey values (-1000 to about
    1000) with a brighter ball, shifted by ``k``; every voxel non-zero."""
    z, y, x = np.mgrid[0:30, 0:34, 0:38].astype(float)
    image = -1000.0 + 50.0 * x + 5.0 * y + 3.0 * k
    image[(z - 15) ** 2 + (y - 17) ** 2 + (x - 19 - k) ** 2 < 8 ** 2] += 1200.0
    sitk.WriteImage(sitk.GetImageFromArray(np.round(image).astype(kind)), str(path))
    return path


def refused_build(out, paths, *options):
    """``build`` of ``paths`` into ``out`` that must reject every one: exit 2 (fewer than 3
    usable cases), no model, no traceback; returns {file name: its rejection line}."""
    result = run("build", *paths, "-o", out, "--points", 42, "--workers", 2, *options)
    assert result.returncode == 2, result.stderr
    assert "only 0 usable case(s)" in result.stderr and "Traceback" not in result.stderr
    assert not (out / "model.h5").exists()
    lines = {}
    for path in paths:
        (line,) = [line for line in result.stderr.splitlines()
                   if "rejected" in line and str(path) in line]
        lines[path.name] = line
    return lines


def test_intensity_images_are_not_label_maps(tmp_path):
    """Three int16 CT-like images given without --label: each rejected in one line that says it
    is not a label map and suggests --label (not a 'model' of the image's box)."""
    paths = [intensity_image(tmp_path / f"ct_{k}.nii.gz", k) for k in range(3)]
    for name, line in refused_build(tmp_path / "out", paths).items():
        assert "not a label map" in line and "distinct values" in line, name
        assert "--label" in line, name


def test_an_object_that_fills_its_image_out_to_the_border_is_refused(tmp_path):
    """An image whose non-zero voxels reach every side of its box (an 8-bit intensity image of
    fewer grey values than a label map may have, a mask of ones) is no object's label map:
    without --label the line suggests it; with --label, the label that fills the image is
    named."""
    noise = np.random.default_rng(0).integers(1, 200, size=(3, 16, 18, 20)).astype(np.uint8)
    paths = [tmp_path / "grey_0.nii.gz", tmp_path / "grey_1.nii.gz", tmp_path / "ones.nii.gz"]
    for path, values in zip(paths, (noise[0], noise[1], np.ones((16, 18, 20), np.uint8))):
        sitk.WriteImage(sitk.GetImageFromArray(values), str(path))
    for name, line in refused_build(tmp_path / "out", paths).items():
        assert "not a label map" in line and "border on every side" in line, name
        assert "--label" in line, name
    labelled = [tmp_path / f"box_{k}.nii.gz" for k in range(3)]
    for k, path in enumerate(labelled):
        write_label_map(path, np.ones((12 + k, 14, 16)))
    for name, line in refused_build(tmp_path / "labelled", labelled, "--label", 1).items():
        assert "label 1 fills the image out to its border on every side" in line, name


def test_a_missing_label_map_is_a_rejection_that_says_so(tmp_path):
    """Through the Python API (the CLI checks paths before), a file that is not there is a
    rejection with a plain reason, not SimpleITK's message."""
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.prepare import prepare_case

    missing = tmp_path / "gone.nii.gz"
    result = prepare_case(str(missing), BuildConfig())
    assert result.name == "gone"
    assert "no such file" in result.reason
    write_label_map(missing, small_mask(0.0))
    assert not hasattr(prepare_case(str(missing), BuildConfig(cache_dir="")), "reason")


def test_a_bug_while_preparing_stops_the_build_naming_the_case(tmp_path, monkeypatch):
    """Only problems of the input are rejections: an exception of our own code (here a
    ZeroDivisionError planted in the sphere map) stops the build with a message that says it is a
    bug and names the case, and the traceback goes to build.log."""
    import pytest

    from mdlshapemodel import BuildConfig, InternalError, build_model
    from mdlshapemodel.prepare import case as preparation, prepare_case

    folder = tmp_path / "inputs"
    folder.mkdir()
    for k, position in enumerate((-0.5, 0.0, 0.5)):
        write_label_map(folder / f"case_{k}.nii.gz", small_mask(position))

    def broken_sphere_map(vertices, faces, **options):
        raise ZeroDivisionError("planted")

    monkeypatch.setattr(preparation, "sphere_map", broken_sphere_map)
    with pytest.raises(ZeroDivisionError):
        prepare_case(str(folder / "case_0.nii.gz"), BuildConfig(cache_dir=""))
    output = tmp_path / "out"
    with pytest.raises(InternalError) as raised:
        build_model([folder], output, BuildConfig(workers=1, cache_dir="", points=42))
    message = str(raised.value)
    assert "case_0.nii.gz" in message and "bug" in message and "ZeroDivisionError" in message
    log = (output / "build.log").read_text()
    assert "Traceback" in log and "broken_sphere_map" in log
    assert not (output / "model.h5").exists()
    # a bug is not an input error: code that rejects inputs by catching those lets it through
    from mdlshapemodel import MDLShapeModelError

    assert not isinstance(raised.value, MDLShapeModelError)


# --- damaged files and headers that lie ----------------------------------------------------------

def prepared_or_reason(path):
    """``prepare_case``'s verdict on a file: 'prepared' or the rejection's reason."""
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.prepare import prepare_case

    result = prepare_case(path, BuildConfig(cache_dir=""))
    return getattr(result, "reason", "prepared")


def write_compressed(folder, suffix):
    """A small label map written compressed; returns (the file to read, the file of its
    compressed voxels)."""
    import gzip

    image = sitk.GetImageFromArray(small_mask(0.0).astype(np.uint8))
    if suffix == ".img.gz":                     # an Analyze/NIfTI pair with a gzipped image
        sitk.WriteImage(image, str(folder / "case.hdr"))
        (folder / "case.img.gz").write_bytes(gzip.compress((folder / "case.img").read_bytes()))
        (folder / "case.img").unlink()
        return folder / "case.hdr", folder / "case.img.gz"
    path = folder / f"case{suffix}"
    sitk.WriteImage(image, str(path), True)
    data = {".nhdr": "case.raw.gz", ".mhd": "case.zraw"}.get(suffix, path.name)
    return path, folder / data


@pytest.mark.parametrize("suffix", [".nii.gz", ".img.gz", ".nrrd", ".nhdr", ".mha", ".mhd"])
def test_a_compressed_label_map_cut_short_or_damaged_is_rejected(tmp_path, suffix):
    """Measured before: a .nii.gz cut to half its length was read without an error, the missing
    voxels zeros, and prepared as a good case. Every compressed stream is now checked whole
    (gzip: CRC-32 and length; MetaImage's zlib: Adler-32 and size) before a reader trusts it."""
    path, data = write_compressed(tmp_path, suffix)
    whole = data.read_bytes()
    assert prepared_or_reason(path) == "prepared"
    data.write_bytes(whole[:len(whole) // 2])
    assert "compressed data is truncated or corrupt" in prepared_or_reason(path)
    damaged = bytearray(whole)
    damaged[len(whole) * 3 // 4] ^= 0x10        # one bit, well inside the compressed voxels
    data.write_bytes(bytes(damaged))
    assert "compressed data is truncated or corrupt" in prepared_or_reason(path)


def test_a_compressed_stream_far_longer_than_its_header_says_is_refused(tmp_path):
    """A compression bomb costs at most 1 MiB of decompressing beyond what the header says."""
    import gzip

    path, _ = write_compressed(tmp_path, ".nii.gz")
    path.write_bytes(gzip.compress(gzip.decompress(path.read_bytes()) + bytes(20 << 20)))
    voxels = 352 + np.prod(small_mask(0.0).shape)      # the NIfTI header and one byte per voxel
    assert (f"the compressed data holds more than the {voxels:,} bytes its header says"
            in prepared_or_reason(path))


@pytest.mark.parametrize("suffix", [".nii", ".hdr", ".nrrd", ".mha"])
def test_an_uncompressed_label_map_shorter_than_its_header_says_is_rejected(tmp_path, suffix):
    """Before, a .nii (or Analyze .img) cut short was read with zeros for the missing voxels."""
    path = tmp_path / f"case{suffix}"
    write_label_map(path, small_mask(0.0))
    data = path.with_suffix(".img") if suffix == ".hdr" else path
    data.write_bytes(data.read_bytes()[:-1000])
    reason = prepared_or_reason(path)
    assert reason.startswith("the image data is truncated: the header says"), reason


NRRD = "NRRD0004\ntype: uint8\ndimension: {dimension}\n{space}\nsizes: {sizes}\n" \
       "space directions: {directions}\nkinds: {kinds}\nencoding: raw\n\n"
META = "ObjectType = Image\nNDims = {dimension}\nDimSize = {sizes}\nElementType = MET_UCHAR\n" \
       "ElementSpacing = {spacing}\nElementNumberOfChannels = {channels}\n{matrix}" \
       "ElementDataFile = LOCAL\n"


def nrrd(sizes, spacing=(1.0, 1.0, 1.0), vector=False) -> bytes:
    """A NRRD header (with as many voxels after it as a tiny image needs)."""
    axes = [f"({','.join(str(s if i == k else 0) for i in range(len(spacing)))})"
            for k, s in enumerate(spacing)]
    header = NRRD.format(dimension=len(sizes), sizes=" ".join(map(str, sizes)),
                         space=("space: 3D-right-handed" if len(spacing) == 3
                                else f"space dimension: {len(spacing)}"),
                         directions=("none " if vector else "") + " ".join(axes),
                         kinds=("vector " if vector else "") + " ".join(["domain"] * len(axes)))
    return header.encode() + bytes(min(np.prod(sizes), 4096))


def meta(sizes, spacing="1 1 1", channels=1, dimension=None, matrix=None) -> bytes:
    header = META.format(dimension=dimension or len(sizes), sizes=" ".join(map(str, sizes)),
                         spacing=spacing, channels=channels,
                         matrix=f"TransformMatrix = {matrix}\n" if matrix else "")
    return header.encode() + bytes(min(np.prod(sizes) * channels, 4096))


LYING_HEADERS = {
    # a header of a few bytes that claims 10^15 voxels: refused from the header, with its size
    "huge.nrrd": (nrrd([100000, 100000, 100000]),
                  "the header claims 100000 x 100000 x 100000 = 1,000,000,000,000,000 voxels "
                  "(1,000,000.0 GB of 8-bit unsigned integer); a label map may have at most"),
    "huge.mha": (meta([100000, 100000, 100000]), "= 1,000,000,000,000,000 voxels"),
    "movie.mha": (meta([4, 4, 4, 2], "1 1 1 1"), "a 4-D image (4 x 4 x 4 x 2); this build needs"),
    "vector.nrrd": (nrrd([2, 4, 4, 4], vector=True), "got an image of 2 values per voxel"),
    "channels.mha": (meta([4, 4, 4], channels=3), "got an image of 3 values per voxel"),
    "negative.mha": (meta([4, 4, 4], "1 -0.5 1"), "the header's spacing (1, -0.5, 1) is zero or "
                                                  "negative"),
    "zero.mha": (meta([4, 4, 4], "0 1 1"), "the header's spacing (0, 1, 1) is zero or negative"),
    "nan.mha": (meta([4, 4, 4], "nan nan nan"), "is zero or negative"),   # MetaIO: NaN -> 0
    "zero.nrrd": (nrrd([4, 4, 4], (0.0, 1.0, 1.0)), "is zero or negative"),
    # SimpleITK's Execute ran for more than 30 minutes on this one
    "direction.mha": (meta([4, 4, 4], matrix="1 0 0 0 1 0 1e308 0 1"),
                      "the header's direction (1, 0, 1e+308, 0, 1, 0, 0, 0, 1) is not a rotation"),
    # MetaIO crashes the process on these (a segmentation fault): refused before it reads them
    "dimensions.mha": (meta([4, 4, 4], dimension=-1), "the MetaImage header's NDims is '-1'"),
    "many.mha": (meta([4, 4, 4], dimension=1000000), "NDims is '1000000'; 1 to 10 are possible"),
}


@pytest.mark.parametrize("name", sorted(LYING_HEADERS))
def test_a_header_that_lies_is_rejected_before_any_voxel_is_read(tmp_path, monkeypatch, name):
    """Checked from the header (SimpleITK's ReadImageInformation) before anything is allocated:
    the voxels are never read (the reader's Execute is not called)."""
    data, phrase = LYING_HEADERS[name]
    (tmp_path / name).write_bytes(data)

    def never(self):
        raise AssertionError("the voxels of a rejected header were read")

    monkeypatch.setattr(sitk.ImageFileReader, "Execute", never)
    reason = prepared_or_reason(tmp_path / name)
    assert phrase in reason, reason


def test_nan_and_zero_in_a_nifti_header_are_taken_as_its_reader_says(tmp_path):
    """What SimpleITK already handles: a NIfTI pixdim of NaN or 0 is read as spacing 1 (its
    documented fallback), a NaN in the sform is an error of the reader, named."""
    import struct

    write_label_map(tmp_path / "case.nii", small_mask(0.0))
    header = bytearray((tmp_path / "case.nii").read_bytes())
    struct.pack_into("<hh", header, 252, 0, 0)                    # no qform, no sform
    struct.pack_into("<4f", header, 76, 1.0, float("nan"), 0.0, 1.0)
    (tmp_path / "pixdim.nii").write_bytes(bytes(header))
    assert read_label_map(tmp_path / "pixdim.nii").spacing == (1.0, 1.0, 1.0)
    struct.pack_into("<h", header, 254, 1)                        # sform with a NaN
    struct.pack_into("<4f", header, 280, float("nan"), 0.0, 0.0, 0.0)
    (tmp_path / "sform.nii").write_bytes(bytes(header))
    reason = prepared_or_reason(tmp_path / "sform.nii")
    assert reason.startswith("not a readable image (ITK only supports orthonormal"), reason


def test_a_4d_image_of_one_volume_is_its_3d_volume(tmp_path):
    mask = small_mask(0.0).astype(np.uint8)
    sitk.WriteImage(sitk.JoinSeries(sitk.GetImageFromArray(mask)), str(tmp_path / "one.nii.gz"))
    assert np.array_equal(read_label_map(tmp_path / "one.nii.gz").mask, mask != 0)


def test_the_size_bound_is_stated_once_and_follows_the_memory_budget():
    from mdlshapemodel import config

    assert config.MAX_VOXELS == config.MEMORY_BUDGET // config.PREPARATION_BYTES_PER_VOXEL
    assert config.MAX_MESH_POINTS == (config.MEMORY_BUDGET
                                      // config.PREPARATION_BYTES_PER_MESH_POINT)
    readme = (Path(__file__).parents[1] / "README.md").read_text()
    assert f"{config.MAX_VOXELS:,}" in readme and f"{config.MAX_MESH_POINTS:,}" in readme


# --- meshes --------------------------------------------------------------------------------------

def sphere_mesh():
    from mdlshapemodel.correspondence.sampling import icosphere

    vertices, faces = icosphere(2)
    return vertices * 10.0, faces


def legacy_vtk(points: str, polygons: str) -> bytes:
    return ("# vtk DataFile Version 3.0\nx\nASCII\nDATASET POLYDATA\n" + points
            + polygons).encode()


PLY_HEADER = b"ply\nformat binary_little_endian 1.0\nelement vertex %d\nproperty float x\n" \
             b"property float y\nproperty float z\nelement face %d\n" \
             b"property list uchar int vertex_indices\nend_header\n"


def damaged_ply(kind: str) -> bytes:
    """Binary PLY files on which VTK's PLY reader crashed the process (segmentation fault)."""
    vertices, faces = sphere_mesh()
    body = vertices.astype("<f4").tobytes()
    records = np.zeros(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    records["n"], records["v"] = 3, faces
    if kind == "negative index":
        records["v"][5, 1] = -16777216
    if kind == "list count":
        records["n"][0] = 200
    data = PLY_HEADER % (len(vertices), len(faces)) + body + records.tobytes()
    if kind == "cut short":
        data = data[:len(data) // 2]
    if kind == "huge count":
        data = PLY_HEADER % (10**11, len(faces)) + body
    return data


def far_obj() -> bytes:
    """An OBJ mesh with a point at 10^300 mm (finite: its squares overflow)."""
    vertices, faces = sphere_mesh()
    vertices[0, 0] = 1e300
    return "\n".join(["v " + " ".join(f"{v:.9g}".replace("e+", "e") for v in point)
                      for point in vertices]
                     + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]).encode()


MESHES = {
    "far.obj": (far_obj(), "the mesh has a coordinate of 1e+300 mm, beyond 1e+09"),   # a bug before
    "huge.vtk": (legacy_vtk("POINTS 100000000000 float\n0 0 0 1 0 0 0 1 0\n", ""),
                 "the header claims 100,000,000,000 points; a mesh may have at most"),
    "lying.vtk": (legacy_vtk("POINTS 5000000 float\n0 0 0 1 0 0 0 1 0\n", ""),
                  "the header claims 5,000,000 points in a file of"),
    "index.vtk": (legacy_vtk("POINTS 3 float\n0 0 0 1 0 0 0 1 0\n", "POLYGONS 1 4\n3 0 1 99\n"),
                  "a cell refers to point 99; the mesh has 3 points"),
    "huge.vtp": (b'<?xml version="1.0"?>\n<VTKFile type="PolyData" version="0.1">\n<PolyData>\n'
                 b'<Piece NumberOfPoints="3" NumberOfPolys="1000000000000">\n',
                 "the header claims 1,000,000,000,000 cells"),      # VTK aborted (bad_alloc)
    "cut.ply": (damaged_ply("cut short"), "the file ends within the face elements"),
    "negative.ply": (damaged_ply("negative index"), "a face refers to vertex -16777216"),
    "count.ply": (damaged_ply("list count"), "not a readable PLY file"),
    "huge.ply": (damaged_ply("huge count"), "the header claims 100,000,000,000 vertex elements"),
}


@pytest.mark.parametrize("name", sorted(MESHES))
def test_a_damaged_or_lying_mesh_file_is_rejected_not_a_crash(tmp_path, name):
    """Each of these crashed the process, allocated what the header claimed or was a Python
    exception (a bug) before."""
    data, phrase = MESHES[name]
    (tmp_path / name).write_bytes(data)
    reason = prepared_or_reason(tmp_path / name)
    assert phrase in reason, reason


def test_a_vtk_file_whose_offsets_overrun_its_indices_is_rejected_not_a_crash(tmp_path):
    """Found by mutating files in child processes: VTK's legacy reader takes a last offset of
    9600 for 960 indices, and vtkTriangleFilter then crashed the process."""
    import re

    path = tmp_path / "mesh.vtk"
    write_polydata(path, *sphere_mesh())
    text = path.read_text()
    last = re.search(r"(\d+)\s*\nCONNECTIVITY", text)
    path.write_text(text[:last.start(1)] + last.group(1) + "0" + text[last.end(1):])
    reason = prepared_or_reason(path)
    assert reason == f"the cells' offsets (0 to {last.group(1)}0) do not fit their " \
                     f"{last.group(1)} point indices", reason


def test_a_vtp_whose_block_header_says_blocks_of_0_bytes_is_rejected_not_a_crash(tmp_path):
    """Found by mutating files in child processes: one changed base64 digit made a compressed
    array's block size 0, and VTK's XML reader divided by it (SIGFPE, the process ended)."""
    import base64
    import struct

    path = tmp_path / "mesh.vtp"
    write_polydata(path, *sphere_mesh())
    data = path.read_bytes()
    start = data.index(b"_", data.index(b"<AppendedData")) + 1
    header = base64.b64decode(data[start:start + 16])            # blocks, block size, last
    blocks, _, last = struct.unpack("<3I", header)
    damaged = base64.b64encode(struct.pack("<3I", blocks, 0, last))
    path.write_bytes(data[:start] + damaged + data[start + 16:])
    reason = prepared_or_reason(path)
    assert reason.startswith("not a readable VTK XML file (the data of ") and \
        f"blocks of 0 bytes, the last of {last}" in reason, reason


def test_a_vtp_with_a_damaged_compressed_block_is_rejected(tmp_path):
    """VTK XML files compress their arrays in zlib blocks (Adler-32); the reader's error on a
    damaged block is a rejection, even when the other arrays were read."""
    path = tmp_path / "mesh.vtp"
    write_polydata(path, *sphere_mesh())
    data = path.read_bytes()
    start = data.index(b"<AppendedData")
    start = data.index(b"_", start) + 1
    end = data.index(b"</AppendedData>")
    for at in range(start + (end - start) // 3, end - 10, (end - start) // 7):
        damaged = bytearray(data)
        damaged[at] = ord("A") if damaged[at] != ord("A") else ord("B")   # another base64 digit
        path.write_bytes(bytes(damaged))
        assert prepared_or_reason(path).startswith("not a readable mesh ("), at


def test_the_package_reads_ply_files_as_vtk_does(tmp_path):
    """The package's PLY reader (VTK's crashes on damaged files) gives VTK's points and faces
    on valid files: ASCII and binary, both byte orders, colours, quads."""
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    from mdlshapemodel.prepare.ply import read_ply
    from mdlshapemodel.prepare.surface import arrays_to_polydata

    vertices, faces = sphere_mesh()
    polydata = arrays_to_polydata(vertices, faces)
    colours = vtk.vtkUnsignedCharArray()
    colours.SetNumberOfComponents(3)
    colours.SetName("RGB")
    for k in range(len(vertices)):
        colours.InsertNextTuple3(k % 256, 7, 9)
    polydata.GetPointData().SetScalars(colours)
    quads = vtk.vtkPolyData()
    quads.SetPoints(polydata.GetPoints())
    cells = vtk.vtkCellArray()
    cells.InsertNextCell(4, [0, 1, 2, 3])
    cells.InsertNextCell(3, [4, 5, 6])
    quads.SetPolys(cells)
    for name, data, setting in [("ascii", polydata, "SetFileTypeToASCII"),
                                ("little", polydata, "SetFileTypeToBinary"),
                                ("big", polydata, "SetDataByteOrderToBigEndian"),
                                ("colours", polydata, None), ("quads", quads, "SetFileTypeToASCII")]:
        writer = vtk.vtkPLYWriter()
        writer.SetFileName(str(tmp_path / f"{name}.ply"))
        if setting:
            getattr(writer, setting)()
        if name == "colours":
            writer.SetArrayName("RGB")
        writer.SetInputData(data)
        writer.Write()
        reader = vtk.vtkPLYReader()
        reader.SetFileName(str(tmp_path / f"{name}.ply"))
        reader.Update()
        expected = reader.GetOutput()
        found = read_ply(tmp_path / f"{name}.ply")
        np.testing.assert_array_equal(found.vertices,
                                      vtk_to_numpy(expected.GetPoints().GetData()))
        np.testing.assert_array_equal(found.offsets,
                                      vtk_to_numpy(expected.GetPolys().GetOffsetsArray()))
        np.testing.assert_array_equal(found.connectivity,
                                      vtk_to_numpy(expected.GetPolys().GetConnectivityArray()))


# --- names and where outputs go ------------------------------------------------------------------

def test_a_case_file_stays_directly_in_its_folder_whatever_the_name(tmp_path):
    from mdlshapemodel.prepare.io import case_file

    for name in ("../escaped", "../../etc/passwd", "a/b", "a\\b", "..", ".", "", "x\ny",
                 "\x1b[2Jterminal", "/absolute"):
        path = case_file(tmp_path, name)
        assert path.parent == tmp_path and path.name.isprintable(), name
        assert path.name.removesuffix(".vtp").strip("."), name
    assert case_file(tmp_path, "gööd 1 ✓").name == "gööd 1 ✓.vtp"    # unicode and spaces kept
    assert case_file(tmp_path, "..").name == "__.vtp"


@pytest.mark.slow
def test_names_that_would_leave_out_write_inside_it(tmp_path):
    """Case names from anywhere (here: a manifest's case column, as a caller of the API or a
    Slicer node could give them too) make files only inside OUT; the names are kept in the
    model."""
    from mdlshapemodel import BuildConfig, ShapeModel, build_model

    folder = tmp_path / "inputs"
    folder.mkdir()
    names = {"a": "../../escaped", "b": "sub/dir/x", "c": ".."}
    rows = ["case,part,file"]
    for position, (stem, name) in zip((-0.5, 0.0, 0.5), names.items()):
        write_label_map(folder / f"{stem}.nii.gz", small_mask(position))
        rows.append(f"{name},shape,{stem}.nii.gz")
    manifest = folder / "cases.csv"
    manifest.write_text("\n".join(rows) + "\n")
    before = set(tmp_path.rglob("*"))
    out = tmp_path / "deep" / "out"
    build_model([], out, BuildConfig(points=42, max_sweeps=1, workers=1, cache_dir="",
                                     specificity_samples=50, evaluation_modes=1),
                manifest=manifest)
    written = set(tmp_path.rglob("*")) - before
    assert all(path in (out, out.parent) or out in path.parents for path in written)
    assert sorted(p.name for p in (out / "correspondence").iterdir()) == [
        ".._.._escaped.vtp", "__.vtp", "sub_dir_x.vtp"]
    assert sorted(ShapeModel.load(out / "model.h5").names) == sorted(names.values())


# --- data only: nothing from a file is run ----------------------------------------------------------

class Planted:
    """Unpickling this would run code (touch a file): what a hostile pickle does."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_a_cache_entry_holding_a_pickle_is_made_anew_not_run(tmp_path):
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.prepare.cache import cache_key, prepare_case_cached

    path = tmp_path / "case.nii.gz"
    write_label_map(path, small_mask(0.0))
    config = BuildConfig(cache_dir=str(tmp_path / "cache"))
    entry = tmp_path / "cache" / f"{cache_key(str(path), config)}.npz"
    entry.parent.mkdir()
    marker = tmp_path / "the pickle ran"
    np.savez(entry, reason=np.array([Planted(marker)], dtype=object))
    result, reused = prepare_case_cached(str(path), config, config.cache_dir)
    assert not marker.exists() and not reused and not hasattr(result, "reason")
    # the entry is now the real one; cut short (a damaged zip), it is made anew too
    entry.write_bytes(entry.read_bytes()[:300])
    result, reused = prepare_case_cached(str(path), config, config.cache_dir)
    assert not reused and not hasattr(result, "reason")


def test_a_checkpoint_holding_a_pickle_is_refused_not_run(tmp_path):
    from mdlshapemodel.folders import load_checkpoint

    marker = tmp_path / "the pickle ran"
    np.savez(tmp_path / "checkpoint.npz", names=np.array([Planted(marker)], dtype=object))
    with pytest.raises(ValueError, match="allow_pickle"):
        load_checkpoint(tmp_path / "checkpoint.npz")
    assert not marker.exists()


def test_no_file_is_unpickled_or_evaluated_anywhere_in_the_package():
    """Model files are read through h5py datasets, settings and metrics as JSON, arrays with
    allow_pickle=False: nothing in the package (nor the Slicer module) unpickles or evaluates."""
    import re

    # the source tree (an installed package has no MDLShapeModel.py beside it)
    package = Path(__file__).resolve().parents[1] / "MDLShapeModel" / "mdlshapemodel"
    risky = re.compile(r"\bimport pickle|\bpickle\.|allow_pickle\s*=\s*True|\beval\(|\bexec\(|"
                       r"\bmarshal\b|\bshelve\b|yaml\.load|\bdill\b|joblib|(?<![.\w])compile\(")
    for file in sorted(package.rglob("*.py")) + [package.parent / "MDLShapeModel.py"]:
        for number, line in enumerate(file.read_text().splitlines(), 1):
            assert not risky.search(line), f"{file}:{number}: {line.strip()}"
