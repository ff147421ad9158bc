"""Closed 2-D curves: the readers of every kind of file, their one-line rejections, the arc-length
parameterization and the alignment of origins (prepare/curve.py)."""

from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import vtk
from vtk.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray

from mdlshapemodel.errors import InputError
from mdlshapemodel.prepare.curve import (align_curve_origins, check_curve, curve_map,
                                         find_crossing, point_at, resample_curve,
                                         segment_lengths, segment_vertex_lengths, signed_area)
from mdlshapemodel.prepare.curve_io import is_curve_file, read_curve

from common import DATA, HANDS


def ellipse(n=60, a=20.0, b=10.0, centre=(5.0, -3.0), clockwise=False):
    t = 2 * np.pi * np.arange(n) / n
    if clockwise:
        t = -t
    return np.stack([centre[0] + a * np.cos(t), centre[1] + b * np.sin(t)], axis=1)


def write_table(path, points, separator=",", header="x,y", extra=None):
    lines = [header] if header else []
    for row in points:
        values = list(row) + ([] if extra is None else [extra])
        lines.append(separator.join(repr(float(v)) for v in values))
    Path(path).write_text("\n".join(lines) + "\n")
    return path


def polydata_of(points, cells, polygons=None):
    """vtkPolyData with points (n, 3) and line cells (lists of point ids)."""
    polydata = vtk.vtkPolyData()
    vtk_points = vtk.vtkPoints()
    vtk_points.SetData(numpy_to_vtk(np.ascontiguousarray(points, dtype=np.float64), deep=True))
    polydata.SetPoints(vtk_points)
    for attribute, groups in (("SetLines", cells), ("SetPolys", polygons)):
        if groups:
            array = vtk.vtkCellArray()
            offsets = np.cumsum([0] + [len(c) for c in groups])
            array.SetData(numpy_to_vtkIdTypeArray(offsets.astype(np.int64), deep=True),
                          numpy_to_vtkIdTypeArray(np.concatenate(groups).astype(np.int64),
                                                  deep=True))
            getattr(polydata, attribute)(array)
    return polydata


def write_polydata(path, polydata):
    writer = vtk.vtkXMLPolyDataWriter() if str(path).endswith(".vtp") else vtk.vtkPolyDataWriter()
    writer.SetInputData(polydata)
    writer.SetFileName(str(path))
    writer.Write()
    return path


def with_z(points, z=0.0):
    return np.column_stack([points, np.full(len(points), z)])


def disc_mask(shape=(40, 50), centre=(20, 24), radius=12.0):
    rows, columns = np.indices(shape)
    return ((rows - centre[0]) ** 2 + (columns - centre[1]) ** 2 <= radius ** 2).astype(np.uint8)


def same_curve(a, b, tolerance=1e-9):
    """The same closed polygon up to the choice of first point."""
    assert len(a) == len(b)
    shift = int(np.argmin(np.linalg.norm(b - a[0], axis=1)))
    np.testing.assert_allclose(np.roll(b, -shift, axis=0), a, atol=tolerance)


# ------------------------------------------------------------------------------------------------
# Readers


def test_tables_with_commas_tabs_spaces_and_headers_read_the_same_curve(tmp_path):
    points = ellipse()
    comma = read_curve(write_table(tmp_path / "a.csv", points))
    tab = read_curve(write_table(tmp_path / "b.txt", points, "\t", header=None))
    space = read_curve(write_table(tmp_path / "c.txt", points, "  ", header="# x y\nX Y"))
    constant_z = read_curve(write_table(tmp_path / "d.csv", points, ",", "x,y,z", extra=7.5))
    for curve in (comma, tab, space, constant_z):
        np.testing.assert_allclose(curve, points, atol=1e-12)


def test_a_clockwise_curve_with_repeated_points_is_cleaned(tmp_path):
    points = ellipse(clockwise=True)
    noisy = np.concatenate([points[:10], points[9:10], points[10:], points[:1]])  # repeat + close
    curve = read_curve(write_table(tmp_path / "c.csv", noisy))
    assert signed_area(curve) > 0
    assert len(curve) == len(points)
    np.testing.assert_array_equal(curve[0], points[0])           # the first point stays first
    assert np.all(segment_lengths(curve) > 0)
    same_curve(curve, points[::-1])


