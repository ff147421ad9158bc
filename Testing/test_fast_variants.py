"""benchmarks/fast_variants.py runs as its docstring says, on a tiny population: one JSON row per
variant, each from a fresh process, with the numbers it names."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from synthetic import write_population

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "fast_variants.py"


def run_script(*arguments) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, arguments)],
                          capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_each_variant_prints_one_row_of_finite_numbers(tmp_path):
    """Two variants on 4 of 5 small label maps, one second of optimisation each: a row per
    variant, in order, of the first 4 cases, with the fast strategy's phases, eq. 14 before and
    after, and G, S (M = 1..3) with their standard errors, all finite."""
    write_population(tmp_path / "labels", 5)
    completed = run_script("default", "rounds2", "--data", tmp_path / "labels", "--cases", 4,
                           "--label", 1, "--max-time", 1)
    assert completed.returncode == 0, completed.stderr[-3000:]
    rows = [json.loads(line) for line in completed.stdout.splitlines()]
    assert [row["variant"] for row in rows] == ["default", "rounds2"]
    for row in rows:
        assert row["cases"] == 4 and row["evaluations"] > 0
        assert set(row["phases_end"]) <= {"coarse fixed", "coarse integrated", "fixed",
                                          "integrated"} and row["phases_end"]
        for name in ("G", "G_se", "S", "S_se"):
            assert len(row[name]) == 3, name
        numbers = [row["seconds"], row["initial_eq14"], row["eq14"], *row["G"], *row["G_se"],
                   *row["S"], *row["S_se"], *(x for end in row["phases_end"].values()
                                              for x in end)]
        assert all(math.isfinite(x) for x in numbers), row
        assert all(x > 0 for x in row["G"] + row["S"]), row
    # the same initial correspondence, so the same eq. 14 before the variants differ
    assert rows[0]["initial_eq14"] == rows[1]["initial_eq14"]


def test_an_unknown_variant_is_refused_before_any_work(tmp_path):
    completed = run_script("rounds7", "--data", tmp_path, "--cases", 1)
    assert completed.returncode != 0
    assert "unknown variant 'rounds7'" in completed.stderr
