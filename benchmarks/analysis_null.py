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

``--tfce``: the points are the vertices of an icosphere (``--subdivisions``, radius 20 mm) and
each case's errors are smoothed over it (a Gaussian of ``--smoothing`` mm, rescaled to unit
variance per point), and every test also enhances its map by threshold-free cluster enhancement
(``analyze --tfce``); the table gives the family-wise error by the maximum statistic and by the
maximum of the enhanced maps, with variance groups, and pooled where the groups vary alike. Smoothing makes the Student's t
errors less heavy-tailed (a sum of several).

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
    python benchmarks/analysis_null.py --tfce --replicates 200 --permutations 499
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
             nuisance: bool, effect: float = 0.0, smoothing=None):
    """One null data set: (y (n, points), group indicator (n, 1), nuisance (n, c) or None,
    groups (n,)). ``smoothing`` (points, points): each case's errors smoothed by it."""
    n = small + large
    groups = np.r_[np.zeros(small), np.ones(large)]
    if errors == "normal":
        noise = rng.normal(size=(n, points))
    else:
        noise = rng.standard_t(3, size=(n, points)) / np.sqrt(3.0)
    if smoothing is not None:
        noise = noise @ smoothing.T
    y = noise * np.where(groups == 0, ratio, 1.0)[:, None]
    y[:, :EFFECT_POINTS] += effect * groups[:, None]
    columns = None
    if nuisance:
        standard = (groups - groups.mean()) / groups.std()
        columns = 0.6 * standard[:, None] + rng.normal(size=(n, NUISANCE_COLUMNS))
        y = y + columns.sum(axis=1)[:, None]
    return y, groups[:, None], columns, groups


def icosphere_smoothing(args):
    """The icosphere's surface and the matrix that smooths errors over it (``--tfce``)."""
    from mdlshapemodel.analysis.tfce import surface_of
    from mdlshapemodel.correspondence.sampling import icosphere

    unit, triangles = icosphere(args.subdivisions)
    points = 20.0 * unit
    apart = np.linalg.norm(points[:, None] - points[None], axis=2)
    kernel = np.exp(-0.5 * (apart / args.smoothing) ** 2)
    return surface_of(points, triangles), kernel / np.sqrt(np.sum(kernel ** 2, axis=1))[:, None]


def rates(args, small, large, ratio, errors, nuisance) -> dict:
    """Per-point rejection rate and family-wise error of each variant over the replicates
    (with ``--tfce``, the share of data sets with any point significant by TFCE last)."""
    rng = np.random.default_rng(args.seed)
    surface, smoothing = icosphere_smoothing(args) if args.tfce else (None, None)
    points = args.points if surface is None else surface.n_points
    variants = [("pooled", None, "maximum", args.permutations),
                ("groups", True, "maximum", args.permutations)]
    if args.tfce and ratio != 1:
        variants = variants[1:]        # the pooled test is not valid there (the table above)
    if args.min_p_permutations:
        variants.append(("groups_min_p", True, "min-p", args.min_p_permutations))
    found = {name: [] for name, *_ in variants}
    for _ in range(args.replicates):
        y, group, columns, groups = data_set(rng, small, large, ratio, errors, points,
                                             nuisance, args.effect, smoothing)
        seed = int(rng.integers(1 << 30))
        for name, by_group, family_wise, permutations in variants:
            result = permutation_test(y, group, columns, permutations, seed,
                                      variance_groups=groups if by_group else None,
                                      family_wise=family_wise, surface=surface)
            if args.effect:
                hits = result.p_fwer[:EFFECT_POINTS] <= args.alpha
                found[name].append((np.mean(hits), bool(np.any(hits)),
                                    bool(np.any(result.q_fdr[:EFFECT_POINTS] <= args.alpha))))
            else:
                found[name].append((np.mean(result.p <= args.alpha),
                                    bool(np.any(result.p_fwer <= args.alpha)),
                                    bool(np.any(result.q_fdr <= args.alpha)))
                                   + ((bool(np.any(result.tfce_p_fwer <= args.alpha)),)
                                      if surface is not None else ()))
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


def designs_of(args) -> tuple:
    """The designs run: all of :data:`DESIGNS`, or the one ``--design`` gives."""
    if args.design is None:
        return DESIGNS
    small, large, ratio = args.design
    return ((int(small), int(large), ratio),)


def tfce_rates(args, se: float):
    """The family-wise error of TFCE beside the maximum statistic's, per design (``--tfce``)."""
    surface, _ = icosphere_smoothing(args)
    print(f"{args.replicates} replicates of {surface.n_points} points on an icosphere of radius "
          f"20 mm, errors smoothed over {args.smoothing:g} mm; alpha {args.alpha}; SE of a "
          f"family-wise rate {se:.4f}; {args.permutations} permutations")
    print("| groups (SD ratio) | errors | nuisance | FWER, pooled | FWER, variance groups | "
          "TFCE FWER, pooled | TFCE FWER, variance groups |")
    print("|---|---|---|---|---|---|---|")
    for small, large, ratio in designs_of(args):
        for errors in ERRORS:
            for nuisance in (False, True):
                start = time.perf_counter()
                found = rates(args, small, large, ratio, errors, nuisance)
                cells = [f"{found[name][column]:.3f} "
                         f"({(found[name][column] - args.alpha) / se:+.1f} SE)"
                         if name in found else "-"
                         for column in (1, 3) for name in ("pooled", "groups")]
                print(f"| {small} vs {large} ({ratio:g}) | {errors} | "
                      f"{'3 columns' if nuisance else 'none'} | " + " | ".join(cells) + " |",
                      flush=True)
                print(f"{time.perf_counter() - start:.0f} s", file=sys.stderr, flush=True)


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
    parser.add_argument("--tfce", action="store_true",
                        help="points on an icosphere, errors smoothed over it, and the "
                             "family-wise error of threshold-free cluster enhancement")
    parser.add_argument("--subdivisions", type=int, default=2,
                        help="with --tfce: the icosphere's subdivisions (2: 162 points)")
    parser.add_argument("--smoothing", type=float, default=3.0,
                        help="with --tfce: the errors' smoothing, Gaussian sigma in mm")
    parser.add_argument("--design", type=float, nargs=3, metavar=("SMALL", "LARGE", "RATIO"),
                        help="one design only: the group sizes and the smaller group's SD ratio")
    parser.add_argument("--build", help="real shapes: a build's output folder")
    parser.add_argument("--splits", type=int, default=60)
    parser.add_argument("--small", type=int, default=5, help="cases of the scaled group")
    parser.add_argument("--ratio", type=float, default=3.0)
    args = parser.parse_args()
    if args.build:
        real_shapes(args)
        return
    se = np.sqrt(args.alpha * (1 - args.alpha) / args.replicates)
    if args.tfce:
        tfce_rates(args, se)
        return
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
    for small, large, ratio in designs_of(args):
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
