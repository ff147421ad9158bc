"""The interactive 3-D viewer of report.html (report/viewer.py), in a real browser.

The page is opened from disk (file://) in headless Chromium through Playwright, with every
request that is not file: aborted (the viewer must work offline), and checked: no console error,
the canvas draws, mode 1's slider at +3 SD changes the drawing, the case picker switches the
mesh. Where /usr/bin/chromium (or the playwright package) is missing these tests are skipped,
saying why.
"""

from __future__ import annotations

import base64
import io
import re
import time
from pathlib import Path

import numpy as np
import pytest

from mdlshapemodel.correspondence.sampling import sphere_grid
from mdlshapemodel.model.shape_model import ShapeModel
from mdlshapemodel.report.html import html_page, write_report
from mdlshapemodel.report.viewer import EffectMap, viewer_section

from browser import browser, open_page as _open  # noqa: F401 (browser: a fixture)


def population(n_s=6, n_points=642, seed=0, parts=1):
    """Deformed ellipsoids on one icosphere grid (one or several parts side by side)."""
    rng = np.random.default_rng(seed)
    directions, triangles = sphere_grid(n_points)
    shapes, all_triangles = [], []
    for _ in range(n_s):
        pieces = []
        for part in range(parts):
            axes = np.array([14.0, 9.0, 7.0]) * (1 + 0.15 * rng.normal(size=3))
            bump = 1 + 0.1 * rng.normal() * np.sin(3 * directions[:, 0])
            pieces.append(directions * axes * bump[:, None] + [30.0 * part, 0, 0])
        shapes.append(np.concatenate(pieces))
    for part in range(parts):
        all_triangles.append(triangles + part * n_points)
    weights = np.full(n_points * parts, 1.0 / (n_points * parts))
    names = [f"case_{i:02d}" for i in range(n_s)]
    model = ShapeModel.from_shapes(
        np.stack(shapes), weights, names=names, triangles=np.concatenate(all_triangles),
        part_sizes=[n_points] * parts,
        part_names=[f"part{p}" for p in range(parts)] if parts > 1 else None)
    return model, np.stack(shapes), names


def test_page_size_of_a_realistic_model():
    """82 cases x 2562 points, 10 modes: the viewer section stays under 10 MB."""
    model, shapes, names = population(n_s=82, n_points=2562)
    size = len("\n".join(viewer_section(model, shapes, names)).encode())
    assert size < 10e6, size


def curves(n_s=5, n_points=64, seed=1):
    """Closed 2-D outlines (ellipses with a bump), a model of curves (segments)."""
    rng = np.random.default_rng(seed)
    angle = 2 * np.pi * np.arange(n_points) / n_points
    shapes = []
    for _ in range(n_s):
        radius = 1 + 0.15 * rng.normal() * np.exp(-((angle - np.pi) ** 2) / 0.3)
        a, b = 20 * (1 + 0.1 * rng.normal()), 10 * (1 + 0.1 * rng.normal())
        shapes.append(np.stack([a * radius * np.cos(angle), b * radius * np.sin(angle),
                                np.zeros(n_points)], axis=1))
    segments = np.stack([np.arange(n_points), (np.arange(n_points) + 1) % n_points], axis=1)
    names = [f"outline_{i}" for i in range(n_s)]
    model = ShapeModel.from_shapes(np.stack(shapes), np.full(n_points, 1.0 / n_points),
                                   names=names, triangles=segments)
    return model, np.stack(shapes), names


def test_a_large_population_shows_a_sample_spanning_its_first_mode(monkeypatch):
    from mdlshapemodel.report import viewer

    model, shapes, names = population(n_s=9, n_points=42)
    monkeypatch.setattr(viewer, "MAX_CASE_BYTES", 4 * 6 * 42)
    page = "".join(viewer.viewer_section(model, shapes, names))
    assert "a sample of 4 of the 9 cases" in page
    options = re.findall(r"<option value=\d+>(case_\d+)</option>", page)
    assert len(options) == 4 and options == sorted(options)      # in the cases' order
    # the cases of the lowest and the highest score on mode 1 are among them
    scores = [model.project(shape, 1)[0] for shape in shapes]
    assert names[int(np.argmin(scores))] in options and names[int(np.argmax(scores))] in options
    # the same sample at every writing
    assert page == "".join(viewer.viewer_section(model, shapes, names))


