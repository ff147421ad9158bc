"""The time of the generalization G(M) and of its jackknife (for the baselines' paired
differences) with every case left out and with a random subset of them
(``BuildConfig.generalization_cases``), on n_s shapes drawn from a model (its modes' scores
b_m ~ N(0, lambda_m), plus 0.2 mm of independent noise per coordinate), BLAS on one thread as
in a build's evaluation.

    python benchmarks/generalization_subset.py --model /tmp/h82/model.h5 --sizes 1000 2000
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000])
    parser.add_argument("--subset", type=int, default=None,
                        help="cases left out (default: BuildConfig's generalization_cases)")
    parser.add_argument("--modes", type=int, default=10)
    parser.add_argument("--full", action="store_true",
                        help="also every case left out (grows as n_s^2 n_p; the jackknife as "
                             "n_s^3)")
    args = parser.parse_args()
    from threadpoolctl import threadpool_limits

    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.model.evaluation import (generalization, generalization_jackknife,
                                                leave_out_cases)
    from mdlshapemodel.model.shape_model import ShapeModel
    from mdlshapemodel.model.space import model_space

    model = ShapeModel.load(args.model)
    subset = args.subset or BuildConfig().generalization_cases
    print("| n_s | left out | model space | G(M) | jackknife | G(1) mm² ± SE (subset's part) |")
    print("|---|---|---|---|---|---|")
    for n_s in args.sizes:
        rng = np.random.default_rng(n_s)
        scores = rng.standard_normal((n_s, model.n_modes)) * np.sqrt(model.variances)
        shapes = np.stack([model.instance(s) for s in scores])
        shapes += rng.normal(scale=0.2, size=shapes.shape)
        with threadpool_limits(limits=1, user_api="blas"):
            started = time.perf_counter()
            space = model_space(shapes, model.weights)
            spaced = time.perf_counter() - started
            choices = [leave_out_cases(n_s, subset, np.random.default_rng(0))]
            if args.full:
                choices.append(None)
            for cases in choices:
                started = time.perf_counter()
                g = generalization(shapes, model.weights, args.modes, space, cases)
                measured = time.perf_counter() - started
                started = time.perf_counter()
                generalization_jackknife(space, args.modes, cases=cases)
                jackknifed = time.perf_counter() - started
                part = (f" ({g['squared_subsample_se'][0]:.4f})"
                        if "squared_subsample_se" in g else "")
                print(f"| {n_s} | {n_s if cases is None else len(cases)} | {spaced:.1f} s | "
                      f"{measured:.1f} s | {jackknifed:.1f} s | {g['squared'][0]:.4f} ± "
                      f"{g['squared_se'][0]:.4f}{part} |", flush=True)


if __name__ == "__main__":
    main()