def test_polylines_in_vtk_and_vtp_files_read_as_one_closed_curve(tmp_path):
    points = ellipse(n=40)
    n = len(points)
    # legacy .vtk: one polyline closed by repeating its first id
    closed_ids = polydata_of(with_z(points, 2.0), [list(range(n)) + [0]])
    from_vtk = read_curve(write_polydata(tmp_path / "one.vtk", closed_ids))
    # .vtp: segments in scrambled order and directions, forming one closed chain
    rng = np.random.default_rng(3)
    segments = [[k, (k + 1) % n] if rng.random() < 0.5 else [(k + 1) % n, k]
                for k in rng.permutation(n)]
    from_vtp = read_curve(write_polydata(tmp_path / "pieces.vtp",
                                         polydata_of(with_z(points), segments)))
    # first and last points coincide (two ids, one place)
    repeated = polydata_of(with_z(np.vstack([points, points[:1]])), [list(range(n + 1))])
    from_coincident = read_curve(write_polydata(tmp_path / "coincident.vtk", repeated))
    np.testing.assert_allclose(from_vtk, points, atol=1e-12)
    same_curve(from_vtp, points)
    np.testing.assert_allclose(from_coincident, points, atol=1e-12)


def test_a_png_label_image_gives_the_outline_of_its_region(tmp_path):
    mask = disc_mask()
    mask[20, 24] = 0                                            # a hole: filled
    sitk.WriteImage(sitk.GetImageFromArray(mask * 255), str(tmp_path / "disc.png"))
    curve = read_curve(tmp_path / "disc.png")
    assert signed_area(curve) > 0
    # the same mask saved as a grey picture in colour (RGB) reads alike
    grey = np.repeat((mask * 255)[..., None], 3, axis=2)
    sitk.WriteImage(sitk.GetImageFromArray(grey, isVector=True), str(tmp_path / "grey.png"))
    np.testing.assert_array_equal(read_curve(tmp_path / "grey.png"), curve)
    # pixel coordinates: x along columns, y along rows; the sub-pixel outline of a disc of radius
    # 12 pixels lies near radius 12 from its centre
    radii = np.linalg.norm(curve - [24.0, 20.0], axis=1)
    assert np.all(np.abs(radii - 12.0) < 0.8)
    assert abs(np.sqrt(signed_area(curve) / np.pi) - 12.0) < 0.5


def test_a_one_slice_volume_gives_its_outline_in_physical_coordinates(tmp_path):
    mask = np.zeros((1, 40, 50), dtype=np.uint8)
    mask[0] = disc_mask() * 3
    mask[0, :3, :3] = 5                                         # another label, not selected
    image = sitk.GetImageFromArray(mask)
    image.SetSpacing((0.5, 0.25, 2.0))
    image.SetOrigin((10.0, -20.0, 4.0))
    sitk.WriteImage(image, str(tmp_path / "slice.nii.gz"))
    curve = read_curve(tmp_path / "slice.nii.gz", labels=[3])
    # the disc of radius 12 pixels becomes an ellipse of semi-axes 6 (x) and 3 (y) mm
    centre = np.array([10.0 + 24 * 0.5, -20.0 + 20 * 0.25])
    offsets = (curve - centre) / [6.0, 3.0]
    assert np.all(np.abs(np.linalg.norm(offsets, axis=1) - 1.0) < 0.1)
    assert abs(signed_area(curve) - np.pi * 18.0) < 0.08 * np.pi * 18.0


@pytest.mark.skipif(not HANDS, reason=f"shared hands not found at {DATA / 'hands2d'}")
def test_the_shared_hands_read_as_clean_closed_curves():
    for path in HANDS:
        notes = []
        curve = read_curve(path, notes=notes)
        # their outlines have a few sub-pixel twists, cut out as small loops
        assert 1500 <= len(curve) <= 1590
        assert signed_area(curve) > 0
        assert find_crossing(curve) is None
        assert is_curve_file(path)
        assert notes == [] if len(curve) == 1590 else notes[0].endswith(
            "cut where the curve crossed itself")