def test_the_sample_is_at_evenly_spaced_ranks_of_the_first_modes_weighted_scores(monkeypatch):
    """Half the points weigh 50 times less: the cases' scores on mode 1 (ShapeModel.project,
    which weighs the points) rank them otherwise than the points' plain sum would."""
    from mdlshapemodel.report import viewer

    first, shapes, names = population(n_s=9, n_points=42, seed=3)
    weights = np.where(np.arange(42) < 21, 1.0, 0.02)
    model = ShapeModel.from_shapes(shapes, weights / weights.sum(), names=names,
                                   triangles=first.triangles)
    monkeypatch.setattr(viewer, "MAX_CASE_BYTES", 4 * 6 * 42)
    scores = [model.project(shape, 1)[0] for shape in shapes]
    ranked = np.argsort(scores)[[0, 3, 5, 8]]         # np.rint(np.linspace(0, 8, 4))
    data = viewer.viewer_data(model, shapes, names)
    assert data["cases"] == [names[i] for i in sorted(ranked)]


def test_the_sample_scored_a_few_cases_at_a_time_is_that_of_all_at_once(monkeypatch):
    """shown_cases scores SCORED_AT_ONCE cases at a time (its memory bounded at any population):
    the scores, and so the sample, are those of the whole population's differences at once."""
    from mdlshapemodel.report import viewer

    model, shapes, _ = population(n_s=23, n_points=42, seed=5)
    weighted = np.asarray(model.modes[0]) * np.asarray(model.weights)[:, None]
    scores = np.einsum("pd,spd->s", weighted, shapes - model.mean)
    ranks = np.unique(np.rint(np.linspace(0, 22, 6)).astype(np.int64))
    expected = np.sort(np.argsort(scores, kind="stable")[ranks])
    for at_once in (1, 4, 23, 100):
        monkeypatch.setattr(viewer, "SCORED_AT_ONCE", at_once)
        np.testing.assert_array_equal(viewer.shown_cases(model, shapes, 6), expected)


def test_a_sampled_case_is_coloured_by_its_own_distances(monkeypatch):
    from mdlshapemodel.report import viewer

    model, shapes, names = population(n_s=9, n_points=42)
    monkeypatch.setattr(viewer, "MAX_CASE_BYTES", 4 * 6 * 42)
    # case i lies i + 1 mm from its input at every point
    distances = np.repeat(np.arange(1.0, 10.0)[:, None], 42, axis=1)
    data = viewer.viewer_data(model, shapes, names, distances=distances)
    shown = np.array([names.index(name) for name in data["cases"]])
    assert len(shown) == 4 and shown.max() == 8
    colours = np.frombuffer(base64.b64decode(data["case_distance"]), dtype=np.uint8)
    # each shown case's colour: its own distance over the largest shown, in 255 steps
    expected = np.rint(255 * (shown + 1) / 9.0)
    np.testing.assert_array_equal(colours.reshape(4, 42), np.repeat(expected[:, None], 42, 1))


def test_notes_instead_of_a_viewer():
    model, shapes, names = population(n_s=4, n_points=42)
    model.triangles = None
    assert "no triangles" in "".join(viewer_section(model, shapes, names))
    assert viewer_section(None) == []


def test_curve_normals_point_outward():
    from mdlshapemodel.report.viewer import viewer_data
    import base64

    model, shapes, names = curves()
    data = viewer_data(model, shapes, names)
    assert data["kind"] == "curve"
    normals = np.frombuffer(base64.b64decode(data["normals"]), np.float32).reshape(-1, 3)
    outward = np.einsum("ij,ij->i", normals, model.mean - model.mean.mean(axis=0))
    assert np.all(outward > 0)


