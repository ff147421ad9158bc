"""How often ``mdlshapemodel compare`` calls two correspondences' generalization different: false
positives when they are equally good, power when one is noisier.

The truth is a real build's corresponded shapes (its model.h5, in the model frame). Each trial
draws ``--cases`` of them, makes two correspondences of those cases by adding independent
Gaussian noise to every point (sd ``--sigma`` mm, and ``ratio`` times that for the second) and
asks compare's rule (two standard errors of the difference) at M = 1..``--modes``, with the
jackknife standard error that compare uses (``--groups`` sets where its groups begin) and with the
per-case differences' own spread.

    python benchmarks/compare_calibration.py /tmp/h82/default --cases 15 --trials 200
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mdlshapemodel.model.evaluation import (JACKKNIFE_GROUPS, generalization_difference,
                                           generalization_jackknife)
from mdlshapemodel.model.space import model_space
from mdlshapemodel.compare import load_population


def trial(shapes, weights, rng, cases, sigma, ratio, modes, groups):
    """(significant by the jackknife, significant by the per-case spread), each (modes,)."""
    chosen = shapes[rng.choice(len(shapes), cases, replace=False)]
    a = chosen + rng.normal(0.0, sigma, chosen.shape)
    b = chosen + rng.normal(0.0, ratio * sigma, chosen.shape)
    result = generalization_difference(
        *[generalization_jackknife(model_space(c, weights), modes, groups) for c in (a, b)])
    magnitude = np.abs(result["difference"])
    return magnitude > 2 * result["se"], magnitude > 2 * result["paired_se"]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("build", help="a build's output folder (its model.h5 is the truth)")
    parser.add_argument("--cases", type=int, nargs="+", default=[10, 15, 30])
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--sigma", type=float, default=0.3, help="noise sd, mm (default 0.3)")
    parser.add_argument("--ratios", type=float, nargs="+", default=[1.0, 1.1])
    parser.add_argument("--modes", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--groups", type=int, default=JACKKNIFE_GROUPS,
                        help="the jackknife's groups beyond this many cases (default: compare's, "
                             "%(default)s)")
    args = parser.parse_args()
    population = load_population(args.build)
    print(f"truth: {population.label}, {len(population.names)} cases, "
          f"{population.shapes.shape[1]} points; noise sd {args.sigma} mm; {args.trials} trials; "
          f"the jackknife in {args.groups} groups beyond {args.groups} cases")
    print("cases  ratio  called different at M = 1..%d: jackknife | per-case spread   seconds"
          % args.modes)
    for cases in args.cases:
        for ratio in args.ratios:
            rng = np.random.default_rng(args.seed)
            started = time.perf_counter()
            counts = np.zeros((2, args.modes))
            for _ in range(args.trials):
                counts += np.array(trial(population.shapes, population.weights, rng, cases,
                                         args.sigma, ratio, args.modes, args.groups))
            rates = counts / args.trials
            print(f"{cases:5d}  {ratio:5.2f}  {' '.join(f'{r:5.3f}' for r in rates[0])} | "
                  f"{' '.join(f'{r:5.3f}' for r in rates[1])}   "
                  f"{time.perf_counter() - started:.0f}", flush=True)


if __name__ == "__main__":
    main()
