"""The unusual-case test under the null and with a planted unusual case: the normal-theory p
(``p_normal``: a scaled Beta for training cases, which assumes multivariate normal scores)
beside the p that flags (``p``: against the empirical null of the other cases,
:mod:`mdlshapemodel.model.outliers`).

Printed per setting: the share of cases with p below 0.01 and 0.05 (it should be at most the
level), with the standard error across the replicates (the cases of one sample are not
independent, so the SE is that of the replicates' own rates).

(a) Gaussian shapes: n cases of ``--dims`` numbers with variances 0.85^m (a spread like the
hippocampi's, 95 % in about 17 modes), and with k = n - 2 modes; (b) the same scaled per case
by sqrt(nu / chi^2_nu) (a scale mixture: multivariate t with nu degrees of freedom), or a
tenth of the cases (at random) scaled by 2 (two spreads).

``--build DIR`` (a build's folder with model.h5): (c) real shapes: ``--draws`` samples of n of
its cases (``--sizes``; no case known to be unusual: the share shows how many a user would be
told of), and
(d) power: in each draw, one case deformed by a bump along the mean's outward normals (Gaussian
of ``--radius`` mm, height ``--heights`` mm, at a random point), as a training case of the draw
and as a new case against the draw's other cases: the share of draws in which it is flagged at
0.01 and its median rank among the draw's p-values (1: the most unusual).

Examples (the tables in docs/analysis.md; seeds fixed)::

    python benchmarks/unusual_calibration.py --replicates 100
    python benchmarks/unusual_calibration.py --replicates 0 --build /tmp/s39/h82-icp4 --draws 100
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from mdlshapemodel.analysis import vertex_normals
from mdlshapemodel.model.outliers import modes_explaining, new_case_distances, training_distances
from mdlshapemodel.model.shape_model import ShapeModel

LEVELS = (0.01, 0.05)


def principal_scores(x: np.ndarray):
    """Scores and variances (divisor n) of the rows of x, all modes."""
    u, s, _ = np.linalg.svd(x - x.mean(0), full_matrices=False)
    keep = s > 1e-9 * s[0]
    return u[:, keep] * s[keep], s[keep] ** 2 / len(x)


def rates(samples, modes_of) -> tuple:
    """Per level, the mean share of flagged cases (normal-theory p, p) and their SEs."""
    shares = []
    for x in samples:
        scores, variances = principal_scores(x)
        found = training_distances(scores, variances, modes_of(variances, len(x)))
        shares.append([np.mean(found.p_normal < a) for a in LEVELS]
                      + [np.mean(found.p < a) for a in LEVELS])
    shares = np.array(shares)
    return shares.mean(0), shares.std(0, ddof=1) / np.sqrt(len(shares))


def row(label: str, mean: np.ndarray, se: np.ndarray) -> str:
    cells = [f"{m:.3f} ± {s:.3f}" for m, s in zip(mean, se)]
    return f"| {label} | " + " | ".join(cells) + " |"


HEADER = ("| setting | p_normal < 0.01 | p_normal < 0.05 | p < 0.01 | p < 0.05 |\n"
          "|---|---|---|---|---|")


def synthetic(args, rng):
    spectrum = 0.85 ** np.arange(args.dims)
    explained = lambda variances, n: modes_explaining(variances, n_cases=n)  # noqa: E731
    near_n = lambda variances, n: n - 2                                       # noqa: E731
    print(HEADER)
    for nu in (np.inf, 10.0, 5.0, 3.0, 0.0):
        for n in (10, 20, 40, 82):
            for name, modes_of in (("95 %", explained), ("k = n - 2", near_n)):
                def samples():
                    for _ in range(args.replicates):
                        x = rng.normal(size=(n, args.dims)) * np.sqrt(spectrum)
                        if nu == 0:
                            x *= np.where(rng.random((n, 1)) < 0.1, 2.0, 1.0)
                        elif np.isfinite(nu):
                            x /= np.sqrt(rng.chisquare(nu, size=(n, 1)) / nu)
                        yield x
                kind = ("Gaussian" if not np.isfinite(nu) else
                        "two spreads (a tenth x 2)" if nu == 0 else f"t, nu = {nu:g}")
                print(row(f"{kind}, n = {n}, {name}", *rates(samples(), modes_of)), flush=True)


def bumped(shape: np.ndarray, normals: np.ndarray, rng, height: float, radius: float):
    centre = shape[rng.integers(len(shape))]
    weight = np.exp(-np.sum((shape - centre) ** 2, axis=1) / (2 * radius ** 2))
    return shape + height * weight[:, None] * normals


def real(args, rng):
    model = ShapeModel.load(Path(args.build) / "model.h5")
    shapes = model.instance(model.scores)
    normals = vertex_normals(model.mean, model.triangles, model.part_of_triangles())
    root = np.sqrt(model.weights)[None, :, None]
    flat = lambda s: (s * root).reshape(len(s), -1)                            # noqa: E731
    print(f"{args.build}: {len(shapes)} cases, {shapes.shape[1]} points")
    all_found = training_distances(model.scores, model.variances,
                                   modes_explaining(model.variances, n_cases=len(shapes)))
    print(f"all {len(shapes)} cases, k = {all_found.modes}: "
          f"{int(np.sum(all_found.p_normal < 0.01))} flagged by p_normal < 0.01, "
          f"{int(np.sum(all_found.p < 0.01))} by p < 0.01; "
          f"{int(np.sum(all_found.p_normal < 0.05))} and {int(np.sum(all_found.p < 0.05))} "
          f"at 0.05; the null: centre {all_found.null.centre:.2f}, "
          f"spread {all_found.null.spread:.2f}")
    print(HEADER)
    sizes = [n for n in args.sizes if n < len(shapes)]
    for n in sizes:
        samples = (flat(shapes[rng.choice(len(shapes), n, replace=False)])
                   for _ in range(args.draws))
        print(row(f"{n} of the {len(shapes)} real cases",
                  *rates(samples, lambda v, m: modes_explaining(v, n_cases=m))), flush=True)
    print("\n| planted bump | n | training: p_normal < 0.01 | training: p < 0.01 | rank (p) "
          "| new: p_normal < 0.01 | new: p < 0.01 |\n|---|---|---|---|---|---|---|")
    for height in args.heights:
        for n in sizes + [len(shapes)]:
            found = []
            for _ in range(args.draws):
                chosen = rng.permutation(len(shapes))[:n]
                sample = shapes[chosen].copy()
                sample[0] = bumped(sample[0], normals, rng, height, args.radius)
                scores, variances = principal_scores(flat(sample))
                k = modes_explaining(variances, n_cases=n)
                training = training_distances(scores, variances, k)
                rank = 1 + np.sum(training.p < training.p[0])
                # the same bumped case as a new case against the other n - 1
                rest, mean = flat(sample[1:]), flat(sample[1:]).mean(0)
                u, s, vt = np.linalg.svd(rest - mean, full_matrices=False)
                rest_variances = s ** 2 / (n - 1)
                keep = rest_variances > 1e-12 * rest_variances[0]
                k_new = modes_explaining(rest_variances[keep], n_cases=n - 1)
                new = new_case_distances((flat(sample[:1]) - mean) @ vt[keep].T,
                                         rest_variances[keep], u[:, keep] * s[keep], k_new)
                found.append([training.p_normal[0] < 0.01, training.p[0] < 0.01, rank,
                              new.p_normal[0] < 0.01, new.p[0] < 0.01])
            found = np.array(found, dtype=float)
            print(f"| {height:g} mm, radius {args.radius:g} mm | {n} | {found[:, 0].mean():.2f} "
                  f"| {found[:, 1].mean():.2f} | {np.median(found[:, 2]):.0f} "
                  f"| {found[:, 3].mean():.2f} | {found[:, 4].mean():.2f} |", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--replicates", type=int, default=400,
                        help="synthetic samples per setting (0: none)")
    parser.add_argument("--dims", type=int, default=81)
    parser.add_argument("--build", help="a build's folder (model.h5): real cases")
    parser.add_argument("--draws", type=int, default=100)
    parser.add_argument("--heights", type=float, nargs="+", default=[1.0, 2.0, 4.0])
    parser.add_argument("--radius", type=float, default=4.0)
    parser.add_argument("--sizes", type=int, nargs="+", default=[20, 40, 60],
                        help="the numbers of real cases drawn (and all of them for the bumps)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    if args.replicates:
        synthetic(args, rng)
    if args.build:
        real(args, rng)


if __name__ == "__main__":
    main()