def report_metrics() -> dict:
    """The metrics of a build of 4 cases and 42 points that write_report needs."""
    return {"objective": {"initial": 1.0, "final": 0.5}, "n_shapes": 4, "n_points": 42,
            "strategy": "fast", "n_rejected": 0, "interrupted": False,
            "modes": [1, 2], "compactness": [1.0, 1.5], "compactness_se": [0.1, 0.1],
            "generalization": [2.0, 1.0], "generalization_se": [0.1, 0.1],
            "specificity": [2.0, 2.5], "specificity_se": [0.1, 0.1]}


def test_write_report_holds_the_viewer(tmp_path):
    model, shapes, names = population(n_s=4, n_points=42)
    metrics = report_metrics()
    page = write_report(tmp_path, metrics, [], [], model, shapes, names).read_text()
    assert "id='viewer-plot'" in page and "MIT licence" in page


def _pixels(png: bytes) -> np.ndarray:
    from matplotlib.image import imread

    return imread(io.BytesIO(png), format="png")[..., :3]


def _slide(page, mode: int, value: float):
    """Move a slider as a user does: its value, then its input event."""
    page.eval_on_selector(f"#viewer-mode-{mode}", "(e, v) => { e.value = v; "
                          "e.dispatchEvent(new Event('input', {bubbles: true})); }", str(value))


def _frames(page):
    """Wait two animation frames: the viewer redraws on the next one after an input."""
    page.evaluate("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")


def _plot_shot(page) -> np.ndarray:
    page.wait_for_timeout(400)          # one animation frame for the restyle, one to draw
    return _pixels(page.locator("#viewer-plot").screenshot())


def _changed(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean(np.any(np.abs(a - b) > 0.02, axis=-1)))


def _drawn(image: np.ndarray) -> float:
    """The fraction of pixels that are not the white background."""
    return float(np.mean(~np.all(image > 0.97, axis=-1)))


def _eventually(page, condition, seconds: float = 10.0) -> np.ndarray:
    """The plot's screenshot once ``condition(screenshot)`` holds (a busy machine draws late),
    or the last one."""
    deadline = time.monotonic() + seconds
    while True:
        shot = _plot_shot(page)
        if condition(shot) or time.monotonic() > deadline:
            return shot


def test_viewer_in_a_browser(browser, tmp_path):
    model, shapes, names = population(n_s=6, n_points=642)
    path = tmp_path / "viewer.html"
    path.write_text(html_page("viewer", viewer_section(model, shapes, names)), encoding="utf-8")
    page, errors, requests = _open(browser, path)

    mean = _eventually(page, lambda shot: _drawn(shot) > 0.05)
    assert _drawn(mean) > 0.05, "the 3-D canvas draws nothing"

    _slide(page, 0, 3)
    assert page.inner_text("#viewer-sd-0") == "3.0"
    plus3 = _eventually(page, lambda shot: _changed(mean, shot) > 0.005)
    assert _changed(mean, plus3) > 0.005, "mode 1 at +3 SD draws the same picture"

    page.select_option("#viewer-case", "2")
    case = _eventually(page, lambda shot: _changed(plus3, shot) > 0.005)
    assert _changed(plus3, case) > 0.005, "the case picker does not change the mesh"
    _frames(page)
    x = page.evaluate("document.getElementById('viewer-plot').data[0].x.slice(0, 5)")
    assert np.allclose(x, shapes[2, :5, 0], atol=1e-3)

    page.click("#viewer-reset")
    _frames(page)
    x = page.evaluate("document.getElementById('viewer-plot').data[0].x.slice(0, 5)")
    assert np.allclose(x, model.mean[:5, 0], atol=1e-4)

    assert not errors, errors
    assert not requests, requests
    page.close()


