"""analysis.html cannot mislead: opened in a real browser after `mdlshapemodel analyze` of a real
build, a null result stays dark on the 3-D viewer's fixed -log10 p scale (the significance level
marked on its colour bar), and the discriminant and the classification of groups the global test
does not separate are shown as not significant, with its p-value."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from mdlshapemodel import BuildConfig, build_model

from browser import browser, open_page  # noqa: F401 (browser: a fixture)
from common import run_cli
from synthetic import small_mask

pytestmark = pytest.mark.slow        # a real build and the real command line

N = 12
ALPHA = 0.05
# the 'thin' cases (odd k) are 8% smaller; the null grouping puts 3 thin and 3 full cases, of the
# same mean bump position, in each group
GROUPINGS = {"size": ["thin" if k % 2 else "full" for k in range(N)],
             "null": ["a" if k % 4 in (0, 3) else "b" for k in range(N)]}


@pytest.fixture(scope="module")
def pages(tmp_path_factory) -> dict:
    """grouping -> (analysis.html, analysis.json's content) of one build analysed two ways."""
    folder = tmp_path_factory.mktemp("analysis-page")
    paths = []
    for k, position in enumerate(np.linspace(-0.5, 0.5, N)):
        paths.append(folder / "labels" / f"case_{k:02d}.nii.gz")
        paths[-1].parent.mkdir(exist_ok=True)
        mask = small_mask(float(position), 0.92 if k % 2 else 1.0).astype(np.uint8)
        sitk.WriteImage(sitk.GetImageFromArray(mask), str(paths[-1]))
    build_model(paths, folder / "build", BuildConfig(
        points=162, strategy="none", baselines=[], workers=1, evaluation_modes=2,
        specificity_samples=100, surface_samples=0, cache_dir=""))
    found = {}
    for name, groups in GROUPINGS.items():
        table = folder / f"{name}.csv"
        table.write_text("case,group\n" + "".join(f"case_{k:02d},{g}\n"
                                                  for k, g in enumerate(groups)))
        output = folder / f"findings-{name}"
        result = run_cli("analyze", folder / "build", "--table", table, "--group", "group",
                         "-o", output, "--permutations", 999, "--alpha", ALPHA, "-q")
        assert result.returncode == 0, result.stderr
        found[name] = (output / "analysis.html",
                       json.loads((output / "analysis.json").read_text()))
    return found


def colour_scale(page) -> dict:
    """The 3-D viewer's colour range and the colour bar's ticks of the map shown."""
    return page.evaluate("""() => { var t = document.getElementById('effects-plot').data[0];
        return {cmin: t.cmin, cmax: t.cmax, ticks: t.colorbar.tickvals || [],
                labels: t.colorbar.ticktext || []}; }""")


def test_a_null_result_stays_dark_on_a_fixed_scale_with_alpha_marked(browser, pages):
    path, summary = pages["null"]
    assert summary["global_test"]["p"] > ALPHA and summary["significant_points"]["fwer"] == 0
    page, errors, requests = open_page(browser, path, drawn="#effects-plot canvas")
    assert errors == [] and requests == []
    scale = colour_scale(page)
    level = -np.log10(ALPHA)
    assert scale["cmin"] == 0 and scale["cmax"] >= level, scale
    assert f"α = {ALPHA:g}" in scale["labels"]
    marked = scale["ticks"][scale["labels"].index(f"α = {ALPHA:g}")]
    assert marked == pytest.approx(level)
    # every point's -log10 p lies in the lower part of the scale: dark in Viridis
    shown = page.evaluate("Array.from(document.getElementById('effects-plot').data[0]"
                          ".intensity)")
    assert max(shown) < level <= scale["cmax"]
    page.close()


def test_the_discriminant_of_groups_that_do_not_differ_is_marked_not_significant(browser,
                                                                                pages):
    path, summary = pages["null"]
    p = summary["global_test"]["p"]
    assert p > ALPHA
    page, errors, _ = open_page(browser, path, drawn="#effects-plot canvas")
    assert errors == []
    for name in ("discriminant", "classification"):
        section = page.locator(f"section#{name}")
        assert "not-significant" in section.get_attribute("class")
        text = section.inner_text()
        assert "Not significant" in text and f"p = {p:.2g}" in text
    picture = page.locator("section#discriminant img").first
    assert "grayscale" in picture.evaluate("e => getComputedStyle(e).filter")
    c = summary["classification"]       # this balanced null grouping is classified below chance
    assert min(c["balanced_accuracy"], c["auc"]) < 0.5
    assert "Below chance" in page.locator("section#classification").inner_text()
    page.close()


def test_the_discriminant_of_groups_that_differ_is_shown_plainly(browser, pages):
    path, summary = pages["size"]
    assert summary["global_test"]["p"] <= ALPHA
    page, errors, _ = open_page(browser, path, drawn="#effects-plot canvas")
    assert errors == []
    for name in ("discriminant", "classification"):
        section = page.locator(f"section#{name}")
        assert section.count() == 1
        assert "not-significant" not in (section.get_attribute("class") or "")
        assert "Not significant" not in section.inner_text()
    assert "Below chance" not in page.locator("section#classification").inner_text()
    picture = page.locator("section#discriminant img").first
    assert "grayscale" not in picture.evaluate("e => getComputedStyle(e).filter")
    scale = colour_scale(page)          # from 0 to the level, or to the data beyond it
    shown = page.evaluate("Array.from(document.getElementById('effects-plot').data[0]"
                          ".intensity)")
    assert scale["cmin"] == 0 and scale["cmax"] >= max(max(shown), -np.log10(ALPHA))
    page.close()
