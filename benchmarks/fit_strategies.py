"""Fitting held-out hippocampi to a model: each optimisation strategy's objective, reconstruction
error and time.

Builds (once; reused when OUTPUT/model holds it) a model of the first N shared hippocampus label
maps (labels 1+2, build defaults), then fits the next K maps to it with each strategy in
``--strategies`` (the same preprocessing, the same budget) and prints, per strategy, the mean over
the held-out cases of: eq. 14 of the training set with the case added, before and after the
optimisation of the case; the reconstruction error with 1, 3, 10 and all modes (area-weighted
mean squared point distance, mm^2); the evaluations and seconds of the fit.

    python benchmarks/fit_strategies.py --cases 40 --held-out 5 --output /tmp/fit40
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "hippocampus" / "labels"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=40, help="training cases")
    parser.add_argument("--held-out", type=int, default=5)
    parser.add_argument("--data", default=str(DATA))
    parser.add_argument("--strategies", default="one-at-a-time-pose,fast")
    parser.add_argument("--max-time", type=float, default=60.0, help="seconds per fit")
    parser.add_argument("--output", default="fit-benchmark")
    args = parser.parse_args()

    from mdlshapemodel import BuildConfig, build_model
    from mdlshapemodel.folders import BuildFolder
    from mdlshapemodel.model.fitting import build_config_of, fit_case
    from mdlshapemodel.prepare import prepare_case

    paths = sorted(Path(args.data).glob("*.nii.gz"))
    if len(paths) < args.cases + args.held_out:
        print(f"{args.data}: fewer than {args.cases + args.held_out} label maps", file=sys.stderr)
        return 2
    training, held_out = paths[:args.cases], paths[args.cases:args.cases + args.held_out]
    folder = Path(args.output) / "model"
    if not (folder / "model.h5").exists():
        started = time.perf_counter()
        build_model([str(p) for p in training], folder, BuildConfig(labels=[1, 2]))
        print(f"model of {len(training)} cases built in {time.perf_counter() - started:.0f} s")
    model = BuildFolder(folder).model()
    config = build_config_of(model)
    prepared = [prepare_case(str(p), config) for p in held_out]
    columns = [m for m in (1, 3, 10) if m <= model.n_modes] + [model.n_modes]
    print(f"{len(held_out)} held-out cases, {args.max_time:.0f} s budget per fit\n")
    print(f"{'strategy':<20} {'eq. 14 before':>13} {'after':>10} "
          + " ".join(f"{'E(' + str(m) + ')':>8}" for m in columns)
          + f" {'evaluations':>11} {'seconds':>8}")
    for strategy in [s for s in args.strategies.split(",") if s]:
        rows = []
        for path, case in zip(held_out, prepared):
            result = fit_case(model, path, config, max_time=args.max_time, prepared=case,
                              strategy=strategy)
            rows.append([result.objective["initial"], result.objective["final"]]
                        + [result.squared_error[m] for m in columns]
                        + [result.objective["evaluations"], result.objective["seconds"]])
        mean = np.mean(rows, axis=0)
        print(f"{strategy:<20} {mean[0]:>13.2f} {mean[1]:>10.2f} "
              + " ".join(f"{v:>8.4f}" for v in mean[2:-2])
              + f" {mean[-2]:>11.0f} {mean[-1]:>8.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