def test_a_guided_models_landmarks_follow_the_sliders_and_the_picked_case(browser, tmp_path):
    """The landmarks are a labelled trace at their rows of the shape shown: the mean, the mean
    moved by a slider, a picked case."""
    model, shapes, names = population(n_s=6, n_points=642)
    model.landmarks = {"tip": 3, "base": 517}
    rows = [3, 517]
    path = tmp_path / "viewer.html"
    path.write_text(html_page("viewer", viewer_section(model, shapes, names)), encoding="utf-8")
    page, errors, requests = _open(browser, path)
    plot = "document.getElementById('viewer-plot').data"

    def shown():
        _frames(page)
        trace = page.evaluate(f"{plot}[1]")
        return np.column_stack([trace["x"], trace["y"], trace["z"]])

    assert page.evaluate(f"{plot}.length") == 2
    assert page.evaluate(f"{plot}[1].text") == ["tip", "base"]
    np.testing.assert_allclose(shown(), model.mean[rows], atol=1e-4)
    _slide(page, 0, 2)
    moved = model.mean + 2 * np.sqrt(model.variances[0]) * model.modes[0]
    np.testing.assert_allclose(shown(), moved[rows], atol=1e-3)
    page.select_option("#viewer-case", "4")
    np.testing.assert_allclose(shown(), shapes[4][rows], atol=1e-2)   # quantised on the page
    assert "landmarks that guided the build" in page.inner_text("#viewer p")
    assert not errors, errors
    assert not requests, requests
    page.close()


def test_multi_part_viewer_in_a_browser(browser, tmp_path):
    model, shapes, names = population(n_s=4, n_points=162, parts=2)
    path = tmp_path / "parts.html"
    path.write_text(html_page("parts", viewer_section(model, shapes, names)), encoding="utf-8")
    page, errors, requests = _open(browser, path)
    assert page.evaluate("document.getElementById('viewer-plot').data.length") == 2
    before = _eventually(page, lambda shot: _drawn(shot) > 0.05)
    page.locator(".legend .traces").nth(1).locator(".legendtoggle").click()   # hide part1
    # plotly acts on a legend click once its double-click time has passed
    page.wait_for_function("document.getElementById('viewer-plot').data[1].visible "
                           "=== 'legendonly'", timeout=10000)
    after = _eventually(page, lambda shot: _drawn(shot) < _drawn(before) - 0.005)
    assert _drawn(after) < _drawn(before) - 0.005, "hiding a part leaves the picture as it was"
    assert not errors, errors
    assert not requests, requests
    page.close()


def test_curve_viewer_in_a_browser(browser, tmp_path):
    model, shapes, names = curves()
    path = tmp_path / "curves.html"
    path.write_text(html_page("curves", viewer_section(model, shapes, names)), encoding="utf-8")
    page, errors, requests = _open(browser, path, drawn="#viewer-plot .scatterlayer path")
    mean = _eventually(page, lambda shot: _drawn(shot) > 0.01)
    assert _drawn(mean) > 0.01, "the curve is not drawn"
    _slide(page, 0, 3)
    plus3 = _eventually(page, lambda shot: _changed(mean, shot) > 0.002)
    assert _changed(mean, plus3) > 0.002, "mode 1 at +3 SD draws the same picture"
    page.select_option("#viewer-case", "1")
    _frames(page)
    x = page.evaluate("document.getElementById('viewer-plot').data[0].x.slice(0, 2)")
    assert np.allclose(x, shapes[1, :2, 0], atol=1e-3)
    assert not errors, errors
    assert not requests, requests
    page.close()


