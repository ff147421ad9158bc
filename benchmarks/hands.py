"""The shared 2-D hand outlines: taken out of correspondence, then modelled by MDL and by equal arc
length.

The 17 hands (../shared/data/hands2d, statismo's example data) come in correspondence: the same
number of points, point k the same place on every hand. ``resample`` takes that away: each outline
is resampled at ``--points`` points equally spaced in arc length from a random start (seeded), and
written as a CSV point list. ``build`` runs the real CLI on them with default settings; its
baseline ``none`` is the equal-arc-length model of the same outlines after origin alignment (what
``--strategy none`` builds). It prints G and S (mm², ± SE) for M = 1..5, the differences in
standard errors of the difference, and the time.

    python benchmarks/hands.py resample --output /tmp/hands
    python benchmarks/hands.py build /tmp/hands
    # the paper's 2-D strategy study (Table II) on the same outlines:
    python benchmarks/strategy_scaling.py --data /tmp/hands/inputs --pattern "*.csv" \\
        --sizes 5 10 15 --points 128 --budget 20 --output /tmp/hands/scaling
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HANDS = Path(__file__).resolve().parents[2] / "shared" / "data" / "hands2d"


def resample(args) -> int:
    from mdlshapemodel.prepare.curve import resample_curve
    from mdlshapemodel.prepare.curve_io import read_curve

    inputs = Path(args.output) / "inputs"
    inputs.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    files = sorted(Path(args.data).glob("hand-*.vtk"), key=lambda p: int(p.stem.split("-")[1]))
    for path in files:
        points = resample_curve(read_curve(path), args.points, start=float(rng.random()))
        np.savetxt(inputs / f"{path.stem}.csv", points, delimiter=",", header="x,y",
                   comments="", fmt="%.6f")
    print(f"{len(files)} outlines, {args.points} points each from a random start: {inputs}")
    return 0


def build(args) -> int:
    folder = Path(args.folder)
    output = folder / "mdl"
    started = time.perf_counter()
    run = subprocess.run([sys.executable, "-m", "mdlshapemodel.cli", "build", str(folder / "inputs"),
                          "-o", str(output), "--overwrite", *args.options],
                         capture_output=True, text=True)
    seconds = time.perf_counter() - started
    if run.returncode != 0:
        print(run.stderr, file=sys.stderr)
        return run.returncode
    metrics = json.loads((output / "metrics.json").read_text())
    baseline = metrics["baselines"]["none"]
    print(f"{metrics['n_shapes']} outlines, n_p = {metrics['n_points']}, {seconds:.1f} s wall "
          f"(CLI in a subprocess); objective {metrics['objective']['initial']:.2f} -> "
          f"{metrics['objective']['final']:.2f}")
    for key in ("generalization", "specificity"):
        print(f"\n{key} [mm^2 +- SE]  M = 1..5")
        for label, values in (("MDL", metrics), ("equal arc length", baseline)):
            print(f"  {label:<18}" + "  ".join(f"{v:8.3f} +- {e:6.3f}" for v, e in
                                               zip(values[key][:5], values[key + "_se"][:5])))
        # the build's own difference (MDL minus baseline) and its SE: compare's rule
        found = baseline["differences"][key]
        print(f"  {'better by (SE)':<18}" + "  ".join(
            f"{-d / s:18.1f}" for d, s in zip(found["difference"][:5], found["se"][:5])))
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    maker = commands.add_parser("resample", help="the hands out of correspondence, as CSV")
    maker.add_argument("--data", default=str(HANDS))
    maker.add_argument("--output", required=True)
    maker.add_argument("--points", type=int, default=400)
    maker.add_argument("--seed", type=int, default=2003)
    builder = commands.add_parser("build", help="MDL against equal arc length (the CLI)")
    builder.add_argument("folder")
    builder.add_argument("options", nargs="*", help="more build options, after --")
    args = parser.parse_args(argv)
    return {"resample": resample, "build": build}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