# ------------------------------------------------------------------------------------------------
# Rejections: one line naming the problem


def rejection(path, *args) -> str:
    with pytest.raises(InputError) as error:
        read_curve(path, *args)
    message = str(error.value)
    assert "\n" not in message
    return message


def test_open_curves_are_rejected_with_the_gap_between_their_ends(tmp_path):
    arc = ellipse(n=40)[:30]                                    # three quarters of an ellipse
    assert rejection(write_table(tmp_path / "arc.csv", arc)).startswith(
        "the curve is open: its ends are ")
    polyline = polydata_of(with_z(arc), [list(range(len(arc)))])
    message = rejection(write_polydata(tmp_path / "arc.vtk", polyline))
    gap = np.linalg.norm(arc[-1] - arc[0])
    assert message == f"the curve is open: its ends are {gap:.4g} mm apart"


def test_a_curve_that_crosses_itself_is_rejected_near_the_crossing(tmp_path):
    t = 2 * np.pi * np.arange(80) / 80
    figure_eight = np.stack([10 * np.sin(t), 10 * np.sin(t) * np.cos(t) + 0.5 * np.cos(t)], 1)
    figure_eight[:, 1] += 0.3 * np.sin(3 * t)                   # not symmetric: some area
    message = rejection(write_table(tmp_path / "eight.csv", figure_eight))
    assert message.startswith("the curve crosses itself near (")
    x, y = (float(v) for v in message[message.index("(") + 1:-1].split(","))
    assert np.hypot(x, y) < 1.5                                 # the crossing is near (0, 0)


def test_bad_tables_are_rejected_with_one_line(tmp_path):
    square = [(0, 0), (1, 0), (1, 1), (0, 1)]
    assert rejection(write_table(tmp_path / "few.csv", square)) == \
        "the curve has 4 points; a curve needs at least 8"
    points = ellipse(n=20)
    points[5, 0] = np.nan
    assert rejection(write_table(tmp_path / "nan.csv", points)) == \
        "the curve has non-finite (NaN or infinite) coordinates"
    line = np.stack([np.arange(10.0), np.zeros(10)], 1)
    there_and_back = np.concatenate([line, line[-2:0:-1]])
    assert rejection(write_table(tmp_path / "flat.csv", there_and_back)) == \
        "the curve encloses no area (its points are collinear)"
    varying = np.column_stack([ellipse(n=20), np.linspace(0, 1, 20)])
    assert rejection(write_table(tmp_path / "z.csv", varying, header="x,y,z")).startswith(
        "the curve is not planar: z varies by 1 mm")
    text = (tmp_path / "text.csv")
    text.write_text("x,y\n1,2\n3,4\nfive,6\n")
    assert rejection(text) == "line 4 is not numbers: 'five,6'"
    wide = tmp_path / "wide.csv"
    wide.write_text("1 2 3 4\n")
    assert rejection(wide) == "line 1 has 4 values; expected x y (or x y z)"


def test_bad_polydata_is_rejected_with_one_line(tmp_path):
    points = with_z(ellipse(n=20))
    tilted = points.copy()
    tilted[:, 2] = np.linspace(0, 3, 20)
    assert rejection(write_polydata(tmp_path / "tilted.vtp",
                                    polydata_of(tilted, [list(range(20)) + [0]]))).startswith(
        "the curve is not planar")
    mesh = polydata_of(points, None, polygons=[[0, 1, 2], [0, 2, 3]])
    assert rejection(write_polydata(tmp_path / "mesh.vtk", mesh)) == \
        "the mesh has polygons; a 2-D curve file holds a closed polyline"
    branch = polydata_of(points, [list(range(20)) + [0], [5, 12]])
    assert rejection(write_polydata(tmp_path / "branch.vtk", branch)).startswith(
        "the lines branch at (")
    pieces = polydata_of(points, [list(range(8)), list(range(10, 18))])
    assert rejection(write_polydata(tmp_path / "pieces.vtk", pieces)) == \
        "the lines form 2 open pieces; a curve is one closed chain"
    two = polydata_of(np.vstack([points, points + [100, 0, 0]]),
                      [list(range(20)) + [0], list(range(20, 40)) + [20]])
    assert rejection(write_polydata(tmp_path / "two.vtp", two)) == \
        "2 separate curves; a 2-D curve file must hold one closed curve"