def test_the_analysis_effect_maps_turn_and_threshold_in_a_browser(browser, tmp_path):
    from mdlshapemodel.report.viewer import effects_section

    model, _, _ = population(n_s=4, n_points=642)
    mean = model.mean
    # a significance map high at one end, and a signed effect negative there
    significance = 3.0 * np.exp(-np.sum((mean - mean[np.argmax(mean[:, 0])]) ** 2, axis=1) / 40)
    effect = -0.5 * significance + 0.1 * mean[:, 1] / np.abs(mean[:, 1]).max()
    section = effects_section(mean, model.triangles, [EffectMap("-log10 p", significance),
                                                      EffectMap("effect [mm]", effect, True)])
    path = tmp_path / "effects.html"
    path.write_text(html_page("effects", section), encoding="utf-8")
    page, errors, requests = _open(browser, path, drawn="#effects-plot canvas")

    def shot():
        page.wait_for_timeout(400)
        return _pixels(page.locator("#effects-plot").screenshot())

    first = shot()
    assert _drawn(first) > 0.05
    page.eval_on_selector("#effects-threshold", "(e) => { e.value = 0.5; "
                          "e.dispatchEvent(new Event('input', {bubbles: true})); }")
    thresholded = shot()
    assert _changed(first, thresholded) > 0.005
    assert float(page.inner_text("#effects-threshold-value")) == pytest.approx(1.5, rel=1e-2)
    page.select_option("#effects-map", "1")
    diverging = shot()
    assert _changed(thresholded, diverging) > 0.005
    title = page.evaluate("document.getElementById('effects-plot').data[0].colorbar.title.text")
    assert title == "effect [mm]"
    assert errors == [] and requests == []
    page.close()


def test_the_colour_picker_shows_the_point_index_and_a_cases_distance(browser, tmp_path):
    model, shapes, names = population(n_s=4, n_points=642)
    distances = np.abs(np.random.default_rng(2).normal(0.1, 0.05, size=(4, len(model.mean))))
    path = tmp_path / "colours.html"
    path.write_text(html_page("viewer", viewer_section(model, shapes, names,
                                                       distances=distances)), encoding="utf-8")
    page, errors, requests = _open(browser, path)
    normal = _eventually(page, lambda shot: _drawn(shot) > 0.05)
    page.select_option("#viewer-colour", "index")
    index = _eventually(page, lambda shot: _changed(normal, shot) > 0.01)
    assert _changed(normal, index) > 0.01
    title = "document.getElementById('viewer-plot').layout.coloraxis.colorbar.title.text"
    assert page.evaluate(title) == "point<br>index"
    page.select_option("#viewer-case", "1")
    page.select_option("#viewer-colour", "distance")
    far = _eventually(page, lambda shot: _changed(index, shot) > 0.01)
    assert _changed(index, far) > 0.01
    assert "distance" in page.evaluate(title)
    shown = page.evaluate("document.getElementById('viewer-plot').data[0].intensity")
    top = np.percentile(distances, 99.5)          # the colour scale's top, beyond which: clipped
    np.testing.assert_allclose(shown, np.minimum(distances[1], top), atol=top / 255 * 1.01)
    assert errors == [] and requests == []
    page.close()


def test_two_viewers_on_one_page_move_independently(browser, tmp_path):
    first, _, _ = population(n_s=4, n_points=642, seed=3)
    second, _, _ = population(n_s=4, n_points=642, seed=4)
    body = (viewer_section(first, prefix="viewer0", heading="<h3>a</h3>")
            + viewer_section(second, prefix="viewer1", heading="<h3>b</h3>", with_plotly=False))
    assert "".join(body).count("* plotly.js v") == 1            # plotly.js once for both
    path = tmp_path / "two.html"
    path.write_text(html_page("two viewers", body), encoding="utf-8")
    page, errors, requests = _open(browser, path, drawn="#viewer1-plot canvas")

    def shot(prefix):
        page.wait_for_timeout(400)
        return _pixels(page.locator(f"#{prefix}-plot").screenshot())

    before = [shot("viewer0"), shot("viewer1")]
    assert min(_drawn(image) for image in before) > 0.05
    page.eval_on_selector("#viewer1-mode-0", "(e) => { e.value = 3; "
                          "e.dispatchEvent(new Event('input', {bubbles: true})); }")
    after = [shot("viewer0"), shot("viewer1")]
    assert _changed(before[1], after[1]) > 0.01 and _changed(before[0], after[0]) < 0.001
    assert page.inner_text("#viewer1-sd-0") == "3.0" and page.inner_text("#viewer0-sd-0") == "0.0"
    assert errors == [] and requests == []
    page.close()


