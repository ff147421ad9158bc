"""Offscreen VTK pictures for the report: real rendering (EGL/OSMesa), decoded PNGs, no mocks.

Every rendering test is skipped when this machine has no offscreen OpenGL at all; the two
subprocess tests check that rendering without a display is quiet and that a machine without a
working OpenGL driver gets a RenderingError (not a crash).
"""

import io
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from mdlshapemodel.report import rendering
from mdlshapemodel.errors import MDLShapeModelError
from mdlshapemodel.model.shape_model import ShapeModel
from mdlshapemodel.report.rendering import RenderingError, grid_layout
from mdlshapemodel.correspondence.sampling import sphere_grid
from mdlshapemodel.prepare.surface import triangle_vertex_areas

PACKAGE_ROOT = str(Path(rendering.__file__).resolve().parents[1])
SIZE = (160, 140)


@pytest.fixture(scope="module")
def offscreen():
    """The offscreen window class, or skip the test when this machine cannot render."""
    try:
        return rendering.offscreen_window_class()
    except RenderingError as error:
        pytest.skip(str(error))


def decode(png: bytes) -> np.ndarray:
    """(h, w, 3) uint8 image of PNG bytes."""
    import matplotlib.image

    image = matplotlib.image.imread(io.BytesIO(png), format="png")
    if image.dtype != np.uint8:
        image = np.round(image * 255).astype(np.uint8)
    return image[:, :, :3]


def foreground(panel: np.ndarray) -> np.ndarray:
    """Pixels that are not the white background."""
    return np.any(panel < 240, axis=2)


def extent(mask: np.ndarray, axis: int) -> int:
    """Width (axis=1) or height (axis=0) in pixels of the foreground."""
    occupied = np.flatnonzero(mask.any(axis=1 - axis))
    return int(occupied[-1] - occupied[0] + 1) if len(occupied) else 0


def ellipsoids(semi_axes):
    grid, triangles = sphere_grid(642)
    return np.array([grid * np.asarray(a, float) for a in semi_axes]), triangles


@pytest.fixture(scope="module")
def two_mode_model():
    """Ellipsoids whose x semi-axis (10 +- 3) and y semi-axis (6 +- 1) vary independently: mode 1
    is the x length, mode 2 the y length; z (4) is the smallest axis, the viewing direction."""
    shapes, triangles = ellipsoids([(13, 6, 4), (7, 6, 4), (10, 7, 4), (10, 5, 4)])
    weights = triangle_vertex_areas(shapes.mean(axis=0), triangles)
    model = ShapeModel.from_shapes(shapes, weights / weights.sum(), triangles=triangles)
    assert model.n_modes == 2
    return model


def signed_extent_change(model, mode, axis):
    """Extent along ``axis`` of the +2 SD shape minus that of the -2 SD shape."""
    sd = np.sqrt(model.variances[mode])
    scores = np.zeros(mode + 1)
    scores[mode] = 2 * sd
    plus, minus = model.instance(scores), model.instance(-scores)
    return np.ptp(plus[:, axis]) - np.ptp(minus[:, axis])


def test_modes_picture_has_the_grid_size_and_no_blank_panel(offscreen, two_mode_model):
    png = rendering.render_modes(two_mode_model, n_modes=3, size=SIZE)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    image = decode(png)
    layout = grid_layout("modes", 2, 3, SIZE)          # the model has 2 modes, not 3
    assert image.shape == (layout.height, layout.width, 3)
    for row in range(2):
        for col in range(3):
            assert foreground(image[layout.panel(row, col)]).mean() > 0.05, (row, col)
    # the colour bar right of the panels shows both ends of the diverging map
    bar = image[layout.top:layout.top + 2 * SIZE[1], layout.left + 3 * SIZE[0]:]
    red = (bar[..., 0].astype(int) - bar[..., 2] > 80).sum()
    blue = (bar[..., 2].astype(int) - bar[..., 0] > 80).sum()
    assert red > 50 and blue > 50
    # labels in the margins
    assert foreground(image[:layout.top, layout.left:layout.left + 3 * SIZE[0]]).any()
    assert foreground(image[layout.top:layout.top + 2 * SIZE[1], :layout.left]).any()