def test_bad_label_images_are_rejected_with_one_line(tmp_path):
    mask = disc_mask(radius=8)
    mask[:, 40:46] = 1                                          # a second region, apart
    sitk.WriteImage(sitk.GetImageFromArray(mask * 255), str(tmp_path / "two.png"))
    message = rejection(tmp_path / "two.png")
    assert message.startswith("2 separate regions (")
    assert message.endswith("pixels); a 2-D label image must hold one region")
    volume = sitk.GetImageFromArray(np.stack([disc_mask()] * 3))
    sitk.WriteImage(volume, str(tmp_path / "volume.nii.gz"))
    assert rejection(tmp_path / "volume.nii.gz") == \
        "a 3-D image (50 x 40 x 3); a 2-D label image has one slice"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((20, 20), np.uint8)),
                    str(tmp_path / "empty.png"))
    assert rejection(tmp_path / "empty.png") == "the label map is empty (no non-zero voxels)"
    assert rejection(tmp_path / "missing.png") == "no such file"
    colour = np.zeros((40, 50, 3), np.uint8)
    colour[..., 0] = disc_mask() * 255
    sitk.WriteImage(sitk.GetImageFromArray(colour, isVector=True), str(tmp_path / "red.png"))
    assert rejection(tmp_path / "red.png") == \
        "a colour image (3 values per pixel); a 2-D label image has one value per pixel"
    (tmp_path / "garbage.png").write_bytes(b"\x89PNG not really" * 10)
    assert rejection(tmp_path / "garbage.png").startswith("not a readable image")
    (tmp_path / "garbage.vtk").write_bytes(b"# vtk DataFile Version 3.0\nnothing\n")
    assert rejection(tmp_path / "garbage.vtk").startswith("not a readable mesh")


# ------------------------------------------------------------------------------------------------
# Deciding whether a file is a curve


def test_is_curve_file_tells_curves_from_meshes_and_volumes(tmp_path):
    points = with_z(ellipse(n=20))
    assert is_curve_file(write_table(tmp_path / "c.csv", points[:, :2]))
    assert is_curve_file(write_polydata(tmp_path / "c.vtk",
                                        polydata_of(points, [list(range(20)) + [0]])))
    assert is_curve_file(write_polydata(tmp_path / "c.vtp",
                                        polydata_of(points, [list(range(20)) + [0]])))
    mesh = polydata_of(points, None, polygons=[[0, 1, 2], [0, 2, 3]])
    assert not is_curve_file(write_polydata(tmp_path / "m.vtk", mesh))
    assert not is_curve_file(write_polydata(tmp_path / "m.vtp", mesh))
    sitk.WriteImage(sitk.GetImageFromArray(disc_mask()), str(tmp_path / "d.png"))
    assert is_curve_file(tmp_path / "d.png")
    sitk.WriteImage(sitk.GetImageFromArray(disc_mask()[None]), str(tmp_path / "s.nrrd"))
    assert is_curve_file(tmp_path / "s.nrrd")
    sitk.WriteImage(sitk.GetImageFromArray(np.stack([disc_mask()] * 3)),
                    str(tmp_path / "v.nii.gz"))
    assert not is_curve_file(tmp_path / "v.nii.gz")
    assert not is_curve_file(tmp_path / "missing.vtk")
    assert not is_curve_file(tmp_path / "surface.stl")


# ------------------------------------------------------------------------------------------------
# Crossings, parameterization, origins, weights


