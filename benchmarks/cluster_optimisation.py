"""One evaluation of the fast strategy with its per-example work on 1, 2, 4 Dask workers.

A population of ``--shapes`` examples is made from the first ``--base`` label maps of ``--data``
(prepared through the preprocessing cache, their initial correspondence on ``--points`` sample
points, the grid the fast strategy optimises on): example k is a copy of case k mod ``--base``
(its own surface, point locator and samples: the per-example work and the data sent are those of
a population of that size). One round of field level ``--level`` is set up and evaluations are
made as the optimisation makes them (the samples at random parameters within the round's bounds,
F and dF/dX, the chain rule), ``--repeat`` of them after one that is not counted (the workers'
first call loads the compiled kernels):

- ``here``: in this process, the per-example work on ``--threads`` threads (a build without
  ``--scheduler``);
- ``w workers``: a ``distributed.LocalCluster`` of w worker processes of one thread on 127.0.0.1,
  each holding n_s / w examples (:mod:`mdlshapemodel.correspondence.strategies.spread`).

For each it prints per evaluation the wall time, the CPU time of this process and the largest
CPU time of one worker, and the megabytes sent each way. On a machine whose cores are shared
(or with more workers than cores) the wall times say little: the CPU times do. From them it fits

    t(w) = t_central + t_example * n_s / w + t_comm * w

with t_central + t_comm w a line fitted to this process's CPU time per evaluation against w (the
central part, F and dF/dX from the shapes and the poses, and the sending and receiving per
worker), t_example a worker's CPU time per example (the least over w), and prints t(w) for more
workers than were measured, assuming a core for each worker and one for this process. Every evaluation gives the same F and gradient as
here, bit for bit (checked).

    python benchmarks/cluster_optimisation.py --data ../shared/data/hippocampus/labels \\
        --shapes 400 --workers 1 2 4
"""

from __future__ import annotations

import argparse
import copy
import pickle
import time
from pathlib import Path

import numpy as np


def population(prepared: list, config, n_s: int):
    """A state of ``n_s`` examples, copies of the initial correspondence of ``prepared`` in
    turn, with the build's integrated objective."""
    from mdlshapemodel.correspondence.initial import initial_state
    from mdlshapemodel.correspondence.state import CorrespondenceState

    state, (_, integrated), _, _ = initial_state(prepared, config)
    examples = []
    for k in range(n_s):
        example = copy.deepcopy(state.examples[k % len(state.examples)])
        example.name = f"copy_{k}"
        examples.append(example)
    return CorrespondenceState(examples, state.grids, integrated, scaling=state.scaling)


def evaluations(state, round_, parameters: list) -> tuple[list, dict]:
    """(F, dF/dx) at each of ``parameters`` after the first, and the seconds of the pieces."""
    from mdlshapemodel.correspondence.strategies.fast import gradient_at

    results, seconds = [], {"wall": 0.0, "cpu": 0.0, "central": 0.0}
    for k, x in enumerate(parameters):
        wall, cpu = time.perf_counter(), time.process_time()
        trial = round_.trial(x, ())
        central = time.process_time()
        value, shape_gradient = gradient_at(state, trial.shapes)
        central = time.process_time() - central
        gradient = round_.gradient(trial, shape_gradient)
        if k:
            seconds["wall"] += time.perf_counter() - wall
            seconds["cpu"] += time.process_time() - cpu
            seconds["central"] += central
            results.append((value, gradient))
    return results, {key: value / (len(parameters) - 1) for key, value in seconds.items()}


def worker_cpu(client) -> dict:
    """CPU seconds of each worker process so far."""
    return client.run(time.process_time)


def measure_here(state, level: int, parameters: list, threads: int) -> tuple[list, dict]:
    from mdlshapemodel.correspondence.strategies.fast import FieldRound
    from mdlshapemodel.parallel import Threads

    with Threads(threads) as pool:
        round_ = FieldRound(state, range(state.n_shapes), level, 2.0, pool)
        return evaluations(state, round_, parameters)


