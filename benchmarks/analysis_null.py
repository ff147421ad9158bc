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
share of point p-values at or below alpha; it should be alpha), the family-wise error by the
maximum statistic (the share of data sets with any point family-wise significant; it should be
alpha, within 2 SE, SE = sqrt(alpha (1 - alpha) / replicates)) and the share with any FDR
discovery (under the complete null of independent points, Benjamini-Hochberg's is alpha). With
``--min-p-permutations B`` (0: not run), also the family-wise error of the variance groups by
min-p with B permutations (B well above points / alpha).

``--effect D``: power instead of the null: the larger group's mean shifted by D SDs at the
first 10 points; per design, the share of those points family-wise significant and the share of
data sets with one of them family-wise (FDR) significant.

``--build DIR``: real shapes instead: the build's cases, ``--small`` of them drawn at random
``--splits`` times and their deviations from the mean of all cases scaled by ``--ratio`` (no
difference of mean shape in expectation), each split analysed with
:func:`mdlshapemodel.analysis.analyze_shapes` (normal displacement) pooled and with a variance
per group; prints the share of splits with any point family-wise significant and the mean share
of points with p <= alpha.

Examples (the tables in docs/analysis.md; seeds fixed)::

    python benchmarks/analysis_null.py --replicates 300
    python benchmarks/analysis_null.py --replicates 100 --min-p-permutations 4999
    python benchmarks/analysis_null.py --build hip20 --splits 60
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
# with --effect, the larger group's mean is shifted at this many points
EFFECT_POINTS = 10


def data_set(rng, small: int, large: int, ratio: float, errors: str, points: int,
             nuisance: bool, effect: float = 0.0):
    """One null data set: (y (n, points), group indicator (n, 1), nuisance (n, c) or None,
    groups (n,))."""
    n = small + large
    groups = np.r_[np.zeros(small), np.ones(large)]
    if errors == "normal":
        noise = rng.normal(size=(n, points))
    else:
        noise = rng.standard_t(3, size=(n, points)) / np.sqrt(3.0)
    y = noise * np.where(groups == 0, ratio, 1.0)[:, None]
    y[:, :EFFECT_POINTS] += effect * groups[:, None]
    columns = None
    if nuisance:
        standard = (groups - groups.mean()) / groups.std()
        columns = 0.6 * standard[:, None] + rng.normal(size=(n, NUISANCE_COLUMNS))
        y = y + columns.sum(axis=1)[:, None]
    return y, groups[:, None], columns, groups


def rates(args, small, large, ratio, errors, nuisance) -> dict:
    """Per-point rejection rate and family-wise error of each variant over the replicates."""
    rng = np.random.default_rng(args.seed)
    variants = [("pooled", None, "maximum", args.permutations),
                ("groups", True, "maximum", args.permutations)]
    if args.min_p_permutations:
        variants.append(("groups_min_p", True, "min-p", args.min_p_permutations))
    found = {name: [] for name, *_ in variants}
    for _ in range(args.replicates):
        y, group, columns, groups = data_set(rng, small, large, ratio, errors, args.points,
                                             nuisance, args.effect)
        seed = int(rng.integers(1 << 30))
        for name, by_group, family_wise, permutations in variants:
            result = permutation_test(y, group, columns, permutations, seed,
                                      variance_groups=groups if by_group else None,
                                      family_wise=family_wise)
            if args.effect:
                hits = result.p_fwer[:EFFECT_POINTS] <= args.alpha
                found[name].append((np.mean(hits), bool(np.any(hits)),
                                    bool(np.any(result.q_fdr[:EFFECT_POINTS] <= args.alpha))))
            else:
                found[name].append((np.mean(result.p <= args.alpha),
                                    bool(np.any(result.p_fwer <= args.alpha)),
                                    bool(np.any(result.q_fdr <= args.alpha))))
    return {name: np.mean(values, axis=0) for name, values in found.items()}


def real_shapes(args):
    """The null with unequal variances on a build's shapes (``--build``)."""
    import csv
    import tempfile
    from pathlib import Path

    from mdlshapemodel.analysis import analyze_shapes, read_build, subjects
    from mdlshapemodel.config import AnalysisConfig

    built = read_build(args.build)
    names = list(built.model.names)
    rng = np.random.default_rng(args.seed)
    found = {"pooled": [], "groups": []}
    table = Path(tempfile.mkdtemp()) / "split.csv"
    for split in range(args.splits):
        chosen = rng.permutation(len(names)) < args.small
        with open(table, "w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(["case", "group"])
            writer.writerows([name, "small" if c else "large"] for name, c in zip(names, chosen))
        shapes = built.shapes.copy()
        mean = shapes.mean(axis=0)
        shapes[chosen] = mean + args.ratio * (shapes[chosen] - mean)
        design = subjects(table, names, group="group")
        for variance in found:
            config = AnalysisConfig(group="group", permutations=args.permutations,
                                    variance=variance, seed=split, alpha=args.alpha)
            points = analyze_shapes(built.model, shapes, design, config).points
            found[variance].append((bool(np.any(points.p_fwer <= args.alpha)),
                                    float(np.mean(points.p <= args.alpha))))
    for variance, values in found.items():
        values = np.array(values)
        print(f"{variance}: any point family-wise significant in {values[:, 0].mean():.3f} of "
              f"{args.splits} splits; points with p <= {args.alpha}: {values[:, 1].mean():.4f}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--replicates", type=int, default=300)
    parser.add_argument("--points", type=int, default=100)
    parser.add_argument("--permutations", type=int, default=999)
    parser.add_argument("--min-p-permutations", type=int, default=0,
                        help="also min-p with this many permutations (0: not run; min-p needs "
                             "B well above points / alpha)")
    parser.add_argument("--alpha", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=2014)
    parser.add_argument("--effect", type=float, default=0.0,
                        help="power instead: the larger group shifted by this many (larger "
                             "group) SDs at the first 10 points; the columns become the share "
                             "of those points family-wise significant and the share of data sets "
                             "with one of them significant (family-wise, FDR)")
    parser.add_argument("--build", help="real shapes: a build's output folder")
    parser.add_argument("--splits", type=int, default=60)
    parser.add_argument("--small", type=int, default=5, help="cases of the scaled group")
    parser.add_argument("--ratio", type=float, default=3.0)
    args = parser.parse_args()
    if args.build:
        real_shapes(args)
        return
    se = np.sqrt(args.alpha * (1 - args.alpha) / args.replicates)
    print(f"{args.replicates} replicates of {args.points} independent points; "
          f"alpha {args.alpha}; SE of a family-wise rate {se:.4f}; "
          f"{args.permutations} permutations")
    extra = " FWER, variance groups, min-p |" if args.min_p_permutations else ""
    if args.effect:
        print(f"power: the larger group shifted by {args.effect:g} SD at {EFFECT_POINTS} points")
        print("| groups (SD ratio) | errors | nuisance | shifted points found, pooled | shifted "
              "points found, variance groups | any found (FWER), pooled | any found (FWER), "
              "variance groups | any found (FDR), pooled | any found (FDR), variance groups |"
              + extra)
    else:
        print("| groups (SD ratio) | errors | nuisance | per point, pooled | per point, variance "
              "groups | FWER, pooled | FWER, variance groups | any FDR, pooled | any FDR, "
              "variance groups |" + extra)
    print("|---|---|---|---|---|---|---|---|---|" + ("---|" if extra else ""))
    for small, large, ratio in DESIGNS:
        for errors in ERRORS:
            for nuisance in (False, True):
                start = time.perf_counter()
                found = rates(args, small, large, ratio, errors, nuisance)

                def rate(name, column=1):
                    value = found[name][column]
                    if args.effect:
                        return f"{value:.3f}"
                    return f"{value:.3f} ({(value - args.alpha) / se:+.1f} SE)"

                print(f"| {small} vs {large} ({ratio:g}) | {errors} | "
                      f"{'3 columns' if nuisance else 'none'} | {found['pooled'][0]:.4f} | "
                      f"{found['groups'][0]:.4f} | {rate('pooled')} | {rate('groups')} | "
                      f"{rate('pooled', 2)} | {rate('groups', 2)} |"
                      + (f" {rate('groups_min_p')} |" if args.min_p_permutations else ""),
                      flush=True)
                print(f"{time.perf_counter() - start:.0f} s", file=sys.stderr, flush=True)


if __name__ == "__main__":
    main()
