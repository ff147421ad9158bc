"""One build with older commits and with this tree, one after the other in one run: a speed
claim, or a change of quality, checked the way it is judged.

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

Several older commits give one row each (a bisection). With ``--landmarks SET`` the inputs are a
landmark set of ``landmark_data.py`` (``SET/meshes``) and every build's landmark-transfer error
(median of templates, ``landmarks.py``) joins the table; with ``--truth POPULATION`` the inputs
are a ``ground_truth.py`` population (``POPULATION/labels``) and the error to the known
correspondence joins it:

    python benchmarks/side_by_side.py 715a569 4cccc67 --repeat 1 --output /tmp/bisect \
        --truth /tmp/gt-femur -- --max-time 600
    python benchmarks/side_by_side.py 715a569 --repeat 1 --output /tmp/sbs-femur \
        --landmarks /tmp/landmarks/femur -- --points 2562

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


def anatomy(output: Path, args, cache: dict) -> dict:
    """The build's landmark-transfer error (median of templates, mean and median over the cases
    and labels, mm) and its error to the known correspondence (mean and 95th percentile, mm),
    where the run measures them."""
    found = {}
    if args.landmarks:
        import landmarks as transfer           # benchmarks/landmarks.py, beside this script
        from mdlshapemodel.prepare import io
        from mdlshapemodel.prepare.landmarks import read_landmarks

        data = Path(args.landmarks)
        cases = sorted(p.stem for p in (output / "correspondence").glob("*.vtp"))
        if "landmarks" not in cache:
            read = {p.stem: read_landmarks(p) for p in (data / "landmarks").glob("*.csv")}
            cache["landmarks"] = read
            cache["surfaces"] = {p.stem: io.read_mesh(p) for p in (data / "meshes").glob("*.vtp")}
        read = cache["landmarks"]
        labels = list(read[cases[0]].labels)
        result = transfer.evaluate_build(data, output, cases, labels,
                                         {c: read[c].points for c in cases}, cache["surfaces"])
        found.update(landmarks_mean=result["median_of_templates"]["mean"],
                     landmarks_median=result["median_of_templates"]["median"],
                     located=result["located"]["mean"], landmark_cases=len(cases))
    if args.truth:
        import ground_truth                    # benchmarks/ground_truth.py, beside this script

        cases = sorted(p.stem for p in (output / "correspondence").glob("*.vtp"))
        result = ground_truth.correspondence_error(Path(args.truth), output, cases)
        found.update(truth_mean=result["mean_mm"], truth_p95=result["p95_mm"],
                     truth_cases=len(cases))
    return found


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
            # eq. 14 alone (a build before the objective's parts reported eq. 14 as "final")
            "objective": metrics["objective"].get("parts", {}).get("final", {}).get(
                "description_length", metrics["objective"]["final"])}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("old", nargs="+",
                        help="the older commits (anything git rev-parse takes), each a row")
    parser.add_argument("--cases", type=int, default=None,
                        help="the first N inputs (default: 82 hippocampi, every landmark case or "
                             "every case of the population)")
    sources = parser.add_mutually_exclusive_group()
    sources.add_argument("--landmarks", metavar="SET",
                         help="a landmark set of landmark_data.py: its meshes are the inputs, and "
                              "each build's landmark-transfer error is measured")
    sources.add_argument("--truth", metavar="POPULATION",
                         help="a population of ground_truth.py: its label maps are the inputs, "
                              "and each build's error to the known correspondence is measured")
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--output", required=True)
    parser.add_argument("--no-warm-up", dest="warm_up", action="store_false",
                        help="time the first build after installing too (numba compiles then)")
    words = sys.argv[1:]
    mine, extra = (words[:words.index("--")], words[words.index("--") + 1:]) if "--" in words \
        else (words, [])
    args = parser.parse_args(mine)
    output = Path(args.output)
    if args.landmarks:
        cases = sorted((Path(args.landmarks) / "meshes").glob("*.vtp"))
    elif args.truth:
        cases = sorted((Path(args.truth) / "labels").glob("*.nii.gz"))
    else:
        # hippocampus_011 is hippocampus_010 byte for byte, which a build refuses
        cases = [p for p in sorted(DATA.glob("*.nii.gz")) if p.name != "hippocampus_011.nii.gz"]
        extra = extra or ["--label", "1,2"]     # after --: build options for every version
    cases = cases[:args.cases or (82 if not (args.landmarks or args.truth) else None)]
    inputs = linked(cases, output / "inputs")
    commands = {old: install(old, output / f"old-{old}") for old in args.old}
    commands["new"] = install("new", output / "new")
    times = {version: [] for version in commands}
    measured = {}
    if args.warm_up:
        warm_inputs = linked(cases[:5], output / "warm-up-inputs")
        for version, command in commands.items():
            build(command, warm_inputs, output / f"{version}-warm-up", "--max-time", "5", *extra)
    what = ("landmark set " + args.landmarks if args.landmarks else
            "population " + args.truth if args.truth else "hippocampi")
    print(f"{len(cases)} inputs ({what}), build options {' '.join(extra)}; "
          f"old = {' '.join(args.old)}, new = this tree")
    print("version  run  wall_s  prepare_s  optimise_s  evaluations  G(1) +- SE        "
          "S(1) +- SE        F" + ("  landmarks mean/median mm  located" if args.landmarks
                                   else "  truth mean/p95 mm" if args.truth else ""))
    for repeat in range(args.repeat):
        for version, command in commands.items():
            folder = output / f"{version}-{repeat}"
            started = time.perf_counter()
            build(command, inputs, folder, *extra)
            wall = time.perf_counter() - started
            times[version].append(wall)
            s = stages(folder)
            a = anatomy(folder, args, measured)
            quality = (f"  {a['landmarks_mean']:.3f} / {a['landmarks_median']:.3f} "
                       f"({a['landmark_cases']} cases)  {a['located']:.3f}" if args.landmarks
                       else f"  {a['truth_mean']:.3f} / {a['truth_p95']:.3f} "
                       f"({a['truth_cases']} cases)" if args.truth else "")
            print(f"{version:<7}  {repeat:>3}  {wall:6.1f}  {s['prepare_s']:9.1f}  "
                  f"{s['optimise_s']:10.1f}  {s['evaluations']!s:>11}  "
                  f"{s['G1']:.4f} +- {s['G1_se']:.4f}  {s['S1']:.4f} +- {s['S1_se']:.4f}  "
                  f"{s['objective']:.1f}" + quality, flush=True)
    new = statistics.median(times["new"])
    for version in args.old:
        old = statistics.median(times[version])
        print(f"median wall: {version} {old:.1f} s, new {new:.1f} s, old/new {old / new:.2f}")


if __name__ == "__main__":
    main()
