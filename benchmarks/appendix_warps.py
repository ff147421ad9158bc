"""Do the Appendix warps lower the final objective on the hippocampi?  ``--warps`` compared.

Preprocesses (or reuses the cache of) the first N shared hippocampus label maps (labels 1+2),
builds the initial correspondence as ``mdlshapemodel build`` does (2562 points), then runs
``--strategy one-at-a-time-pose`` for every configuration of ``--warps`` and every seed with the
same repeatable budget: at most SWEEPS sweeps over the examples in each phase (eq. 13, then
eq. 14), no time limit. Prints each run (with eq. 13 at the end of the first phase), then, per
configuration, the final objective (eq. 14, nats) as mean +- standard error over the seeds and
per seed, the CPU seconds and objective evaluations per run, and the warps accepted by kind;
then each configuration's difference from the first.

    PYTHONPATH=MDLShapeModel python benchmarks/appendix_warps.py --cases 20 --sweeps 15 \\
        --seeds 0 1 2 --jobs 2

Runs are independent processes (``--jobs`` at a time, each single-threaded).
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "hippocampus" / "labels"
CONFIGURATIONS = ("symmetric", "symmetric,rotation", "symmetric,asymmetric,shear,rotation")

_prepared = None  # the preprocessed cases, shared with the worker processes (fork)


def initial_state(prepared, points: int):
    """The state and objectives exactly as the build pipeline sets them up."""
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.correspondence.initial import initial_state as pipeline_state

    state, objectives, _, _ = pipeline_state(prepared, BuildConfig(points=points))
    return state, objectives


def run(job: tuple) -> dict:
    """One optimisation: (warps, seed, sweeps, points) -> final objective, CPU s, evaluations."""
    from mdlshapemodel.config import OptimisationSettings
    from mdlshapemodel.correspondence.strategies import optimise
    from mdlshapemodel.correspondence.strategies.one_at_a_time import warp_counts
    from mdlshapemodel.correspondence.trace import Trace

    warps, seed, sweeps, points = job
    state, objectives = initial_state(_prepared, points)
    initial = objectives[1](state.covariance())
    settings = OptimisationSettings(strategy="one-at-a-time-pose", max_time=1e9,
                                    max_sweeps=sweeps, warps=tuple(warps.split(",")))
    cpu = time.process_time()
    wall = time.perf_counter()
    trace = Trace()
    final = optimise(state, objectives, settings, np.random.default_rng(seed), trace)
    fixed_end = [row.objective for row in trace.rows if row.phase == "fixed"][-1]
    return {"warps": warps, "seed": seed, "initial": initial, "final": final, "fixed": fixed_end,
            "cpu": time.process_time() - cpu, "wall": time.perf_counter() - wall,
            "evaluations": state.evaluations, "accepted": warp_counts(state)}


def mean_se(values) -> tuple[float, float]:
    values = np.asarray(values, dtype=np.float64)
    se = values.std(ddof=1) / np.sqrt(len(values)) if len(values) > 1 else float("nan")
    return float(values.mean()), float(se)


def main() -> int:
    global _prepared
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.prepare import preprocess

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=20)
    parser.add_argument("--data", default=str(DATA))
    parser.add_argument("--points", type=int, default=2562)
    parser.add_argument("--sweeps", type=int, default=15, help="max sweeps per phase")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--configurations", nargs="+", default=list(CONFIGURATIONS),
                        metavar="WARPS", help="--warps lists to compare; the first is the reference")
    parser.add_argument("--jobs", type=int, default=2, help="runs at a time")
    args = parser.parse_args()
    paths = sorted(Path(args.data).glob("*.nii.gz"))[: args.cases]
    if not paths:
        print(f"no label maps in {args.data}", file=sys.stderr)
        return 2
    _prepared, rejected = preprocess(paths, BuildConfig(labels=[1, 2], workers=args.jobs))
    print(f"{len(_prepared)} hippocampi ({len(rejected)} rejected), {args.points} points, "
          f"one-at-a-time-pose, at most {args.sweeps} sweeps per phase, seeds {args.seeds}",
          flush=True)
    jobs = [(warps, seed, args.sweeps, args.points)
            for seed in args.seeds for warps in args.configurations]
    results = []
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        for result in pool.map(run, jobs):
            results.append(result)
            print(f"  {result['warps']:<38} seed {result['seed']}: eq. 14 "
                  f"{result['initial']:.2f} -> {result['final']:.2f} (eq. 13 at the end of "
                  f"phase 1: {result['fixed']:.2f}), {result['cpu']:.0f} CPU s, "
                  f"{result['evaluations']} evaluations, accepted {result['accepted']}", flush=True)

    print(f"\n{'warps':<38} {'final eq. 14 (nats)':>20}  {'per seed':<24} {'CPU s':>6} "
          f"{'evaluations':>11}  accepted warps per run (sym/asym/shear/rot)")
    reference = None
    for warps in args.configurations:
        rows = [r for r in results if r["warps"] == warps]
        mean, se = mean_se([r["final"] for r in rows])
        seeds = " ".join(f"{r['final']:.2f}" for r in rows)
        accepted = "/".join(f"{np.mean([r['accepted'][k] for r in rows]):.0f}"
                            for k in ("symmetric", "asymmetric", "shear", "rotation"))
        print(f"{warps:<38} {mean:12.2f} +- {se:4.2f}  {seeds:<24} "
              f"{np.mean([r['cpu'] for r in rows]):6.0f} "
              f"{np.mean([r['evaluations'] for r in rows]):11.0f}  {accepted}")
        if reference is None:
            reference = rows
    print(f"\ninitial eq. 14: {results[0]['initial']:.2f} nats; difference from "
          f"{args.configurations[0]!r} (mean, and in units of the SE of the difference):")
    ref_mean, ref_se = mean_se([r["final"] for r in reference])
    for warps in args.configurations[1:]:
        mean, se = mean_se([r["final"] for r in results if r["warps"] == warps])
        gap = mean - ref_mean
        print(f"  {warps:<38} {gap:+.2f} nats ({gap / np.hypot(se, ref_se):+.1f} SE)")
    total = sum(r["cpu"] for r in results)
    print(f"total CPU {total:.0f} s over {len(results)} runs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