def test_a_long_command_line_wraps_in_a_small_box(browser, tmp_path, monkeypatch):
    """A build of hundreds of files: the command stays within the page's width and a few lines."""
    model, shapes, names = population(n_s=4, n_points=42)
    metrics = report_metrics()
    paths = [f"/data/study/labels/subject_{k:04d}_hippocampus_left.nii.gz" for k in range(300)]
    monkeypatch.setattr("sys.argv", ["mdlshapemodel", "build", *paths, "-o", "/tmp/model"])
    path = write_report(tmp_path, metrics, [], [], model, shapes, names)
    page, errors, _ = _open(browser, path)
    assert errors == []
    widths = page.evaluate("[document.documentElement.scrollWidth, window.innerWidth]")
    assert widths[0] <= widths[1], widths
    box = page.locator("pre.command")
    assert "subject_0299_hippocampus_left.nii.gz" in box.inner_text()     # all of it is there
    height = box.bounding_box()["height"]
    line = page.evaluate("parseFloat(getComputedStyle(document.body).fontSize)")
    assert height < 10 * line, (height, line)


def test_the_normals_check_shows_its_map_and_the_cases_most_off(browser, tmp_path):
    from mdlshapemodel.model.normals import normal_agreement

    model, shapes, names = population(n_s=4, n_points=642)
    shapes = shapes.copy()
    shapes[2] = shapes[2][::-1]             # one case's points in reverse order: normals off
    normals = normal_agreement(shapes, model.triangles)
    path = write_report(tmp_path, report_metrics(), [], [], model, shapes, names,
                        normals=normals)
    page, errors, _ = _open(browser, path)
    assert errors == []
    section = page.locator("h2", has_text="Correspondence check: normals")
    assert section.count() == 1
    image = page.locator("img[alt='normal spread']")
    assert image.evaluate("e => e.complete && e.naturalWidth > 0")
    shot = _pixels(image.screenshot())
    assert _drawn(shot) > 0.1, "the normal map draws nothing"
    rows = page.locator("h2:has-text('Correspondence check: normals') ~ table").first
    assert names[2] in rows.inner_text().split("\n")[1]     # the reversed case heads the list
    widths = page.evaluate("[document.documentElement.scrollWidth, window.innerWidth]")
    assert widths[0] <= widths[1], widths
    page.close()


def test_the_landmarks_section_lists_each_label_and_its_farthest_case(browser, tmp_path):
    from mdlshapemodel.folders import CorrespondedLandmark
    from mdlshapemodel.outputs import landmark_summary

    model, shapes, names = population(n_s=4, n_points=42)
    model.landmarks = {"tip": 3, "base": 17}
    records = [CorrespondedLandmark(name, label, np.zeros(3), np.array([distance, 0.0, 0.0]))
               for name, distances in zip(names, ((0.2, 0.5), (0.4, 2.5), (0.1, 0.3), (0.3, 0.0)))
               for label, distance in zip(("tip", "base"), distances)]
    records[-1] = CorrespondedLandmark(names[-1], "base", np.zeros(3), None)   # not given
    metrics = {**report_metrics(), "landmarks": landmark_summary(model, records)}
    path = write_report(tmp_path, metrics, [], [], model, shapes, names)
    page, errors, _ = _open(browser, path)
    assert errors == []
    heading = page.locator("h2", has_text="Landmarks that guided the correspondence")
    assert heading.count() == 1
    lines = page.locator("h2:has-text('Landmarks that guided') ~ table").first.inner_text()
    tip, base = lines.split("\n")[1:3]
    assert tip.split("\t")[:2] == ["tip", "4"] and tip.split("\t")[-1] == names[1]
    assert base.split("\t")[:2] == ["base", "3"] and base.split("\t")[3] == "2.5"
    assert "7 landmarks given" in page.locator("h2:has-text('Landmarks that guided') + p").inner_text()
    widths = page.evaluate("[document.documentElement.scrollWidth, window.innerWidth]")
    assert widths[0] <= widths[1], widths
    page.close()


