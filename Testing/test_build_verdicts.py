"""What a build says of itself, through the real command line on shared hippocampi: the report's
verdicts against its baseline are those of `mdlshapemodel compare` on the same two
correspondences, and the cases its checks flag are named in its printout and atop its report."""

from __future__ import annotations

import html
import json
import re

import numpy as np
import pytest

from mdlshapemodel.prepare import io

from common import hippocampi, needs_hippocampi, run_cli_quietly

pytestmark = [pytest.mark.slow, needs_hippocampi]     # real builds

COMMON = ["--points", 162, "--workers", 2, "--specificity-samples", 1000,
          "--evaluation-modes", 8, "--surface-samples", 0, "-q"]


def distinct_hippocampi(count: int) -> list:
    """The first shared hippocampi but hippocampus_011, a copy of hippocampus_010."""
    return [path for path in hippocampi(count + 1) if "_011" not in path.name][:count]


def report_verdicts(page: str, column: str) -> list:
    """The verdict of the MDL model against a baseline per M, as the report's table of the
    measures says it in ``column`` (such as "G none")."""
    quality = page[page.index("<h2>Model quality"):]
    table = quality[:quality.index("</table>")]
    header = re.findall(r"<th>(.*?)</th>", table)
    cells = [re.findall(r"<td[^>]*>(.*?)</td>", row)
             for row in re.findall(r"<tr>(.*?)</tr>", table.split("<tbody>")[1])]
    said = [html.unescape(row[header.index(column)]) for row in cells]
    return ["better" if "(MDL better" in cell else "worse" if "(MDL worse" in cell else "same"
            for cell in said]


def test_the_reports_verdicts_against_its_baseline_are_those_of_compare(tmp_path):
    cases = distinct_hippocampi(10)
    mdl = run_cli_quietly("build", *cases, "-o", tmp_path / "mdl", "--baselines", "none",
                          *COMMON)
    assert mdl.returncode == 0, mdl.stderr
    # the initial correspondence on its own: a build compare can read
    initial = run_cli_quietly("build", *cases, "-o", tmp_path / "none", "--strategy", "none",
                              "--baselines", "", *COMMON)
    assert initial.returncode == 0, initial.stderr
    compared = run_cli_quietly("compare", tmp_path / "none", tmp_path / "mdl", "-o",
                               tmp_path / "cmp", "--modes", 8, "--samples", 1000)
    assert compared.returncode == 0, compared.stderr

    metrics = json.loads((tmp_path / "mdl" / "metrics.json").read_text())
    baseline = metrics["baselines"]["none"]
    alone = json.loads((tmp_path / "none" / "metrics.json").read_text())
    np.testing.assert_allclose(baseline["generalization"], alone["generalization"], rtol=1e-9)
    result = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    (label,) = result["differences"]                 # the MDL build against the initial one
    page = (tmp_path / "mdl" / "report.html").read_text()
    for measure, column in (("generalization", "G none"), ("specificity", "S none")):
        theirs = result["differences"][label][measure]
        said = ["same" if not significant else "better" if difference < 0 else "worse"
                for difference, significant in zip(theirs["difference"], theirs["significant"])]
        assert report_verdicts(page, column) == said, measure
        # metrics.json holds what the report shows: compare's differences and errors
        recorded = baseline["differences"][measure]
        np.testing.assert_allclose(recorded["difference"], theirs["difference"], rtol=1e-6,
                                   atol=1e-12)
        np.testing.assert_allclose(recorded["se"], theirs["se"], rtol=1e-6, atol=1e-12)
    # the measure where the two rules part: somewhere the paired jackknife tells the models
    # apart where two independent standard errors would not
    g = baseline["differences"]["generalization"]
    unpaired = np.hypot(metrics["generalization_se"], baseline["generalization_se"])
    assert any(abs(d) <= 2 * u and v != "same"
               for d, u, v in zip(g["difference"], unpaired, g["verdict"]))


def test_the_build_names_the_cases_it_flags(tmp_path):
    cases = distinct_hippocampi(13)
    result = run_cli_quietly("build", *cases, "-o", tmp_path / "out", "--baselines", "",
                             *COMMON)
    assert result.returncode == 0, result.stderr
    rows = io.read_csv(tmp_path / "out" / "cases.csv")
    outliers = [row["case"] for row in rows if str(row["score_outlier"]) == "True"]
    assert outliers, "no score outlier among these cases: the test needs one"
    said = [line for line in result.stdout.splitlines() if "flagged" in line]
    assert len(said) == 1 and all(name in said[0] for name in outliers), result.stdout
    line = said[0]
    flagged = json.loads((tmp_path / "out" / "metrics.json").read_text())["flagged_cases"]
    assert set(outliers) <= set(flagged)
    for row in rows:
        assert (row["case"] in line) == (row["case"] in flagged), row["case"]
    assert all(flagged[name][0] in line for name in flagged)
    page = (tmp_path / "out" / "report.html").read_text()
    top = page[:page.index("<h2>")]
    assert all(name in top for name in flagged)
