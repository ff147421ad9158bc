"""Headless (offscreen) VTK pictures of a shape model for report.html.

* :func:`render_modes`: modes of variation at -2, 0, +2 standard deviations (Davies et al. 2010,
  Fig. 12-15), coloured by the signed displacement from the mean along the mean's normals.
* :func:`render_correspondence`: corresponded meshes painted with one pattern defined on the point
  index (Fig. 22-23), so corresponding regions have the same colour on every case.

Both take numpy arrays and return PNG bytes (ready to base64-embed). The panels are rendered in one
offscreen render window and composed with matplotlib (labels, colour bar) at an exact pixel size,
see :func:`grid_layout`.

Offscreen OpenGL: on Linux the EGL window (then OSMesa, then X when ``DISPLAY`` is set) is created
directly, after checking that it can make an OpenGL context, so VTK's default factory never tries
X without a display (which prints "bad X server connection"). ``VTK_DEFAULT_OPENGL_WINDOW`` set by
the user is honoured. Elsewhere the platform's window renders offscreen. When none works,
:class:`RenderingError` is raised: catch it to leave the pictures out.
"""

from __future__ import annotations

import ctypes.util
import os
import sys
from dataclasses import dataclass

import numpy as np

from ..errors import ArgumentError, MDLShapeModelError
from ..prepare.io import captured_vtk_messages
from ..prepare.surface import arrays_to_polydata, signed_volume

BACKGROUND = (1.0, 1.0, 1.0)
DISPLACEMENT_COLORMAP = "coolwarm"      # diverging (Moreland), light grey at 0
_DPI = 100
_FONT_PX = 14


class RenderingError(MDLShapeModelError):
    """Offscreen OpenGL rendering is not available on this machine."""


# ---------------------------------------------------------------------------------------------
# the offscreen window


_window_class_cache: list = []


def _window_candidates() -> list[tuple[str, str]]:
    """(VTK class name, why it may work) in order of preference for this machine."""
    if os.environ.get("VTK_DEFAULT_OPENGL_WINDOW"):
        return [("vtkRenderWindow", "VTK_DEFAULT_OPENGL_WINDOW")]
    if not sys.platform.startswith("linux"):
        return [("vtkRenderWindow", "native offscreen")]   # WGL / Cocoa render offscreen
    candidates = []
    if ctypes.util.find_library("EGL"):
        candidates.append(("vtkEGLRenderWindow", "EGL"))
    if ctypes.util.find_library("OSMesa"):             # VTK crashes when it is missing
        candidates.append(("vtkOSOpenGLRenderWindow", "OSMesa"))
    if os.environ.get("DISPLAY"):
        candidates.append(("vtkXOpenGLRenderWindow", "X display"))
    return candidates


def offscreen_window_class():
    """The VTK render-window class that renders offscreen here (checked once per process).

    Raises :class:`RenderingError` naming what was tried when none can create an OpenGL context.
    """
    if _window_class_cache:
        if isinstance(_window_class_cache[0], RenderingError):
            raise _window_class_cache[0]
        return _window_class_cache[0]
    import vtk

    tried = []
    result = None
    for name, reason in _window_candidates():
        window_class = getattr(vtk, name, None)
        if window_class is None:
            tried.append(f"{reason}: not in this VTK build")
            continue
        with captured_vtk_messages() as messages:
            window = window_class()
            window.SetOffScreenRendering(1)
            supported = bool(window.SupportsOpenGL())
            text = messages().strip()
        del window
        if supported:
            result = window_class
            break
        detail = next((line.strip() for line in reversed(text.splitlines()) if line.strip()), "")
        tried.append(f"{reason}: no OpenGL context" + (f" ({detail[:100]})" if detail else ""))
    if result is None:
        tried = tried or ["no EGL or OSMesa library and no DISPLAY"]
        result = RenderingError("offscreen OpenGL rendering is not available ("
                                + "; ".join(tried) + ")")
    _window_class_cache.append(result)
    return offscreen_window_class()


