"""One build with an older commit and with this tree, one after the other in one run: a speed
claim checked the way it is judged.

Each version is installed into a virtualenv of its own (``OLD`` from this repository's history,
exported with ``git archive``; ``new``: this working tree), then the same ``mdlshapemodel build``
runs with each on the same inputs, ``--repeat`` times in turn (old, new, old, new, ...), each with
an empty preprocessing cache. Printed per run: the wall time, the preparation and optimisation
times (from build.log and convergence.csv), the evaluations, and G(1) and S(1) with their SEs
(metrics.json); then the median wall times and their ratio. Before the timed runs, each version
builds the first five cases once, untimed: the first build after installing compiles the numba
loops into their cache, which a user pays once, not per build (``--no-warm-up`` times it too).

    python benchmarks/side_by_side.py bfba680 --cases 82 --output /tmp/sbs
    python benchmarks/side_by_side.py HEAD~5 --cases 20 --output /tmp/sbs -- --points 642

Measure on a quiet machine: another process on the same cores changes both times. The virtualenvs
are kept in ``--output`` and reused when their commit matches.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import shutil
import statistics
import subprocess
import sys
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "hippocampus" / "labels"
# packages that older commits import and this tree no longer needs (the remesher and the conformal
# map of commits before 3ee7f0c)
OLDER_PACKAGES = ["gpytoolbox>=0.3", "lapy>=1.1"]


def run(command, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([str(c) for c in command], check=True, text=True,
                          capture_output=True, **kwargs)


def install(version: str, folder: Path) -> Path:
    """A virtualenv in ``folder`` with ``version`` installed (a commit, or 'new': this tree);
    reused when it holds that commit already. Returns its mdlshapemodel command."""
    commit = (run(["git", "-C", ROOT, "rev-parse", version]).stdout.strip()
              if version != "new" else "new")
    stamp = folder / "installed-commit"
    command = folder / "venv" / "bin" / "mdlshapemodel"
    if command.exists() and stamp.exists() and stamp.read_text() == commit != "new":
        return command
    folder.mkdir(parents=True, exist_ok=True)
    run([sys.executable, "-m", "venv", "--clear", folder / "venv"])
    pip = folder / "venv" / "bin" / "pip"
    if version == "new":
        source = ROOT
    else:
        source = folder / "source"
        shutil.rmtree(source, ignore_errors=True)   # files (and build/) of another commit
        source.mkdir()
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", commit],
                                 check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(source)], input=archive, check=True)
    run([pip, "install", "--quiet", str(source)], timeout=3600)
    if version != "new":
        # an older commit may import a package it did not declare (bfba680 uses gpytoolbox):
        # this tree's dependencies and the packages older ones used go in beside it
        declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
        run([pip, "install", "--quiet", *declared, *OLDER_PACKAGES], timeout=3600)
    stamp.write_text(commit)
    return command


def linked(paths, folder: Path) -> Path:
    """``folder`` (made) holding a symbolic link to each of ``paths``."""
    folder.mkdir(parents=True, exist_ok=True)
    for path in paths:
        link = folder / path.name
        if not link.exists():
            link.symlink_to(path)
    return folder


def build(command: Path, inputs: Path, folder: Path, *options):
    """``command build inputs -o folder`` with an empty cache, quietly, into a fresh folder."""
    shutil.rmtree(folder, ignore_errors=True)   # (older commits lack --overwrite)
    run([command, "build", inputs, "-o", folder, "--no-cache", "-q", *options], timeout=7200)


def stages(output: Path) -> dict:
    """Preparation and optimisation seconds, evaluations, G(1), S(1) and their SEs."""
    log = (output / "build.log").read_text()
    prepared = re.search(r"prepared \d+ cases in ([\d.]+) s", log)
    rows = list(csv.DictReader(open(output / "convergence.csv")))
    metrics = json.loads((output / "metrics.json").read_text())
    return {"prepare_s": float(prepared.group(1)) if prepared else float("nan"),
            "optimise_s": float(rows[-1]["wall_seconds"]) if rows else float("nan"),
            "evaluations": metrics.get("evaluations"),
            "G1": metrics["generalization"][0], "G1_se": metrics["generalization_se"][0],
            "S1": metrics["specificity"][0], "S1_se": metrics["specificity_se"][0],
            "objective": metrics["objective"]["final"]}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("old", help="the older commit (anything git rev-parse takes)")
    parser.add_argument("--cases", type=int, default=82)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--output", required=True)
    parser.add_argument("--no-warm-up", dest="warm_up", action="store_false",
                        help="time the first build after installing too (numba compiles then)")
    words = sys.argv[1:]
    mine, extra = (words[:words.index("--")], words[words.index("--") + 1:]) if "--" in words \
        else (words, [])
    args = parser.parse_args(mine)
    output = Path(args.output)
    extra = extra or ["--label", "1,2"]     # after --: build options for both
    cases = sorted(DATA.glob("*.nii.gz"))[:args.cases]
    inputs = linked(cases, output / "inputs")
    commands = {"old": install(args.old, output / "old"), "new": install("new", output / "new")}
    times = {"old": [], "new": []}
    if args.warm_up:
        warm_inputs = linked(cases[:5], output / "warm-up-inputs")
        for version, command in commands.items():
            build(command, warm_inputs, output / f"{version}-warm-up", "--max-time", "5", *extra)
    print(f"{args.cases} hippocampi, build options {' '.join(extra)}; old = {args.old}, "
          "new = this tree")
    print("version  run  wall_s  prepare_s  optimise_s  evaluations  G(1) +- SE        "
          "S(1) +- SE        F")
    for repeat in range(args.repeat):
        for version, command in commands.items():
            folder = output / f"{version}-{repeat}"
            started = time.perf_counter()
            build(command, inputs, folder, *extra)
            wall = time.perf_counter() - started
            times[version].append(wall)
            s = stages(folder)
            print(f"{version:<7}  {repeat:>3}  {wall:6.1f}  {s['prepare_s']:9.1f}  "
                  f"{s['optimise_s']:10.1f}  {s['evaluations']!s:>11}  "
                  f"{s['G1']:.4f} +- {s['G1_se']:.4f}  {s['S1']:.4f} +- {s['S1_se']:.4f}  "
                  f"{s['objective']:.1f}")
    old, new = (statistics.median(times[v]) for v in ("old", "new"))
    print(f"median wall: old {old:.1f} s, new {new:.1f} s, old/new {old / new:.2f}")


if __name__ == "__main__":
    main()