def case_rows(names) -> list:
    """Rows of a build's case table (cases.csv's columns), with long values: wider than a page."""
    from mdlshapemodel.report.html import CASE_COLUMNS

    rows = []
    for k, name in enumerate(names):
        row = {key: f"{0.123456 * (k + 1):.6f}" for key in CASE_COLUMNS}
        row.update(case=name, flags="score outlier (Mahalanobis distance 3.61, p = 0.004)"
                   if k == 2 else "", file=f"/data/a/rather/long/folder/{name}.nii.gz",
                   warp_kinds="field:36; symmetric:120; asymmetric:12; shear:4",
                   score_outlier=k == 2)
        rows.append(row)
    return rows


def test_the_case_table_scrolls_in_its_box_with_the_case_and_its_flags_pinned(browser,
                                                                             tmp_path):
    model, shapes, names = population(n_s=6, n_points=42)
    names = [f"subject_{k:04d}_hippocampus_left" for k in range(6)]
    path = write_report(tmp_path, report_metrics(), case_rows(names), [], model, shapes, names)
    page, errors, _ = _open(browser, path)
    assert errors == []
    widths = page.evaluate("[document.documentElement.scrollWidth, window.innerWidth]")
    assert widths[0] <= widths[1], widths              # the page itself does not scroll sideways
    box = page.locator("div.cases")
    assert box.evaluate("e => e.scrollWidth > e.clientWidth + 100")   # the table scrolls in it
    row = box.locator("tbody tr").nth(2)
    row.scroll_into_view_if_needed()
    middle = row.locator("td").nth(8)
    before = middle.bounding_box()["x"]
    box.evaluate("e => { e.scrollLeft = e.scrollWidth; }")
    page.wait_for_timeout(200)
    assert middle.bounding_box()["x"] < before - 100   # scrolled
    frame = box.bounding_box()
    for column in (0, 1):                # the case name and its flags stay in view, on top
        cell = row.locator("td").nth(column)
        where = cell.bounding_box()
        assert frame["x"] - 1 <= where["x"] and where["x"] + where["width"] <= (
            frame["x"] + frame["width"] + 1), (column, where, frame)
        shown = page.evaluate("([x, y]) => document.elementFromPoint(x, y).textContent",
                              [where["x"] + where["width"] / 2, where["y"] + where["height"] / 2])
        assert shown == cell.inner_text()
    assert row.locator("td").nth(0).inner_text() == names[2]
    assert "score outlier" in row.locator("td").nth(1).inner_text()
    page.close()


def test_flagged_cases_are_named_at_the_top_of_the_report(browser, tmp_path):
    model, shapes, names = population(n_s=6, n_points=42)
    flagged = {names[2]: ["score outlier (Mahalanobis distance 3.61, p = 0.004)"],
               names[4]: ["normals off at 30 points (more than 60° from the mean direction)"]}
    metrics = {**report_metrics(), "flagged_cases": flagged}
    path = write_report(tmp_path, metrics, case_rows(names), [], model, shapes, names)
    page, errors, _ = _open(browser, path)
    assert errors == []
    listed = page.locator("#flagged")
    assert listed.is_visible()
    text = listed.inner_text()
    assert all(name in text for name in flagged) and "score outlier" in text
    assert "normals off at 30 points" in text and names[0] not in text
    first_section = page.locator("h2").first.bounding_box()["y"]
    assert listed.bounding_box()["y"] < first_section        # above everything else
    page.close()
    path = write_report(tmp_path, {**report_metrics(), "flagged_cases": {}}, case_rows(names),
                        [], model, shapes, names)
    page, errors, _ = _open(browser, path)
    assert "No case is flagged" in page.locator("#flagged").inner_text()
    page.close()
