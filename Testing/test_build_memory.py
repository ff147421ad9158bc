"""benchmarks/build_memory.py's tables from a samples file: each stage's and each round's peaks
over the right samples, and a run whose build compiled the kernels named."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "build_memory.py"


def write_samples(path: Path, compiled: bool) -> None:
    """A build's samples as ``run`` writes them: log lines and ticks, with the helper's memory
    under ``kids``."""
    lines = [(0.0, "log", "compiling numerical kernels (first run only)" if compiled
              else "preprocessing 4 cases", 100, 80, {}),
             (1.0, "log", "prepared 4 cases in 1 s", 150, 90, {}),
             (2.5, "tick", "", 300, 200, {"7": 20}),
             (3.0, "log", "initial objective 10.0", 310, 210, {"7": 20}),
             (3.5, "tick", "", 400, 250, {"7": 500}),
             (4.0, "log", "coarse fixed: level 0, round 1, F = 9.0 (at most 1 min left)", 420, 260,
              {"7": 450}),
             (4.5, "tick", "", 900, 700, {"7": 100}),
             (5.0, "log", "coarse fixed: level 3, round 2, F = 8.0 (at most 1 min left)", 380, 240,
              {"7": 100}),
             (6.0, "log", "final objective 8.0 after 3 s", 350, 230, {"7": 100})]
    with open(path, "w") as file:
        for t, kind, msg, rss, used, kids in lines:
            file.write(json.dumps({"t": t, "kind": kind, "msg": msg, "rss": rss,
                                   "malloc_used": used, "malloc_free": 0, "kids": kids}) + "\n")
        file.write('{"t": 7.0, "kind": "tick", "rss"')      # a line cut short by a kill


def run_script(*arguments) -> str:
    completed = subprocess.run([sys.executable, str(SCRIPT), *map(str, arguments)],
                               capture_output=True, text=True, timeout=120)
    assert completed.returncode == 0, completed.stderr
    return completed.stdout


def cells(output: str, first: str) -> list:
    row = next(line for line in output.splitlines() if first in line)
    return [cell.strip() for cell in row.strip("|").split("|")]


def test_stages_and_rounds_peaks_and_the_compiled_kernels_named(tmp_path):
    cold, warm = tmp_path / "cold.jsonl", tmp_path / "warm.jsonl"
    write_samples(cold, compiled=True)
    write_samples(warm, compiled=False)
    table = run_script("table", cold, warm)
    # the optimisation: from "initial objective" (t = 3) to "final objective" (t = 6)
    assert cells(table, f"{warm} | optimisation")[2:] == ["3", "900", "1000", "500", "700"]
    # the initial correspondence: from "prepared ... cases in" (t = 1) to "initial objective"
    assert cells(table, f"{warm} | initial correspondence")[2:] == ["2", "310", "330", "20",
                                                                     "210"]
    assert f"{cold}: the build compiled the numerical kernels" in table
    assert f"{warm}: the build compiled" not in table
    rounds = run_script("rounds", warm)
    # each round from the line before it to its own: the helper's 500 MB in the first, the
    # build's 900 MB in the second
    assert cells(rounds, "level 0, round 1") == ["coarse fixed: level 0, round 1", "4", "420",
                                                 "900", "500", "260"]
    assert cells(rounds, "level 3, round 2") == ["coarse fixed: level 3, round 2", "5", "900",
                                                 "1000", "450", "700"]
