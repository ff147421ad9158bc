"""What one evaluation of the fast strategy costs per shape as the population grows.

For each size n_s, the first n_s label maps of ``--data`` are prepared (through the preprocessing
cache), given their initial correspondence on ``--points`` sample points (642: the grid the fast
strategy optimises on) and one round of the finest field level is set up; then one evaluation,
as the optimisation makes it, is timed in its three pieces:

- ``sample``: the fields' maps, point location and pose of every example (per example, on
  ``--threads`` threads);
- ``objective``: F and dF/dX from the shapes: the Gram matrix of the n_s shapes, its
  n_s x n_s eigendecomposition and the gradient (one BLAS thread, as in a build);
- ``chain``: dF/dX chained to the fields' coefficients and the poses (per example, threads).

It prints milliseconds per evaluation and per shape for each piece (the median of ``--repeat``
evaluations at random parameters within the round's bounds):

    python benchmarks/evaluation_scaling.py --data /tmp/pop1000/labels --label 1 --sizes 100 250 500 1000

(``benchmarks/population.py`` writes such a population.)
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def timed(function, repeat: int) -> tuple[float, object]:
    """Median seconds of ``repeat`` calls and the last result."""
    seconds = []
    for _ in range(repeat):
        started = time.perf_counter()
        result = function()
        seconds.append(time.perf_counter() - started)
    return float(np.median(seconds)), result


def measure(prepared: list, config, level: int, threads: int, repeat: int) -> dict:
    """Seconds of the three pieces of one evaluation on ``prepared``."""
    from threadpoolctl import threadpool_limits

    from mdlshapemodel.correspondence.initial import initial_state
    from mdlshapemodel.correspondence.strategies.fast import FieldRound, gradient_at
    from mdlshapemodel.parallel import Threads

    state, (_, integrated), _, _ = initial_state(prepared, config)
    state.objective = integrated
    rng = np.random.default_rng(0)
    with Threads(threads) as pool, threadpool_limits(limits=1, user_api="blas"):
        round_ = FieldRound(state, range(state.n_shapes), level, 2.0, pool)
        x = 0.1 * round_.limit * rng.uniform(-1.0, 1.0, round_.size)
        x[~np.isfinite(x)] = 0.0
        sample, trial = timed(lambda: round_.trial(x), repeat)
        objective, (_, shape_gradient) = timed(lambda: gradient_at(state, trial.shapes), repeat)
        chain, _ = timed(lambda: round_.gradient(trial, shape_gradient), repeat)
    return {"sample": sample, "objective": objective, "chain": chain}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="a folder of label maps")
    parser.add_argument("--label", default="1", help="labels of the object (default 1)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[100, 250, 500, 1000])
    parser.add_argument("--points", type=int, default=642)
    parser.add_argument("--level", type=int, default=3, help="field level (3: 642 bumps)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.prepare.batch import preprocess

    config = BuildConfig(labels=tuple(int(x) for x in args.label.split(",")),
                         points=args.points, workers=2)
    inputs = sorted(Path(args.data).glob("*.nii.gz"))
    print(f"{'n_s':>5} {'sample ms':>10} {'objective ms':>13} {'chain ms':>9} {'total ms':>9}"
          f" {'per shape: sample':>18} {'objective':>10} {'chain':>7} {'total ms':>9}")
    for n in args.sizes:
        prepared, rejected = preprocess(inputs[:n], config)
        if rejected:
            print(f"{len(rejected)} of the first {n} cases rejected")
        seconds = measure(prepared, config, args.level, args.threads, args.repeat)
        total = sum(seconds.values())
        count = len(prepared)
        print(f"{count:>5} {1e3 * seconds['sample']:>10.1f} {1e3 * seconds['objective']:>13.1f}"
              f" {1e3 * seconds['chain']:>9.1f} {1e3 * total:>9.1f}"
              f" {1e3 * seconds['sample'] / count:>18.3f} {1e3 * seconds['objective'] / count:>10.3f}"
              f" {1e3 * seconds['chain'] / count:>7.3f} {1e3 * total / count:>9.3f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
