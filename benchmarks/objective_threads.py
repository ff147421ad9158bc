"""Eq. 14 and its gradient past the covariance-route switch on 1 and 2 threads.

On populations drawn as ``evaluation_scaling.py --drawn`` draws them (around the initial
correspondence of the first ``--base`` label maps of ``--data``, 642 points, 0.05 mm of noise),
times ``Objective.data_gradient`` (one BLAS thread, as in a build) with ``threads`` 1 and 2: the
median wall and CPU seconds of ``--repeat`` calls and the load average of the machine meanwhile,
and whether the two give the same value and gradient to the bit:

    python benchmarks/objective_threads.py --data ../shared/data/hippocampus/labels \\
        --drawn 2000 5000 10000
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

import numpy as np

from evaluation_scaling import drawn_state, scaled_data


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="folder of label maps (*.nii.gz)")
    parser.add_argument("--label", default="1", help="labels of the object (default 1)")
    parser.add_argument("--drawn", type=int, nargs="+", required=True, help="population sizes")
    parser.add_argument("--base", type=int, default=40, help="cases the drawn ones are drawn from")
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args()
    from threadpoolctl import threadpool_limits

    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.prepare.batch import preprocess

    config = BuildConfig(labels=tuple(int(x) for x in args.label.split(",")), points=642,
                         workers=2)
    prepared, _ = preprocess(sorted(Path(args.data).glob("*.nii.gz"))[:args.base], config)
    print(f"{'n_s':>6} {'threads':>7} {'wall s':>7} {'CPU s':>6} {'load':>5} {'same bits':>9}")
    for n_s in args.drawn:
        state = drawn_state(prepared, config, n_s, 0.05)
        data = scaled_data(state)
        first = None
        for threads in (1, 2):
            objective = dataclasses.replace(state.objective, threads=threads)
            runs = []
            with threadpool_limits(limits=1, user_api="blas"):
                for _ in range(args.repeat):
                    wall, cpu = time.perf_counter(), time.process_time()
                    value, grad = objective.data_gradient(data)
                    runs.append((time.perf_counter() - wall, time.process_time() - cpu))
            wall, cpu = np.median(runs, axis=0)
            same = "" if first is None else str(value == first[0]
                                                and np.array_equal(grad, first[1]))
            first = first or (value, grad)
            print(f"{n_s:>6} {threads:>7} {wall:>7.2f} {cpu:>6.2f} {os.getloadavg()[0]:>5.1f}"
                  f" {same:>9}", flush=True)
        del state, data, first
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