def test_modes_show_the_variation_in_the_expected_direction(offscreen, two_mode_model):
    model = two_mode_model
    layout = grid_layout("modes", 2, 3, SIZE)
    image = decode(rendering.render_modes(model, size=SIZE))
    panels = [[image[layout.panel(r, c)] for c in range(3)] for r in range(2)]
    raw, row_labels, column_labels, half_range = rendering.mode_panels(model, size=SIZE)
    assert column_labels == ["-2 SD", "mean", "+2 SD"]
    assert row_labels[0].startswith("mode 1") and row_labels[1].startswith("mode 2")
    # the tips of the x axis move most: 2 SD of the x semi-axis (3, -3, 0, 0)
    assert half_range == pytest.approx(2 * np.sqrt(4.5), rel=0.02)
    for r in range(2):
        for c in range(3):                               # the PNG holds the renderings exactly
            np.testing.assert_array_equal(panels[r][c], raw[r][c])
    # the 0 SD column is the mean in every row: the same picture, uncoloured (grey)
    np.testing.assert_array_equal(panels[0][1], panels[1][1])
    mean_pixels = panels[0][1][foreground(panels[0][1])].astype(int)
    assert np.abs(mean_pixels[:, 0] - mean_pixels[:, 2]).max() <= 3
    for r in range(2):
        difference = np.abs(panels[r][0].astype(int) - panels[r][2]).max(axis=2)
        assert (difference > 30).mean() > 0.05
    # mode 1 changes the width (x, horizontal on screen), mode 2 the height (y, vertical)
    for row, axis, pixel_axis in ((0, 0, 1), (1, 1, 0)):
        change = signed_extent_change(model, row, axis)
        sizes = [extent(foreground(p), pixel_axis) for p in panels[row]]
        assert abs(change) > 1.0
        if change > 0:
            assert sizes[0] < sizes[1] < sizes[2], sizes
        else:
            assert sizes[0] > sizes[1] > sizes[2], sizes
    # the other extent stays (mode 1 does not change the height)
    heights = [extent(foreground(p), 0) for p in panels[0]]
    assert max(heights) - min(heights) <= 3
    # colour: the ends of the longer shape moved outwards (red), of the shorter inwards (blue)
    longer, shorter = (panels[0][2], panels[0][0]) if signed_extent_change(model, 0, 0) > 0 \
        else (panels[0][0], panels[0][2])
    for panel, outwards in ((longer, True), (shorter, False)):
        mask = foreground(panel)
        columns = np.flatnonzero(mask.any(axis=0))
        middle_row = panel[SIZE[1] // 2].astype(int)
        for x in (columns[0] + 4, columns[-1] - 4):       # left and right end, near the silhouette
            red_minus_blue = middle_row[x, 0] - middle_row[x, 2]
            assert (red_minus_blue > 20) if outwards else (red_minus_blue < -20), (x, middle_row[x])


def test_modes_of_a_model_without_variation_show_the_mean(offscreen):
    shapes, triangles = ellipsoids([(10, 6, 4)])
    n_p = shapes.shape[1]
    model = ShapeModel(mean=shapes[0], modes=np.zeros((0, n_p, 3)), variances=np.zeros(0),
                       weights=np.full(n_p, 1.0 / n_p), scores=np.zeros((3, 0)),
                       triangles=triangles)
    image = decode(rendering.render_modes(model, size=SIZE))
    layout = grid_layout("modes", 1, 1, SIZE)
    assert image.shape[:2] == (layout.height, layout.width)
    assert foreground(image[layout.panel(0, 0)]).mean() > 0.05


def test_modes_need_triangles(two_mode_model):
    model = ShapeModel(mean=two_mode_model.mean, modes=two_mode_model.modes,
                       variances=two_mode_model.variances, weights=two_mode_model.weights,
                       scores=two_mode_model.scores)
    with pytest.raises(ValueError, match="triangles"):
        rendering.render_modes(model)


def rotated_about_y(points):
    """The same ellipsoid surface, but every point moved to the opposite side (x, z negated)."""
    return points * np.array([-1.0, 1.0, -1.0])


def test_correspondence_colours_follow_the_point_index(offscreen):
    shapes, triangles = ellipsoids([(10, 6, 4)])
    base = shapes[0]
    moved = 1.7 * base + np.array([30.0, -5.0, 12.0])   # same correspondence, other pose and size
    flipped = rotated_about_y(base)                     # same surface, other correspondence
    png = rendering.render_correspondence(np.stack([base, moved, flipped]), triangles,
                                          names=["base", "moved", "flipped"], size=SIZE)
    image = decode(png)
    layout = grid_layout("correspondence", 1, 3, SIZE)
    assert image.shape == (layout.height, layout.width, 3)
    base_panel, moved_panel, flipped_panel = (image[layout.panel(0, c)] for c in range(3))
    for panel in (base_panel, moved_panel, flipped_panel):
        assert foreground(panel).mean() > 0.1
    # the translated and scaled copy, fitted by its own camera, looks the same
    same = np.abs(base_panel.astype(int) - moved_panel).max(axis=2)
    assert np.mean(same > 24) < 0.01
    # the flipped copy has the same silhouette but not the same colours
    a, b = foreground(base_panel), foreground(flipped_panel)
    assert (a & b).sum() / (a | b).sum() > 0.97
    both = a & b
    differ = np.abs(base_panel.astype(int) - flipped_panel).max(axis=2)[both]
    assert np.mean(differ > 40) > 0.3
    # colours vary over the surface (a pattern, not one colour)
    assert len(np.unique(base_panel[a] // 32, axis=0)) > 10


def test_correspondence_pattern_is_defined_on_the_point_index():
    shapes, _ = ellipsoids([(10, 6, 4)])
    colours = rendering.correspondence_pattern(shapes[0])
    assert colours.shape == (shapes.shape[1], 3) and colours.dtype == np.uint8
    # invariant to pose and scale of the reference: a property of the points, not the placement
    np.testing.assert_array_equal(colours, rendering.correspondence_pattern(
        2.5 * shapes[0] + np.array([4.0, 5.0, 6.0])))
    # hue runs along the long axis: the two ends differ
    ends = colours[[np.argmin(shapes[0][:, 0]), np.argmax(shapes[0][:, 0])]].astype(int)
    assert np.abs(ends[0] - ends[1]).max() > 80


def test_max_cases_limits_the_panels(offscreen):
    shapes, triangles = ellipsoids([(10 + k, 6, 4) for k in range(6)])
    names = [f"case {k}" for k in range(6)]
    for max_cases, expected in ((4, 4), (2, 2), (10, 6)):
        image = decode(rendering.render_correspondence(shapes, triangles, names,
                                                       max_cases=max_cases, size=SIZE))
        layout = grid_layout("correspondence", 1, expected, SIZE)
        assert image.shape[:2] == (layout.height, layout.width)
        for c in range(expected):
            assert foreground(image[layout.panel(0, c)]).mean() > 0.05
    panels, indices = rendering.correspondence_panels(shapes, triangles, max_cases=4, size=SIZE)
    assert list(indices) == [0, 2, 3, 5] and len(panels) == 4      # spread, ends included


def test_correspondence_rejects_bad_inputs():
    shapes, triangles = ellipsoids([(10, 6, 4), (11, 6, 4)])
    with pytest.raises(ValueError, match="shapes"):
        rendering.render_correspondence(shapes[0], triangles)
    with pytest.raises(ValueError, match="triangles"):
        rendering.render_correspondence(shapes, triangles + len(shapes[0]))
    with pytest.raises(ValueError, match="names"):
        rendering.render_correspondence(shapes, triangles, names=["only one"])
    with pytest.raises(ValueError, match="max_cases"):
        rendering.render_correspondence(shapes, triangles, max_cases=0)


def test_vertex_normals_point_outwards_whatever_the_orientation():
    grid, triangles = sphere_grid(162)
    for faces in (triangles, triangles[:, ::-1]):
        normals = rendering.vertex_normals(grid * 3.0, faces)
        assert np.einsum("kd,kd->k", normals, grid).min() > 0.95


def run_without_display(code: str, **environment) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items()
           if k not in ("DISPLAY", "WAYLAND_DISPLAY", "VTK_DEFAULT_OPENGL_WINDOW")}
    env["PYTHONPATH"] = os.pathsep.join([PACKAGE_ROOT, env.get("PYTHONPATH", "")])
    env.update(environment)
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env,
                          capture_output=True, text=True, timeout=120)


PROGRAM = """
    import numpy as np
    from mdlshapemodel.report import rendering
    from mdlshapemodel.errors import MDLShapeModelError
    from mdlshapemodel.correspondence.sampling import sphere_grid
    grid, triangles = sphere_grid(162)
    try:
        png = rendering.render_correspondence(np.stack([grid, 2 * grid]), triangles)
    except rendering.RenderingError as error:
        print("RenderingError", isinstance(error, MDLShapeModelError), error)
    else:
        print("rendered", rendering.offscreen_window_class().__name__, len(png))
"""


def test_rendering_without_display_is_offscreen_and_quiet(offscreen):
    result = run_without_display(PROGRAM)
    assert result.returncode == 0, result.stderr
    words = result.stdout.split()
    assert words[0] == "rendered" and words[1] != "vtkXOpenGLRenderWindow"
    assert int(words[2]) > 1000
    assert "X server" not in result.stderr and "WARN" not in result.stderr
    assert result.stderr.strip() == ""


def test_missing_opengl_driver_raises_rendering_error():
    """glvnd's libEGL with no vendor library: EGL cannot make a context (a real broken driver
    setup, no mock). VTK would crash when rendering; we get a RenderingError instead."""
    result = run_without_display(PROGRAM, __EGL_VENDOR_LIBRARY_FILENAMES="/nonexistent.json")
    assert result.returncode == 0, result.stderr             # no segmentation fault
    if result.stdout.startswith("rendered"):
        pytest.skip("OpenGL still works here without EGL vendors (OSMesa or non-glvnd EGL): "
                    + result.stdout.strip())
    assert result.stdout.startswith("RenderingError True offscreen OpenGL rendering is not "
                                    "available"), result.stdout
    assert "WARN" not in result.stderr


def test_rendering_error_is_a_package_error():
    assert issubclass(RenderingError, MDLShapeModelError)
