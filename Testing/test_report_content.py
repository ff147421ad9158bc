"""What report.html and compare.html tell a reader: what was run, where the files are, the
measures with how to read them, the modes from three sides, the cases with readable headings."""

import html
import re

import pytest

from mdlshapemodel.report.html import CASE_COLUMNS
from mdlshapemodel.version import __version__

from common import run_cli
from synthetic import write_population

pytestmark = pytest.mark.slow      # a real build through the command line


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    folder = tmp_path_factory.mktemp("report")
    write_population(folder / "labels", 4)
    output = folder / "out"
    result = run_cli("build", folder / "labels", "-o", output, "--points", 162, "--strategy",
                     "none", "--baselines", "", "--workers", 1, "--no-cache",
                     "--evaluation-modes", 2, "--specificity-samples", 100,
                     "--surface-samples", 0)
    assert result.returncode == 0, result.stderr
    return output, html.unescape((output / "report.html").read_text())


def test_it_says_what_was_run_and_links_the_files(report):
    output, page = report
    assert f"mdlshapemodel {__version__}" in page
    assert re.search(r"<pre class=command>[^<]*mdlshapemodel[^<]* build [^<]*--points 162", page)
    for setting in ("points", "strategy", "labels", "smoothing_sigma"):
        assert f"<td>{setting}</td>" in page
    files = page[page.index("<h3>Output files</h3>"):]
    links = re.findall(r"<a href='([^']+)'>", files[:files.index("</ul>")])
    assert {"model.h5", "cases.csv", "config.json", "correspondence/"} <= set(links)
    assert all((output / link.rstrip("/")).exists() for link in links)


def test_the_measures_are_explained_and_the_modes_drawn_from_three_sides(report):
    _, page = report
    assert "How to read C(M), G(M) and S(M)" in page
    views = re.findall(r"alt='modes of variation, (\w+)'", page)
    assert views == ["front", "top", "side"]


def test_the_case_table_has_readable_headings_and_file_names(report):
    output, page = report
    cases = page[page.index("<h2>Cases</h2>"):]
    headings = re.findall(r"<th>(.*?)</th>", cases)
    assert "mean distance to the input [mm]" in headings and "outlier (p < 0.01)" in headings
    assert not set(headings) & (set(CASE_COLUMNS) - {"case", "warps", "mirrored"})
    assert "case_0.nii.gz" in cases and str(output.parent / "labels") not in cases


def test_compare_html_says_what_was_run_and_links_each_models_report(report, tmp_path):
    output, _ = report
    result = run_cli("compare", output, output, "-o", tmp_path / "cmp", "--modes", 2,
                     "--samples", 100)
    assert result.returncode == 0, result.stderr
    page = html.unescape((tmp_path / "cmp" / "compare.html").read_text())
    assert f"mdlshapemodel {__version__}" in page and "How to read C(M), G(M) and S(M)" in page
    assert re.search(r"<pre class=command>[^<]*mdlshapemodel[^<]* compare ", page)
    links = re.findall(r"<a href='([^']+)'>its report</a>", page)
    assert len(links) == 2
    assert all((tmp_path / "cmp" / link).resolve() == (output / "report.html").resolve()
               for link in links)
    assert "id='viewer0-plot'" in page and "id='viewer1-plot'" in page   # a viewer per model


def test_the_viewer_colours_a_case_by_its_distance_to_its_input(report):
    import base64
    import json

    import numpy as np

    from mdlshapemodel.prepare import io

    output, page = report
    raw = (output / "report.html").read_text()
    payload = re.search(r"<script type='application/json' id='viewer-data'>(.*?)</script>",
                        raw, re.S).group(1).replace("<\\/", "</")
    data = json.loads(payload)
    top = data["distance_max"]
    values = np.frombuffer(base64.b64decode(data["case_distance"]), np.uint8).reshape(
        len(data["cases"]), -1) / 255 * top
    fidelity = {row["case"]: float(row["max_distance_mm"]) for row in
                io.read_csv(output / "cases.csv")}
    for name, per_point in zip(data["cases"], values):
        # the largest per-point value is the case's largest input-to-mesh distance (cases.csv)
        assert abs(per_point.max() - min(fidelity[name], top)) <= top / 255 + 1e-9, name
    assert "a case's distance to its input surface" in page


def test_the_convergence_plot_has_a_panel_per_phase_the_coarse_stage_included(tmp_path):
    import base64
    import struct

    from mdlshapemodel.prepare import io
    from mdlshapemodel.report.html import convergence_plot

    def width(phases) -> int:
        path = tmp_path / f"{len(phases)}.csv"
        io.write_csv(path, ("wall_seconds", "objective", "phase"),
                     [(float(k), 100.0 - k, phase) for phase in phases for k in range(3)])
        png = base64.b64decode(convergence_plot(path))
        return struct.unpack(">I", png[16:20])[0]          # the IHDR chunk's width

    one = width(["integrated"])
    # three panels side by side (the page's margins are cropped: less than 3 times as wide)
    assert 2.4 * one < width(["coarse fixed", "coarse integrated", "integrated"]) < 3.1 * one
    assert 1.6 * one < width(["fixed", "integrated"]) < 2.1 * one
