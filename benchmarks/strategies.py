"""Every optimisation strategy on the same hippocampi: time to reach strategy 4's final objective.

Preprocesses (or reuses the cache of) the first N shared hippocampus label maps (labels 1+2), builds
the initial correspondence at 2562 points, and runs each strategy from it with the build defaults
and the same time budget, each in its own process (``--jobs`` at once; one BLAS thread each). After
every sweep / round the full objective (eq. 14) of the state is recorded, also during the
fixed-Delta phase (whose own objective is eq. 13). The target is the eq.-14 value the paper's
strategy 4 (one example at a time with pose, III-D4) ends at within the budget. For each strategy
the table gives the wall and CPU seconds and objective evaluations at which eq. 14 first reaches
the target (linear interpolation between records), and the speed-up: strategy 4's time to reach its
own final value divided by the strategy's. Traces go to ``OUTPUT/<strategy>.csv``. Then the model
of each strategy's final correspondence is evaluated (compactness, generalization, specificity with
10,000 samples, M = 1..10, area-weighted mm^2; saved to ``OUTPUT/<strategy>.json``) and compared
with strategy 4's: differences are given in standard errors of the difference,
sqrt(SE_a^2 + SE_b^2).

    python benchmarks/strategies.py --cases 40 --budget 600 --jobs 2 --output /tmp/strategies40

Run it on an otherwise idle machine: with two jobs each strategy has one core. ``--reference
OUTPUT/one-at-a-time-pose.csv`` reuses strategy 4's trace of an earlier run on the same cases and
machine instead of running it again (its model is compared when ``one-at-a-time-pose.json`` lies
beside it).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "hippocampus" / "labels"
REFERENCE = "one-at-a-time-pose"
ORDER = (REFERENCE, "one-at-a-time", "multiscale", "multiresolution", "fast")
COLUMNS = ("wall_seconds", "cpu_seconds", "evaluations", "objective", "phase", "sweep", "eq14")


def run(strategy: str, paths: list, budget: float, seed: int) -> tuple:
    """One strategy from the initial correspondence: its trace rows with eq. 14 appended, and the
    quality measures of its final model."""
    import numpy as np

    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.model.evaluation import evaluate
    from mdlshapemodel.model.shape_model import ShapeModel
    from mdlshapemodel.correspondence.initial import initial_state
    from mdlshapemodel.correspondence.strategies import optimise
    from mdlshapemodel.correspondence.trace import Trace
    from mdlshapemodel.prepare import preprocess

    config = BuildConfig(labels=[1, 2], strategy=strategy, max_time=budget, seed=seed, workers=1)
    prepared, _ = preprocess(paths, config)
    state, objectives, _, _ = initial_state(prepared, config)
    integrated = objectives[1]

    class Eq14Trace(Trace):
        """Also records eq. 14 of the state; the time spent doing so is left out of the clocks."""

        def record(self, state, value, phase, sweep):
            wall, cpu = time.perf_counter(), time.process_time()
            eq14 = float(integrated(state.covariance()))
            self.start_wall += time.perf_counter() - wall
            self.start_cpu += time.process_time() - cpu
            super().record(state, value, phase, sweep)
            self.rows[-1] = self.rows[-1] + (eq14,)

    trace = Eq14Trace()
    trace.record(state, integrated(state.covariance()), "start", 0)
    optimise(state, objectives, config.optimisation_settings(), np.random.default_rng(seed), trace)
    state.rebuild()
    aligned = state.aligned_shapes()
    model = ShapeModel.from_shapes(aligned, state.weights)
    return trace.rows, evaluate(aligned, state.weights, model.variances, 10, 10_000,
                                np.random.default_rng(0))


def time_to_reach(rows: list, target: float, column: int) -> float:
    """The first time (column ``column``) at which eq. 14 is at or below ``target``, linearly
    interpolated between the records around it; inf if never."""
    previous = None
    for row in rows:
        if row[-1] <= target:
            if previous is None or previous[-1] == row[-1]:
                return float(row[column])
            fraction = (previous[-1] - target) / (previous[-1] - row[-1])
            return float(previous[column] + fraction * (row[column] - previous[column]))
        previous = row
    return math.inf


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=40)
    parser.add_argument("--data", default=str(DATA))
    parser.add_argument("--budget", type=float, default=600.0, help="seconds per strategy")
    parser.add_argument("--strategies", default=",".join(ORDER))
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", default="strategies-benchmark")
    parser.add_argument("--reference", help="strategy 4's trace (CSV) from an earlier run")
    args = parser.parse_args()
    paths = [str(p) for p in sorted(Path(args.data).glob("*.nii.gz"))[: args.cases]]
    if not paths:
        print(f"no label maps in {args.data}", file=sys.stderr)
        return 2
    strategies = [s for s in args.strategies.split(",") if s]
    if REFERENCE not in strategies:
        strategies.insert(0, REFERENCE)
    traces, quality = {}, {}
    if args.reference:
        with open(args.reference, newline="") as file:
            rows = list(csv.reader(file))[1:]
        traces[REFERENCE] = [(float(r[0]), float(r[1]), int(r[2]), float(r[3]), r[4], int(r[5]),
                              float(r[6])) for r in rows]
        measures = Path(args.reference).with_suffix(".json")
        if measures.exists():
            quality[REFERENCE] = json.loads(measures.read_text())
    output = Path(args.output)
    output.mkdir(parents=True, exist_ok=True)

    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.prepare import preprocess

    started = time.perf_counter()
    prepared, rejected = preprocess(paths, BuildConfig(labels=[1, 2], workers=args.jobs))
    print(f"{len(prepared)} cases prepared ({len(rejected)} rejected) in "
          f"{time.perf_counter() - started:.0f} s; budget {args.budget:.0f} s per strategy, "
          f"{args.jobs} at once", flush=True)
    with ProcessPoolExecutor(args.jobs) as pool:
        futures = {s: pool.submit(run, s, paths, args.budget, args.seed) for s in strategies
                   if s not in traces}
        for strategy, future in futures.items():
            traces[strategy], quality[strategy] = future.result()
            with open(output / f"{strategy}.csv", "w", newline="") as file:
                writer = csv.writer(file)
                writer.writerow(COLUMNS)
                writer.writerows(traces[strategy])
            (output / f"{strategy}.json").write_text(json.dumps(quality[strategy]))
            print(f"  {strategy}: eq. 14 {traces[strategy][0][-1]:.2f} -> "
                  f"{min(r[-1] for r in traces[strategy]):.2f}", flush=True)

    target = min(r[-1] for r in traces[REFERENCE])
    reference = {c: time_to_reach(traces[REFERENCE], target, c) for c in (0, 1, 2)}
    print(f"\ntarget: eq. 14 = {target:.2f}, strategy 4's final value within {args.budget:.0f} s "
          f"(initial {traces[REFERENCE][0][-1]:.2f})\n")
    print(f"{'strategy':<20} {'final eq.14':>11} {'wall s':>8} {'CPU s':>8} {'evaluations':>11} "
          f"{'speed-up (wall)':>15} {'(CPU)':>7} {'(evaluations)':>13}")
    for strategy in strategies:
        rows = traces[strategy]
        times = [time_to_reach(rows, target, c) for c in (0, 1, 2)]
        ratios = [reference[c] / t if t > 0 else math.inf for c, t in enumerate(times)]
        shown = ["-" if math.isinf(t) else f"{t:.1f}" for t in times[:2]]
        shown.append("-" if math.isinf(times[2]) else f"{times[2]:.0f}")
        print(f"{strategy:<20} {min(r[-1] for r in rows):>11.2f} {shown[0]:>8} {shown[1]:>8} "
              f"{shown[2]:>11} {ratios[0]:>15.2f} {ratios[1]:>7.2f} {ratios[2]:>13.2f}")
    print("\n'-': never reached the target within the budget (speed-up 0).")
    for measure in ("compactness", "generalization", "specificity"):
        print(f"\n{measure} [mm^2 +- SE] at M = 1, 2, 3, 5, 10; (strategy - strategy 4) / SE of the "
              "difference in brackets")
        reference = quality.get(REFERENCE)
        for strategy in quality:
            q = quality[strategy]
            cells = []
            for m in (m for m in (0, 1, 2, 4, 9) if m < len(q[measure])):
                gap = math.nan if reference is None else (q[measure][m] - reference[measure][m]) / max(
                    math.hypot(q[measure + "_se"][m], reference[measure + "_se"][m]), 1e-300)
                cells.append(f"{q[measure][m]:.3f}+-{q[measure + '_se'][m]:.3f} ({gap:+.1f})")
            print(f"  {strategy:<20} " + "  ".join(cells))
    return 0


if __name__ == "__main__":
    sys.exit(main())