class _PanelRenderer:
    """One offscreen window, renderer and actor; renders a mesh with given points and colours."""

    def __init__(self, triangles: np.ndarray, n_points: int, size: tuple[int, int]):
        window_class = offscreen_window_class()
        self.size = (int(size[0]), int(size[1]))
        self._messages = captured_vtk_messages()      # quiet while the window exists
        self._messages.__enter__()
        try:
            self._build(window_class, triangles, n_points)
        except BaseException:
            self._messages.__exit__(None, None, None)
            raise

    def _build(self, window_class, triangles, n_points):
        import vtk

        self.window = window_class()
        self.window.SetOffScreenRendering(1)
        self.window.SetSize(*self.size)
        self.window.SetMultiSamples(0)
        self.renderer = vtk.vtkRenderer()
        self.renderer.SetBackground(*BACKGROUND)
        self.renderer.UseFXAAOn()
        self.window.AddRenderer(self.renderer)
        self.polydata = arrays_to_polydata(np.zeros((n_points, 3)), triangles)
        mapper = vtk.vtkPolyDataMapper()
        mapper.SetInputData(self.polydata)
        mapper.SetColorModeToDirectScalars()
        mapper.SetScalarModeToUsePointData()
        mapper.ScalarVisibilityOn()
        actor = vtk.vtkActor()
        actor.SetMapper(mapper)
        prop = actor.GetProperty()
        prop.SetInterpolationToGouraud()
        prop.SetAmbient(0.15)
        prop.SetDiffuse(0.8)
        prop.SetSpecular(0.15)
        prop.SetSpecularPower(20)
        self.renderer.AddActor(actor)
        self.camera = self.renderer.GetActiveCamera()
        self.camera.ParallelProjectionOn()
        self.grabber = vtk.vtkWindowToImageFilter()
        self.grabber.SetInput(self.window)
        self.grabber.SetInputBufferTypeToRGB()
        self.grabber.ReadFrontBufferOff()
        self.grabber.ShouldRerenderOff()

    def render(self, points: np.ndarray, normals: np.ndarray, colours: np.ndarray,
               view: "_View") -> np.ndarray:
        """(h, w, 3) uint8 image, top row first."""
        from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy

        self.polydata.GetPoints().SetData(numpy_to_vtk(np.ascontiguousarray(points, float),
                                                       deep=True))
        point_data = self.polydata.GetPointData()
        normal_array = numpy_to_vtk(np.ascontiguousarray(normals, np.float32), deep=True)
        normal_array.SetName("Normals")
        point_data.SetNormals(normal_array)
        colour_array = numpy_to_vtk(np.ascontiguousarray(colours, np.uint8), deep=True)
        colour_array.SetName("Colours")
        point_data.SetScalars(colour_array)
        self.polydata.Modified()
        self.camera.SetFocalPoint(*view.focal)
        self.camera.SetPosition(*(view.focal + view.axes[2] * view.distance))
        self.camera.SetViewUp(*view.axes[1])
        self.camera.SetParallelScale(view.parallel_scale)
        self.renderer.ResetCameraClippingRange(view.bounds)
        self.window.Render()
        self.grabber.Modified()
        self.grabber.Update()
        image = self.grabber.GetOutput()
        width, height = image.GetDimensions()[:2]
        array = vtk_to_numpy(image.GetPointData().GetScalars()).reshape(height, width, -1)
        return np.ascontiguousarray(array[::-1, :, :3])

    def close(self):
        self.renderer.RemoveAllViewProps()
        self.window.RemoveRenderer(self.renderer)
        self.window.Finalize()
        del self.grabber, self.renderer, self.window, self.camera
        self._messages.__exit__(None, None, None)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# ---------------------------------------------------------------------------------------------
# geometry: axes, normals, cameras


