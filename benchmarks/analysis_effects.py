"""The analysis's confidence intervals on real shapes: how often the interval of the group
difference along the normal misses the true difference (0) when the groups have one mean shape.

The build's cases are split at random, ``--splits`` times, into ``--small`` cases and the rest;
the small group's deviations from the mean of all cases are scaled by ``--ratio`` (1: the groups
vary alike; 3: the small group three times as variable; its mean shape unchanged). The shapes
are aligned as ``analyze`` does (resistant superimposition, size kept), displaced along the
mean's normals, and each point's 95 % interval of the group difference is computed with a random
nuisance column correlated with the group (correlation about 0.7): pooled (Student) and with a
variance per group (Welch-Satterthwaite). Printed: the share of points whose interval misses 0
(should be 0.05), the median half-width (mm) and the median |Cohen's d|.

Example::

    mdlshapemodel build labels20 -o hip20 --label 1,2 --baselines '' --workers 1
    python benchmarks/analysis_effects.py hip20 --small 5 --ratio 3
"""

from __future__ import annotations

import argparse

import numpy as np


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("build")
    parser.add_argument("--small", type=int, default=10)
    parser.add_argument("--ratio", type=float, default=1.0)
    parser.add_argument("--splits", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    from mdlshapemodel.analysis import align, read_build, vertex_normals
    from mdlshapemodel.analysis.effects import cohens_d, interval

    built = read_build(args.build)
    model = built.model
    rng = np.random.default_rng(args.seed)
    n = len(model.names)
    found = {"pooled": [], "groups": []}
    for _ in range(args.splits):
        small = rng.permutation(n) < args.small
        shapes = built.shapes.copy()
        centre = shapes.mean(axis=0)
        shapes[small] = centre + args.ratio * (shapes[small] - centre)
        aligned = align(shapes, model.weights)
        mean = aligned.mean(axis=0)
        normals = vertex_normals(mean, model.triangles, model.part_of_triangles())
        normal = np.einsum("npd,pd->np", aligned - mean, normals)
        group = small.astype(np.int64)
        nuisance = group + rng.normal(size=n) * np.std(group)
        for variance in found:
            bounds = interval(normal, group[:, None].astype(float), np.ones(1),
                              (nuisance - nuisance.mean())[:, None],
                              groups=group if variance == "groups" else None)
            missed = np.mean((bounds.lower > 0) | (bounds.upper < 0))
            half = np.median((bounds.upper - bounds.lower) / 2)
            d = np.median(np.abs(cohens_d(bounds, (0, 1))))
            found[variance].append((missed, half, d))
    print(f"{n} cases, {args.small} of them scaled by {args.ratio} about the mean, "
          f"{args.splits} splits, a nuisance column")
    for variance, values in found.items():
        values = np.array(values)
        print(f"{variance}: intervals missing 0 at {values[:, 0].mean():.4f} of the points "
              f"(SE over splits {values[:, 0].std(ddof=1) / np.sqrt(len(values)):.4f}); "
              f"median half-width {np.median(values[:, 1]):.3f} mm; median |d| "
              f"{np.median(values[:, 2]):.3f}")


if __name__ == "__main__":
    main()
