"""The viewer's colour says which way the surface moved: outward red, inward blue.

A population of ellipsoids that differ only in size, so that mode 1 inflates or deflates the
whole shape: the displacement along the normal the page is given for mode 1 has the sign of the
mode's movement measured here, and in Chromium the inflated surface is drawn red, the deflated
one blue, for the sliders and for a picked case alike (plotly.js's RdBu runs from blue, low, to
red, high)."""

from __future__ import annotations

import base64
import io

import numpy as np
import pytest

from mdlshapemodel.correspondence.sampling import sphere_grid
from mdlshapemodel.model.shape_model import ShapeModel
from mdlshapemodel.report.html import html_page
from mdlshapemodel.report.viewer import viewer_data, viewer_section

from browser import browser, open_page  # noqa: F401 (browser: a fixture)

N_POINTS = 642


@pytest.fixture(scope="module")
def sizes():
    """(model, shapes, names): eight ellipsoids scaled by 0.85 to 1.15, nothing else."""
    directions, triangles = sphere_grid(N_POINTS)
    scales = np.linspace(0.85, 1.15, 8)
    shapes = np.stack([directions * [14.0, 9.0, 7.0] * s for s in scales])
    names = [f"case_{k}" for k in range(8)]
    model = ShapeModel.from_shapes(shapes, np.full(N_POINTS, 1 / N_POINTS), names=names,
                                   triangles=triangles)
    return model, shapes, names


def inflation(model) -> float:
    """+1 when mode 1 at +1 SD moves the mean's points away from its centre on average, else -1
    (the sign of a mode is arbitrary)."""
    moved = np.sqrt(model.variances[0]) * model.modes[0]
    return float(np.sign(np.mean(np.einsum("pd,pd->p", moved,
                                            model.mean - model.mean.mean(axis=0)))))


def test_the_pages_normal_displacement_of_mode_1_has_the_sign_of_its_movement(sizes):
    model, shapes, names = sizes
    data = viewer_data(model, shapes, names)
    along = np.frombuffer(base64.b64decode(data["along"]), np.float32).reshape(-1, N_POINTS)
    radial = model.mean / np.linalg.norm(model.mean, axis=1)[:, None]   # the sphere's outward
    moved = np.einsum("pd,pd->p", np.sqrt(model.variances[0]) * model.modes[0], radial)
    assert np.all(np.sign(along[0]) == np.sign(moved))
    assert np.all(np.sign(along[0]) == inflation(model))


def colours(page) -> tuple[float, float]:
    """The shares of the plot's pixels that are red and that are blue (the colour bar's
    included)."""
    from matplotlib.image import imread

    page.wait_for_timeout(400)
    image = imread(io.BytesIO(page.locator("#viewer-plot").screenshot()), format="png")[..., :3]
    red = np.mean((image[..., 0] - image[..., 2]) > 0.15)
    blue = np.mean((image[..., 2] - image[..., 0]) > 0.15)
    return float(red), float(blue)


def test_an_inflated_surface_is_red_and_a_deflated_one_blue_in_a_browser(browser, sizes,
                                                                         tmp_path):
    model, shapes, names = sizes
    path = tmp_path / "viewer.html"
    path.write_text(html_page("viewer", viewer_section(model, shapes, names)), encoding="utf-8")
    page, errors, _ = open_page(browser, path)
    bar_red, bar_blue = colours(page)      # the mean: a neutral surface, the colour bar
    sign = inflation(model)
    seen = {}
    for value, inflated in ((3 * sign, True), (-3 * sign, False)):
        page.eval_on_selector("#viewer-mode-0", "(e, v) => { e.value = v; "
                              "e.dispatchEvent(new Event('input', {bubbles: true})); }",
                              str(value))
        seen[f"mode 1 at {value:+g} SD"] = (inflated, *colours(page))
    page.click("#viewer-reset")
    for index, inflated in ((7, True), (0, False)):           # the largest case, the smallest
        page.select_option("#viewer-case", str(index))
        seen[f"case {index}"] = (inflated, *colours(page))
    for what, (inflated, red, blue) in seen.items():
        red, blue = red - bar_red, blue - bar_blue          # the surface's own
        assert (red > 0.02 and blue < 0.002) if inflated else (blue > 0.02 and red < 0.002), (
            what, red, blue)
    assert not errors, errors
    page.close()
