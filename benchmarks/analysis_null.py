"""The per-point test under the null: does it reject at its level when the groups differ in
spread and size, the errors are heavy-tailed, or nuisance columns go with the groups?

Synthetic independent null points (no group effect anywhere) through the public API,
:func:`mdlshapemodel.analysis.permutation_test`: for each design, ``--replicates`` data sets of
``--points`` points; the smaller group's errors have ``ratio`` times the larger group's SD. With
nuisance, three columns correlated with the groups (correlation about 0.5) that do move the data
(one unit each), so that what the test adjusts for must not leak into it. Errors normal, or
Student's t with 3 degrees of freedom scaled to unit variance (heavy tails).

Printed per design, for the pooled statistic (one variance for all cases, t^2 / F) and for the
statistic with a variance per group (Welch's v^2): the per-point rejection rate at alpha (the
share of point p-values at or below alpha; it should be alpha) and the family-wise error (the
share of data sets with any point family-wise significant; it should be alpha, within 2 SE,
SE = sqrt(alpha (1 - alpha) / replicates)), by the maximum statistic and, for the variance
groups, by min-p.

Example (the table in docs/analysis.md; seeds fixed)::

    python benchmarks/analysis_null.py --replicates 300
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from mdlshapemodel.analysis import permutation_test

# (smaller group, larger group, SD of the smaller group over the larger's)
DESIGNS = ((6, 24, 3.0), (10, 30, 1.5), (20, 20, 1.0))
ERRORS = ("normal", "t3")
NUISANCE_COLUMNS = 3


def data_set(rng, small: int, large: int, ratio: float, errors: str, points: int,
             nuisance: bool):
    """One null data set: (y (n, points), group indicator (n, 1), nuisance (n, c) or None,
    groups (n,))."""
    n = small + large
    groups = np.r_[np.zeros(small), np.ones(large)]
    if errors == "normal":
        noise = rng.normal(size=(n, points))
    else:
        noise = rng.standard_t(3, size=(n, points)) / np.sqrt(3.0)
    y = noise * np.where(groups == 0, ratio, 1.0)[:, None]
    columns = None
    if nuisance:
        standard = (groups - groups.mean()) / groups.std()
        columns = 0.6 * standard[:, None] + rng.normal(size=(n, NUISANCE_COLUMNS))
        y = y + columns.sum(axis=1)[:, None]
    return y, groups[:, None], columns, groups


def rates(args, small, large, ratio, errors, nuisance) -> dict:
    """Per-point rejection rate and family-wise error of each variant over the replicates."""
    rng = np.random.default_rng(args.seed)
    found = {"pooled": [], "groups": [], "groups_min_p": []}
    for _ in range(args.replicates):
        y, group, columns, groups = data_set(rng, small, large, ratio, errors, args.points,
                                             nuisance)
        seed = int(rng.integers(1 << 30))
        for name, variance_groups, family_wise, permutations in (
                ("pooled", None, "maximum", args.permutations),
                ("groups", groups, "maximum", args.permutations),
                ("groups_min_p", groups, "min-p", args.min_p_permutations)):
            result = permutation_test(y, group, columns, permutations, seed,
                                      variance_groups=variance_groups, family_wise=family_wise)
            found[name].append((np.mean(result.p <= args.alpha),
                                bool(np.any(result.p_fwer <= args.alpha))))
    return {name: np.mean(values, axis=0) for name, values in found.items()}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--replicates", type=int, default=300)
    parser.add_argument("--points", type=int, default=100)
    parser.add_argument("--permutations", type=int, default=999)
    parser.add_argument("--min-p-permutations", type=int, default=4999,
                        help="min-p needs B well above points / alpha")
    parser.add_argument("--alpha", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=2014)
    args = parser.parse_args()
    se = np.sqrt(args.alpha * (1 - args.alpha) / args.replicates)
    print(f"{args.replicates} replicates of {args.points} independent null points; "
          f"alpha {args.alpha}; SE of a family-wise rate {se:.4f}; "
          f"{args.permutations} permutations ({args.min_p_permutations} for min-p)")
    print("| groups (SD ratio) | errors | nuisance | per point, pooled | per point, variance "
          "groups | FWER, pooled | FWER, variance groups | FWER, variance groups, min-p |")
    print("|---|---|---|---|---|---|---|---|")
    for small, large, ratio in DESIGNS:
        for errors in ERRORS:
            for nuisance in (False, True):
                start = time.perf_counter()
                found = rates(args, small, large, ratio, errors, nuisance)

                def fwer(name):
                    value = found[name][1]
                    return f"{value:.3f} ({(value - args.alpha) / se:+.1f} SE)"

                print(f"| {small} vs {large} ({ratio:g}) | {errors} | "
                      f"{'3 columns' if nuisance else 'none'} | {found['pooled'][0]:.4f} | "
                      f"{found['groups'][0]:.4f} | {fwer('pooled')} | {fwer('groups')} | "
                      f"{fwer('groups_min_p')} |", flush=True)
                print(f"{time.perf_counter() - start:.0f} s", file=sys.stderr, flush=True)


if __name__ == "__main__":
    main()