def test_crossings_are_found_among_ten_thousand_points():
    t = 2 * np.pi * np.arange(10_000) / 10_000
    radius = 1 + 0.3 * np.cos(5 * t)
    star = np.stack([radius * np.cos(t), radius * np.sin(t)], axis=1)
    assert find_crossing(star) is None
    swapped = star.copy()
    swapped[[4000, 4001]] = swapped[[4001, 4000]]
    i, j, (x, y) = find_crossing(swapped)
    assert 3998 <= i < j <= 4002
    assert np.hypot(x - star[4000, 0], y - star[4000, 1]) < 1e-3


def test_crossings_are_found_with_a_few_long_segments_among_many_short_ones():
    # a D: a dense half circle closed by one long diagonal segment (it alone would cover some
    # 10^7 cells of the short segments' size)
    t = np.linspace(0, np.pi, 10_000)
    half_disc = np.stack([np.cos(t), np.sin(t)], axis=1) @ np.array([[1, -1], [1, 1]]) / np.sqrt(2)
    assert find_crossing(half_disc) is None
    crossed = half_disc.copy()
    crossed[5000] = -crossed[5000]                              # a spike across the diagonal
    assert find_crossing(crossed) is not None


def test_small_loops_are_cut_out_and_large_ones_rejected():
    points = ellipse(n=200)
    twisted = points.copy()
    twisted[[50, 51]] = twisted[[51, 50]]                       # a tiny twist: cut out
    cleaned = check_curve(twisted)
    assert find_crossing(cleaned) is None and len(cleaned) >= 198
    with pytest.raises(InputError, match="crosses itself"):
        check_curve(twisted, max_loop=0.0)


def test_curve_map_is_the_arc_length_parameterization():
    points = ellipse(n=50)
    mapped = curve_map(points)
    assert mapped.parameter[0] == 0.0
    assert np.all(np.diff(mapped.parameter) > 0) and mapped.parameter[-1] < 2 * np.pi
    assert mapped.length == pytest.approx(segment_lengths(points).sum())
    np.testing.assert_allclose(point_at(mapped, mapped.parameter), points, atol=1e-12)
    # equal parameter steps are equal arc-length steps
    resampled = resample_curve(points, 400, start=0.3)
    steps = segment_lengths(resampled)
    assert np.ptp(steps[np.abs(steps - np.median(steps)) < 0.5 * np.median(steps)]) < \
        0.3 * np.median(steps)


def test_origins_of_a_rotated_and_restarted_population_are_aligned():
    base = ellipse(n=300, a=20, b=8)
    base[:, 1] += 4 * np.maximum(0, np.cos(np.linspace(0, 2 * np.pi, 300, endpoint=False))) ** 8
    rng = np.random.default_rng(0)
    maps, transforms = [], []
    for _ in range(5):
        angle, scale, shift = rng.uniform(-0.5, 0.5), rng.uniform(0.8, 1.2), rng.normal(size=2)
        rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        maps.append(curve_map(resample_curve(base, 200, rng.random()) @ rotation.T * scale + shift))
        transforms.append((rotation, scale, shift))
    aligned = align_curve_origins(maps)
    # every origin, taken back to the base's frame, is the same point of the base
    origins = np.array([((m.points[0] - shift) / scale) @ rotation
                        for m, (rotation, scale, shift) in zip(aligned, transforms)])
    spacing = curve_map(base).length / 200
    assert np.max(np.linalg.norm(origins - origins.mean(axis=0), axis=1)) < spacing
    for m, original in zip(aligned, maps):                     # the same curves, restarted
        assert m.length == pytest.approx(original.length, rel=1e-12)
        assert find_crossing(m.points) is None


def test_segment_weights_are_half_the_neighbouring_segment_lengths():
    points = with_z(ellipse(n=12))
    k = np.arange(12)
    segments = np.stack([k, (k + 1) % 12], axis=1)
    lengths = segment_lengths(points[:, :2])
    expected = 0.5 * (lengths + np.roll(lengths, 1))
    np.testing.assert_allclose(segment_vertex_lengths(points, segments), expected, rtol=1e-14)
