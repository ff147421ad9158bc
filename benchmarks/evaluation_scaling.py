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

``--drawn`` sizes measure the objective piece alone on larger populations, drawn without
preparing them: the first ``--base`` cases' initial correspondence gives a mean and its
deviations; each drawn shape is the mean plus a Gaussian combination of the deviations (the
cases' covariance) plus independent noise of ``--noise`` mm at every coordinate (so that the
population has all 3 n_p modes, as a large one does). For each size it times one evaluation of F
and dF/dX as a build makes it (``CorrespondenceState.shape_gradient``, one BLAS thread) and the
two routes to eq. 14 and dF/dA, through the n_s x n_s Gram matrix (up to ``--gram-up-to`` shapes)
and through the 3 n_p x 3 n_p covariance, each in CPU seconds with its peak of allocated memory
(tracemalloc), and the process's peak resident memory at the end:

    python benchmarks/evaluation_scaling.py --data ../shared/data/hippocampus/labels --sizes \
        --drawn 500 1000 2000 3000 5000 10000 | tee /tmp/drawn.txt
    python benchmarks/evaluation_scaling.py --plot /tmp/drawn.txt docs/evaluation-scaling.png
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


def peak(function) -> tuple[float, float, object]:
    """CPU seconds of this process (one BLAS thread: the work, whatever else the machine runs),
    peak of memory allocated (MB, tracemalloc) and result of one call."""
    import tracemalloc

    tracemalloc.start()
    started = time.process_time()
    result = function()
    seconds = time.process_time() - started
    peak_bytes = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return seconds, peak_bytes / 2 ** 20, result


def drawn_state(prepared: list, config, n_s: int, noise: float, seed: int = 0):
    """A state of ``n_s`` shapes drawn around the initial correspondence of ``prepared``, with
    the build's integrated objective."""
    from mdlshapemodel.correspondence.initial import initial_state
    from mdlshapemodel.correspondence.state import CorrespondenceState, FixedExample

    state, (_, integrated), _, _ = initial_state(prepared, config)
    shapes = state.aligned_shapes()
    mean = shapes.mean(axis=0)
    deviations = (shapes - mean).reshape(len(shapes), -1) / np.sqrt(len(shapes))
    rng = np.random.default_rng(seed)
    examples = []
    for k in range(n_s):
        shape = (mean.ravel() + rng.normal(size=len(shapes)) @ deviations
                 + noise * rng.normal(size=mean.size))
        examples.append(FixedExample(f"drawn_{k}", shape.reshape(mean.shape)))
    return CorrespondenceState(examples, state.grids, integrated, scaling=state.scaling)


def scaled_data(state) -> np.ndarray:
    """A with D' = A A^T: the shapes centred, times sqrt(w) and the rescaling to the target size."""
    from mdlshapemodel.geometry import centroid_size

    mean = state.shapes.mean(axis=0)
    factor = state.target_size / centroid_size(mean, state.weights)
    data = (state.shapes - mean) * (factor * np.sqrt(state.weights))[None, :, None]
    return data.reshape(state.n_shapes, -1)


def measure_drawn(prepared: list, config, sizes: list, noise: float, gram_up_to: int,
                  repeat: int):
    """Print, per drawn size, the state's evaluation and the two routes (seconds, peak MB)."""
    from threadpoolctl import threadpool_limits

    print(f"{'n_s':>6} {'route':>10} {'eval. CPU s':>13} {'peak MB':>8} {'ms/shape':>9}"
          f" {'Gram s':>7} {'Gram MB':>8} {'covariance s':>13} {'cov. MB':>8}")
    for n_s in sizes:
        state = drawn_state(prepared, config, n_s, noise)
        objective = state.objective
        data = scaled_data(state)
        with threadpool_limits(limits=1, user_api="blas"):
            runs = [peak(state.shape_gradient) for _ in range(repeat)]
            seconds = float(np.median([r[0] for r in runs]))
            memory = max(r[1] for r in runs)
            covariance = peak(lambda: objective.data_gradient(data))
            gram = (peak(lambda: objective.gradient(data @ data.T)[1] @ data)
                    if n_s <= gram_up_to else None)
        route = "covariance" if state.by_covariance else "Gram"
        del state, data
        print(f"{n_s:>6} {route:>10} {seconds:>13.3f} {memory:>8.0f} {1e3 * seconds / n_s:>9.3f}"
              + (f" {gram[0]:>7.2f} {gram[1]:>8.0f}" if gram else f" {'-':>7} {'-':>8}")
              + f" {covariance[0]:>13.2f} {covariance[1]:>8.0f}", flush=True)
    import resource
    print(f"peak resident memory of the process: "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 10:.0f} MB")


def plot_drawn(table: Path, output: Path):
    """Plot the drawn sizes' table that ``--drawn`` printed (saved in ``table``): CPU seconds of
    one evaluation against n_s, the state's and the two routes'."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [line.split() for line in table.read_text().splitlines()
            if line.split() and line.split()[0].isdigit()]
    n_s = np.array([int(r[0]) for r in rows])
    state = np.array([float(r[2]) for r in rows])
    gram = [(n, float(r[5])) for n, r in zip(n_s, rows) if r[5] != "-"]
    covariance = np.array([float(r[7]) for r in rows])
    figure, axes = plt.subplots(figsize=(6.4, 4.0))
    axes.plot(n_s, state, "o-", color="black", label="one evaluation (the state's route)")
    axes.plot(*zip(*gram), "s--", color="tab:red", label="eq. 14 + dF/dA via the Gram matrix")
    axes.plot(n_s, covariance, "^--", color="tab:blue", label="eq. 14 + dF/dA via A^T A")
    axes.set_xlabel("shapes n_s (642 points: 3 n_p = 1926)")
    axes.set_ylabel("CPU seconds (one BLAS thread)")
    axes.axvline(1926, color="grey", linewidth=0.8)
    axes.legend(frameon=False)
    figure.tight_layout()
    figure.savefig(output, dpi=110)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", help="a folder of label maps (needed but with --plot)")
    parser.add_argument("--label", default="1", help="labels of the object (default 1)")
    parser.add_argument("--sizes", type=int, nargs="*", default=[100, 250, 500, 1000],
                        help="numbers of prepared cases (none: the drawn sizes only)")
    parser.add_argument("--points", type=int, default=642)
    parser.add_argument("--level", type=int, default=3, help="field level (3: 642 bumps)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--drawn", type=int, nargs="*", default=[],
                        help="population sizes drawn around the first --base cases")
    parser.add_argument("--base", type=int, default=40, help="cases the drawn ones are drawn from")
    parser.add_argument("--noise", type=float, default=0.05, help="mm, per coordinate (drawn)")
    parser.add_argument("--gram-up-to", type=int, default=3000,
                        help="largest drawn size also measured through the Gram matrix")
    parser.add_argument("--plot", nargs=2, metavar=("TABLE", "PNG"),
                        help="only plot a --drawn table (the printed output, saved) to PNG")
    args = parser.parse_args()
    if args.plot:
        plot_drawn(Path(args.plot[0]), Path(args.plot[1]))
        return 0
    if args.data is None:
        parser.error("--data is needed")
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.prepare.batch import preprocess

    config = BuildConfig(labels=tuple(int(x) for x in args.label.split(",")),
                         points=args.points, workers=2)
    inputs = sorted(Path(args.data).glob("*.nii.gz"))
    if args.drawn:
        prepared, _ = preprocess(inputs[:args.base], config)
        measure_drawn(prepared, config, args.drawn, args.noise, args.gram_up_to,
                      min(args.repeat, 3))
    if args.sizes:
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
