"""What a build holds per case: the bytes of the prepared cases, of the optimisation state's
examples (surfaces, sphere maps, locators, samples) and of the evaluation's inputs, measured on N
label maps, and extrapolated linearly to a larger population.

Each holder is measured twice: the numpy arrays it references (``nbytes``, each array once) and
the growth of the traced Python heap while it is made (``tracemalloc``, which sees numpy's and
scipy's buffers too, and what the making leaves behind). The cases are prepared through the
build's own cache (``--cache-dir``), so a second run measures without preparing again.

    python benchmarks/case_memory.py --data /tmp/pop1000/labels --label 1 --cases 200 \\
        --cache-dir /tmp/popcache --extrapolate 10000
"""

from __future__ import annotations

import argparse
import gc
import resource
import sys
import tracemalloc
from pathlib import Path

import numpy as np


def array_bytes(root) -> int:
    """Bytes of the numpy arrays reachable from ``root`` through attributes, lists, tuples and
    dicts (each array counted once; views count their base)."""
    seen, total, stack = set(), 0, [root]
    while stack:
        item = stack.pop()
        if id(item) in seen or item is None or isinstance(item, (str, bytes, int, float)):
            continue
        seen.add(id(item))
        if isinstance(item, np.ndarray):
            base = item if item.base is None else item.base
            if id(base) not in seen or base is item:
                seen.add(id(base))
                total += base.nbytes if isinstance(base, np.ndarray) else item.nbytes
            continue
        if isinstance(item, dict):
            stack.extend(item.values())
        elif isinstance(item, (list, tuple, set)):
            stack.extend(item)
        elif hasattr(item, "__dict__"):
            stack.extend(vars(item).values())
        elif hasattr(item, "__slots__"):
            stack.extend(getattr(item, name, None) for name in item.__slots__)
        else:
            for name in ("data", "tree"):      # scipy's cKDTree keeps its points as .data
                if hasattr(item, name):
                    stack.append(getattr(item, name))
    return total


def traced(make):
    """(result, bytes the traced heap grew by while ``make`` ran and still holds)."""
    gc.collect()
    before = tracemalloc.get_traced_memory()[0]
    result = make()
    gc.collect()
    return result, tracemalloc.get_traced_memory()[0] - before


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="folder of label maps (*.nii.gz)")
    parser.add_argument("--label", default="1")
    parser.add_argument("--cases", type=int, default=200)
    parser.add_argument("--cache-dir", required=True)
    parser.add_argument("--extrapolate", type=int, default=10000)
    parser.add_argument("--specificity-samples", type=int, default=1000,
                        help="for the evaluation (of M = 1, 2 modes and 50 samples surface to "
                             "surface: its memory grows with the cases, not with these)")
    args = parser.parse_args()
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.correspondence.initial import initial_state
    from mdlshapemodel.model.evaluation import evaluate_state
    from mdlshapemodel.prepare.batch import preprocess

    inputs = sorted(Path(args.data).glob("*.nii.gz"))[:args.cases]
    if len(inputs) < args.cases:
        print(f"only {len(inputs)} label maps in {args.data}", file=sys.stderr)
        return 2
    config = BuildConfig(labels=[int(v) for v in args.label.split(",")],
                         cache_dir=args.cache_dir, workers=2,
                         specificity_samples=args.specificity_samples, evaluation_modes=2,
                         surface_samples=50)
    prepared, rejected = preprocess([str(p) for p in inputs], config)   # fills the cache
    del prepared
    n = args.cases - len(rejected)
    tracemalloc.start()
    prepared, prepared_traced = traced(
        lambda: preprocess([str(p) for p in inputs], BuildConfig(**{**vars(config),
                                                                   "workers": 1}))[0])
    (state, *_), state_traced = traced(lambda: initial_state(prepared, config))
    rows = [("prepared cases (PreparedCase)", array_bytes(prepared), prepared_traced),
            ("optimisation state (CorrespondenceState)", array_bytes(state), state_traced)]
    _, released = traced(state.release_sampling)
    rows.append(("state after release_sampling (change)", -0, released))
    surfaces, surfaces_traced = traced(lambda: [
        (state.to_model_frame(i, vertices), faces)
        for i, (vertices, faces) in enumerate(case.surface() for case in prepared)])
    rows.append(("evaluation's true surfaces (model frame)", array_bytes(surfaces),
                 surfaces_traced))
    del surfaces
    # the model's evaluation, here (no pool): the peak of the traced heap above what was held
    gc.collect()
    held = tracemalloc.get_traced_memory()[0]
    tracemalloc.reset_peak()
    evaluate_state(state, config, prepared, background=False)
    rows.append(("evaluation, its peak above what was held", 0,
                 tracemalloc.get_traced_memory()[1] - held))
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    print(f"{n} cases, {state.n_points} points each; ru_maxrss "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB, traced peak "
          f"{peak / 2**20:.0f} MB\n")
    print(f"| holder | arrays per case | traced per case | x {args.extrapolate} (traced) |")
    print("|---|---|---|---|")
    for name, arrays, grown in rows:
        print(f"| {name} | {arrays / n / 1024:.0f} KB | {grown / n / 1024:.0f} KB | "
              f"{grown / n * args.extrapolate / 2**30:.2f} GB |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