def principal_axes(points: np.ndarray, weights: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Centre and principal axes (rows: largest, middle, smallest extent) of a point set.

    Signs are fixed (largest component of the first two axes positive, right-handed), so the
    same shape always gets the same view.
    """
    points = np.asarray(points, dtype=np.float64)
    w = np.full(len(points), 1.0 / len(points)) if weights is None else \
        np.asarray(weights, float) / np.sum(weights)
    centre = w @ points
    centred = points - centre
    covariance = (centred * w[:, None]).T @ centred
    values, vectors = np.linalg.eigh(covariance)
    axes = vectors[:, ::-1].T.copy()
    for k in (0, 1):
        axes[k] *= np.sign(axes[k][np.argmax(np.abs(axes[k]))])
    axes[2] = np.cross(axes[0], axes[1])
    return centre, axes


def vertex_normals(points: np.ndarray, triangles: np.ndarray, outwards: bool = True
                   ) -> np.ndarray:
    """Unit area-weighted vertex normals; pointing out of the enclosed volume when ``outwards``
    (whatever the triangles' orientation)."""
    points = np.asarray(points, dtype=np.float64)
    a, b, c = (points[triangles[:, k]] for k in range(3))
    face = np.cross(b - a, c - a)
    normals = np.zeros_like(points)
    for k in range(3):
        for d in range(3):
            normals[:, d] += np.bincount(triangles[:, k], weights=face[:, d],
                                         minlength=len(points))
    if outwards and signed_volume(points, triangles) < 0:
        normals = -normals
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.where(length > 0, length, 1.0)


@dataclass
class _View:
    focal: np.ndarray
    axes: np.ndarray            # rows: screen right, screen up, towards the viewer
    parallel_scale: float
    distance: float
    bounds: tuple


def _fit_view(shapes, axes: np.ndarray, aspect: float, margin: float = 1.08) -> _View:
    """Parallel camera looking along -axes[2] (screen right axes[0], up axes[1]) that shows all
    ``shapes`` (iterable of (n, 3) arrays) with a small margin."""
    stacked = np.concatenate([np.asarray(s, float).reshape(-1, 3) for s in shapes])
    projected = stacked @ axes.T
    low, high = projected.min(axis=0), projected.max(axis=0)
    middle = 0.5 * (low + high)
    extent = np.maximum(high - low, 1e-9)
    half_height = 0.5 * max(extent[1], extent[0] / aspect) * margin
    radius = 0.5 * float(np.linalg.norm(extent))
    lo, hi = stacked.min(axis=0), stacked.max(axis=0)
    bounds = (lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])
    return _View(focal=middle @ axes, axes=axes, parallel_scale=half_height,
                 distance=2.0 * radius + 1.0, bounds=tuple(float(v) for v in bounds))


# ---------------------------------------------------------------------------------------------
# composition


@dataclass(frozen=True)
class GridLayout:
    """Pixel layout of a composed picture: margins around n_rows x n_cols panels."""

    n_rows: int
    n_cols: int
    panel_width: int
    panel_height: int
    left: int
    top: int
    right: int
    bottom: int

    @property
    def width(self) -> int:
        return self.left + self.n_cols * self.panel_width + self.right

    @property
    def height(self) -> int:
        return self.top + self.n_rows * self.panel_height + self.bottom

    def panel(self, row: int, col: int) -> tuple[slice, slice]:
        """Row and column slices of panel (row, col) in the (height, width) image."""
        y = self.top + row * self.panel_height
        x = self.left + col * self.panel_width
        return slice(y, y + self.panel_height), slice(x, x + self.panel_width)


def grid_layout(kind: str, n_rows: int, n_cols: int, size=(300, 260)) -> GridLayout:
    """The layout of :func:`render_modes` (``kind="modes"``) or :func:`render_correspondence`
    (``kind="correspondence"``) pictures."""
    width, height = int(size[0]), int(size[1])
    if kind == "modes":
        return GridLayout(n_rows, n_cols, width, height, left=46, top=28, right=100, bottom=6)
    if kind == "correspondence":
        return GridLayout(n_rows, n_cols, width, height, left=6, top=28, right=6, bottom=24)
    raise ArgumentError(f"unknown layout {kind!r}")


def _compose(layout: GridLayout, panels, column_labels=(), row_labels=(), caption=None,
             colorbar=None) -> bytes:
    """PNG of the panels (rows of (h, w, 3) uint8 arrays) placed exactly at ``layout.panel``,
    with labels and an optional colour bar ``(cmap, vmin, vmax, label)`` drawn by matplotlib."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    W, H = layout.width, layout.height
    figure = Figure(figsize=(W / _DPI, H / _DPI), dpi=_DPI, facecolor=BACKGROUND)
    canvas = FigureCanvasAgg(figure)
    points = _FONT_PX * 72.0 / _DPI

    def text(x_px, y_px, label, **kwargs):     # pixel coordinates from the top-left corner
        figure.text(x_px / W, 1.0 - y_px / H, label, ha="center", va="center",
                    fontsize=kwargs.pop("size", points), **kwargs)

    for c, label in enumerate(column_labels):
        columns = layout.panel(0, c)[1]
        text(0.5 * (columns.start + columns.stop), layout.top / 2, label)
    for r, label in enumerate(row_labels):
        rows = layout.panel(r, 0)[0]
        text(layout.left / 2, 0.5 * (rows.start + rows.stop), label, rotation=90,
             linespacing=1.3)
    if caption:
        text(W / 2, H - layout.bottom / 2, caption, size=points * 0.85, color="0.3")
    if colorbar is not None:
        cmap, vmin, vmax, label = colorbar
        x0 = layout.left + layout.n_cols * layout.panel_width + 14
        y0 = layout.top + 0.1 * layout.n_rows * layout.panel_height
        bar_height = 0.8 * layout.n_rows * layout.panel_height
        axis = figure.add_axes((x0 / W, 1.0 - (y0 + bar_height) / H, 14 / W, bar_height / H))
        bar = figure.colorbar(ScalarMappable(Normalize(vmin, vmax), cmap), cax=axis)
        bar.ax.tick_params(labelsize=points * 0.8)
        bar.set_label(label, fontsize=points * 0.85)
    canvas.draw()
    image = np.array(canvas.buffer_rgba(), dtype=np.uint8)[:, :, :3]
    if image.shape[:2] != (H, W):
        raise RuntimeError(f"matplotlib drew {image.shape[:2]} pixels instead of {(H, W)}")
    for r, row in enumerate(panels):
        for c, panel in enumerate(row):
            image[layout.panel(r, c)] = panel
    return encode_png(image)


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an (h, w, 3) uint8 image whose first row is the top."""
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy

    height, width, channels = image.shape
    data = vtk.vtkImageData()
    data.SetDimensions(width, height, 1)
    scalars = numpy_to_vtk(np.ascontiguousarray(image[::-1]).reshape(-1, channels), deep=True)
    data.GetPointData().SetScalars(scalars)
    writer = vtk.vtkPNGWriter()
    writer.SetInputData(data)
    writer.SetCompressionLevel(4)
    writer.WriteToMemoryOn()
    writer.Write()
    return vtk_to_numpy(writer.GetResult()).tobytes()


def _colormap(name: str):
    import matplotlib

    return matplotlib.colormaps[name]


def _to_uint8(rgba: np.ndarray) -> np.ndarray:
    return np.clip(np.round(np.asarray(rgba)[..., :3] * 255.0), 0, 255).astype(np.uint8)


# ---------------------------------------------------------------------------------------------
# modes of variation


def _sd_label(s: float) -> str:
    return "mean" if s == 0 else f"{s:+g} SD"


# The views of mode_panels and render_modes: the camera looks along the mean's smallest
# principal axis ("front"), its middle one ("top") or its largest one ("side").
MODE_VIEWS = ("front", "top", "side")


def _view_axes(axes: np.ndarray, view: str) -> np.ndarray:
    """Screen right, screen up and towards the viewer for one of :data:`MODE_VIEWS`."""
    if view == "front":
        return axes
    if view == "top":
        return np.array([axes[0], axes[2], -axes[1]])
    if view == "side":
        return np.array([axes[2], axes[1], -axes[0]])
    raise ArgumentError(f"view must be one of {', '.join(MODE_VIEWS)}, not {view!r}")


def mode_panels(model, n_modes: int = 3, standard_deviations=(-2, 0, 2), size=(300, 260),
                view: str = "front"):
    """The raw panels of :func:`render_modes`: (panels, row labels, column labels, range), with
    panels[r][c] the (h, w, 3) uint8 image of mean + s_c sqrt(lambda_r) mode_r and ``range`` the
    half-width (mm) of the symmetric displacement colour scale."""
    triangles = _checked_triangles(model.triangles, len(model.mean))
    mean = np.asarray(model.mean, dtype=np.float64)
    rows = max(0, min(int(n_modes), int(model.n_modes)))
    sds = [float(s) for s in standard_deviations]
    if not sds:
        raise ArgumentError("standard_deviations is empty")
    normals = vertex_normals(mean, triangles)
    if rows == 0:                       # no variation: show the mean alone
        shapes = [[mean]]
        row_labels = ["mean"]
        sds = [0.0]
    else:
        shapes = []
        for m in range(rows):
            sd = float(np.sqrt(max(model.variances[m], 0.0)))
            shapes.append([mean + s * sd * np.asarray(model.modes[m]) for s in sds])
        row_labels = [f"mode {m + 1}\n√λ = {np.sqrt(max(model.variances[m], 0)):.3g} mm"
                      for m in range(rows)]
    displacement = [[np.einsum("kd,kd->k", shape - mean, normals) for shape in row]
                    for row in shapes]
    half_range = max(float(np.max(np.abs(d))) for row in displacement for d in row)
    half_range = half_range if half_range > 0 else 1.0
    cmap = _colormap(DISPLACEMENT_COLORMAP)
    weights = getattr(model, "weights", None)
    _, axes = principal_axes(mean, weights if weights is not None and len(weights) == len(mean)
                             else None)
    view = _fit_view([s for row in shapes for s in row], _view_axes(axes, view),
                     size[0] / size[1])
    panels = []
    with _PanelRenderer(triangles, len(mean), size) as renderer:
        for shape_row, displacement_row in zip(shapes, displacement):
            panels.append([renderer.render(shape, vertex_normals(shape, triangles),
                                           _to_uint8(cmap(0.5 + 0.5 * d / half_range)), view)
                           for shape, d in zip(shape_row, displacement_row)])
    return panels, row_labels, [_sd_label(s) for s in sds], half_range


def render_modes(model, n_modes: int = 3, standard_deviations=(-2, 0, 2), size=(300, 260),
                 row_labels=None, view: str = "front") -> bytes:
    """PNG of the first modes of variation of a :class:`~mdlshapemodel.model.ShapeModel`.

    Rows are modes 1..n_modes (fewer when the model has fewer; the mean alone when it has none),
    columns ``mean + s sqrt(lambda_m) mode_m`` for s in ``standard_deviations``. Every panel has
    the same parallel camera, fitted once to all shapes (sizes are comparable) and looking along
    the mean's smallest principal axis, with its largest axis horizontal. Surfaces are coloured
    by their signed displacement from the mean along the mean's outward normals (mm; red
    outwards, blue inwards; one symmetric range, shown by the colour bar).

    ``size`` is the (width, height) of each panel in pixels; the picture's layout is
    ``grid_layout("modes", rows, len(standard_deviations), size)``. ``row_labels`` replace the
    rows' labels (mode number and standard deviation). ``view``: one of :data:`MODE_VIEWS`
    (looking along the mean's smallest, middle or largest principal axis).
    Raises :class:`RenderingError` when offscreen rendering is not available.
    """
    panels, labels, column_labels, half_range = mode_panels(
        model, n_modes, standard_deviations, size, view)
    row_labels = labels if row_labels is None else list(row_labels)
    layout = grid_layout("modes", len(panels), len(panels[0]), size)
    colorbar = None if model.n_modes == 0 or n_modes < 1 else (
        _colormap(DISPLACEMENT_COLORMAP), -half_range, half_range, "normal displacement [mm]")
    return _compose(layout, panels, column_labels, row_labels, colorbar=colorbar)


# ---------------------------------------------------------------------------------------------
# correspondence


def correspondence_pattern(reference: np.ndarray, n_bands: int = 8, n_sectors: int = 8
                           ) -> np.ndarray:
    """(n_p, 3) uint8 colours defined on the point index through the reference shape.

    Hue runs along the reference's longest principal axis; a soft checker of ``n_bands`` bands
    along that axis times ``n_sectors`` sectors around it alternates light and dark (smooth, so
    per-vertex colours interpolate without jagged edges). Painted on any corresponded shape, the
    same region (same point indices) gets the same colour.
    """
    from matplotlib.colors import hsv_to_rgb

    centre, axes = principal_axes(reference)
    local = (np.asarray(reference, float) - centre) @ axes.T
    along = local[:, 0]
    t = (along - along.min()) / max(float(np.ptp(along)), 1e-12)
    angle = np.arctan2(local[:, 2], local[:, 1])
    checker = np.cos(np.pi * n_bands * t) * np.cos(0.5 * n_sectors * angle)
    checker = np.tanh(2.5 * checker) / np.tanh(2.5)                   # in [-1, 1]
    radius = np.hypot(local[:, 1], local[:, 2])                       # fade out on the axis,
    checker *= np.clip(radius / max(0.3 * radius.max(), 1e-12), 0, 1)  # where the angle is moot
    hsv = np.stack([0.8 * t, 0.65 - 0.15 * checker, 0.78 + 0.2 * checker], axis=1)
    return _to_uint8(hsv_to_rgb(hsv))


def _checked_triangles(triangles, n_points: int) -> np.ndarray:
    if triangles is None:
        raise ArgumentError("no triangles: the shapes cannot be rendered as surfaces")
    triangles = np.asarray(triangles, dtype=np.int64)
    if triangles.ndim != 2 or triangles.shape[1] != 3 or len(triangles) == 0:
        raise ArgumentError(f"triangles must be an (m, 3) array, got shape {triangles.shape}")
    if triangles.min() < 0 or triangles.max() >= n_points:
        raise ArgumentError(f"triangles index points outside 0..{n_points - 1}")
    return triangles


def _selected_cases(n: int, max_cases: int) -> np.ndarray:
    """At most ``max_cases`` indices spread evenly over 0..n-1 (first and last included)."""
    if max_cases < 1:
        raise ArgumentError("max_cases must be at least 1")
    if n <= max_cases:
        return np.arange(n)
    return np.unique(np.round(np.linspace(0, n - 1, max_cases)).astype(int))


def correspondence_panels(shapes, triangles, max_cases: int = 4, size=(300, 260),
                          reference=None):
    """The raw panels of :func:`render_correspondence`: (list of (h, w, 3) uint8, indices)."""
    shapes = np.asarray(shapes, dtype=np.float64)
    if shapes.ndim != 3 or shapes.shape[2] != 3 or len(shapes) == 0:
        raise ArgumentError(f"shapes must be an (n, n_p, 3) array, got shape {shapes.shape}")
    triangles = _checked_triangles(triangles, shapes.shape[1])
    reference = shapes[0] if reference is None else np.asarray(reference, dtype=np.float64)
    if reference.shape != shapes.shape[1:]:
        raise ArgumentError(f"reference must be ({shapes.shape[1]}, 3), got {reference.shape}")
    colours = correspondence_pattern(reference)
    _, axes = principal_axes(reference)
    indices = _selected_cases(len(shapes), int(max_cases))
    with _PanelRenderer(triangles, shapes.shape[1], size) as renderer:
        panels = [renderer.render(shapes[i], vertex_normals(shapes[i], triangles), colours,
                                  _fit_view([shapes[i]], axes, size[0] / size[1]))
                  for i in indices]
    return panels, indices


def render_correspondence(shapes, triangles, names=None, max_cases: int = 4, size=(300, 260),
                          reference=None) -> bytes:
    """PNG of corresponded meshes painted with one colour pattern defined on the point index.

    ``shapes`` is (n, n_p, 3) with shared ``triangles`` (m, 3); point k corresponds across
    shapes. The pattern (:func:`correspondence_pattern`) is computed on ``reference`` (default:
    the first shape, e.g. pass the model's mean), so corresponding regions have the same colour
    in every panel. At most ``max_cases`` cases are shown (spread evenly over the list), one panel
    each, labelled with ``names``; each panel has its own camera fit but the same view direction
    (along the reference's smallest principal axis). ``size`` is each panel's (width, height);
    the layout is ``grid_layout("correspondence", 1, n_panels, size)``.
    Raises :class:`RenderingError` when offscreen rendering is not available.
    """
    panels, indices = correspondence_panels(shapes, triangles, max_cases, size, reference)
    names = list(names) if names is not None else [f"case {i + 1}" for i in range(len(shapes))]
    if len(names) < len(shapes):
        raise ArgumentError(f"{len(names)} names for {len(shapes)} shapes")
    layout = grid_layout("correspondence", 1, len(panels), size)
    return _compose(layout, [panels], [str(names[i]) for i in indices],
                    caption="same colour = corresponding points")


# ---------------------------------------------------------------------------------------------
# maps of values on the mean surface (the analysis)


def boundary_points(triangles: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Points inside a region that share a triangle with a point outside it: the region's
    outline on the mesh."""
    inside = np.asarray(inside, dtype=bool)
    mixed = inside[triangles].any(axis=1) & ~inside[triangles].all(axis=1)
    outline = np.zeros_like(inside)
    outline[np.unique(triangles[mixed])] = True
    return outline & inside


def render_maps(mean: np.ndarray, triangles: np.ndarray, maps: list, outlined=None,
                size=(260, 230)) -> bytes:
    """PNG of values on a surface from three views (the mean's principal axes: front, back,
    side), one row per map.

    ``maps`` is a list of ``(row label, values (p,), colormap name, vmin, vmax, colour-bar
    label)``; all rows share the first map's colour bar when there is one map, else each row's
    range is written in its label. ``outlined`` (p,) booleans: the boundary of that region is
    drawn black on every map.
    """
    triangles = _checked_triangles(triangles, len(mean))
    mean = np.asarray(mean, dtype=np.float64)
    normals = vertex_normals(mean, triangles)
    _, axes = principal_axes(mean)
    views = [axes, np.array([-axes[0], axes[1], -axes[2]]),
             np.array([axes[2], axes[1], -axes[0]])]
    fitted = [_fit_view([mean], view, size[0] / size[1]) for view in views]
    edge = None if outlined is None else boundary_points(triangles, outlined)
    panels = []
    with _PanelRenderer(triangles, len(mean), size) as renderer:
        for _, values, cmap_name, vmin, vmax, _ in maps:
            cmap = _colormap(cmap_name)
            scaled = (np.asarray(values, float) - vmin) / max(vmax - vmin, 1e-300)
            colours = _to_uint8(cmap(np.clip(scaled, 0.0, 1.0)))
            if edge is not None:
                colours[edge] = 0
            panels.append([renderer.render(mean, normals, colours, view) for view in fitted])
    layout = grid_layout("modes", len(maps), 3, size)
    first = maps[0]
    colorbar = (_colormap(first[2]), first[3], first[4], first[5]) if len(maps) == 1 else None
    return _compose(layout, panels, ("front", "back", "side"), [m[0] for m in maps],
                    colorbar=colorbar)