def measure_cluster(state, level: int, parameters: list, workers: int) -> tuple[list, dict]:
    from distributed import Client, LocalCluster

    from mdlshapemodel.correspondence.strategies.fast import FieldRound
    from mdlshapemodel.correspondence.strategies.spread import ExamplesOnCluster

    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                      dashboard_address=None, host="127.0.0.1") as cluster, \
            Client(cluster) as client:
        started = time.perf_counter()
        with ExamplesOnCluster(client, state, range(state.n_shapes)) as examples:
            held = time.perf_counter() - started
            round_ = FieldRound(state, range(state.n_shapes), level, 2.0, examples=examples)
            # the first evaluation (not counted) loads the kernels in the workers
            results, _ = evaluations(state, round_, parameters[:2])
            before = worker_cpu(client)
            results, seconds = evaluations(state, round_, parameters)
            after = worker_cpu(client)
    spent = [(after[w] - before[w]) / len(parameters) for w in after]
    seconds.update(worker=max(spent), held=held)
    return results, seconds


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="a folder of label maps")
    parser.add_argument("--label", default="1", help="labels of the object (default 1)")
    parser.add_argument("--base", type=int, default=20, help="cases prepared")
    parser.add_argument("--shapes", type=int, default=400, help="examples in the population")
    parser.add_argument("--points", type=int, default=642)
    parser.add_argument("--level", type=int, default=3, help="field level (3: 642 bumps)")
    parser.add_argument("--threads", type=int, default=1, help="threads here")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    from threadpoolctl import threadpool_limits

    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.prepare.batch import preprocess

    config = BuildConfig(labels=tuple(int(x) for x in args.label.split(",")),
                         points=args.points, workers=2)
    inputs = sorted(Path(args.data).glob("*.nii.gz"))[:args.base]
    prepared, _ = preprocess(inputs, config)
    state = population(prepared, config, args.shapes)
    rng = np.random.default_rng(0)
    with threadpool_limits(limits=1, user_api="blas"):
        from mdlshapemodel.correspondence.strategies.fast import FieldRound

        limit = FieldRound(state, range(state.n_shapes), args.level, 2.0).limit
        parameters = []
        for _ in range(args.repeat + 1):
            x = 0.1 * limit * rng.uniform(-1.0, 1.0, len(limit))
            x[~np.isfinite(x)] = 0.0
            parameters.append(x)
        reference, here = measure_here(state, args.level, parameters, args.threads)
        n_s, n_p = state.n_shapes, state.n_points
        sent = (len(limit) * 8 + n_s * n_p * 3 * 8) / 2 ** 20      # x, then dF/dX rows
        received = (n_s * n_p * 3 * 8 + len(limit) * 8) / 2 ** 20  # samples, then gradients
        print(f"n_s = {n_s}, n_p = {n_p}, level {args.level}: {len(limit)} parameters; "
              f"an example's parts pickle to "
              f"{len(pickle.dumps(state.examples[0].parts)) / 2 ** 20:.2f} MB; per evaluation "
              f"{sent:.1f} MB sent to the workers and {received:.1f} MB back")
        print(f"{'where':>10} {'wall ms':>9} {'CPU here ms':>12} {'F, dF/dX ms':>12}"
              f" {'worker CPU ms':>14} {'held s':>7}  same as here")
        print(f"{'here':>10} {1e3 * here['wall']:>9.1f} {1e3 * here['cpu']:>12.1f}"
              f" {1e3 * here['central']:>12.1f} {'-':>14} {'-':>7}  -", flush=True)
        measured = {}
        for w in args.workers:
            results, seconds = measure_cluster(state, args.level, parameters, w)
            same = all(a[0] == b[0] and np.array_equal(a[1], b[1])
                       for a, b in zip(results, reference))
            measured[w] = seconds
            print(f"{f'{w} workers':>10} {1e3 * seconds['wall']:>9.1f}"
                  f" {1e3 * seconds['cpu']:>12.1f} {1e3 * seconds['central']:>12.1f}"
                  f" {1e3 * seconds['worker']:>14.1f}"
                  f" {seconds['held']:>7.1f}  {'yes' if same else 'NO'}", flush=True)
    workers = np.array(sorted(measured), dtype=float)
    here_cpu = np.array([measured[w]["cpu"] for w in sorted(measured)])
    comm, central = (np.polyfit(workers, here_cpu, 1) if len(workers) > 1
                     else (0.0, here_cpu[0]))
    # the least per example: a worker's CPU time also holds its own event loop's, which grows
    # with the wall time of the evaluation (on a loaded machine, with many workers)
    example = min(measured[w]["worker"] * w / n_s for w in measured)
    print(f"model t(w) = t_central + t_example n_s / w + t_comm w (CPU seconds, a core each): "
          f"t_central = {1e3 * central:.1f} ms, t_example = {1e3 * example:.3f} ms, "
          f"t_comm = {1e3 * comm:.2f} ms per worker")
    print(" ".join(f"t({w}) = {1e3 * (central + example * n_s / w + comm * w):.0f} ms"
                   for w in (1, 2, 4, 8, 16, 32, 64)))
    if comm > 0:
        print(f"fastest at w = sqrt(t_example n_s / t_comm) = {np.sqrt(example * n_s / comm):.0f}"
              " workers")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
