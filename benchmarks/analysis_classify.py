"""The classification of groups by their shapes on a real build: calibrated under the null, blind
to a group that is only confounded with a nuisance column once that column is adjusted for, and
what it finds in a planted change.

Everything goes through the public API as ``analyze`` runs it: the build's corresponded shapes
(:func:`mdlshapemodel.analysis.read_build`), aligned by the analysis's default (resistant)
superimposition, classified by :func:`mdlshapemodel.analysis.classify` (repeated stratified
k-fold, shrinkage LDA on the principal scores, the nuisance regressed out in each training fold,
the AUC's permutation p-value with the cross-validation redone per permutation).

Three parts:

- **null**: ``--splits`` random half splits of the cases (no difference): the share of splits
  with p <= alpha (it should be alpha, within 2 SE), a Kolmogorov-Smirnov test of the p-values'
  uniformity, the AUC's mean and SD over the splits, the mean half-width of the corrected
  resampled interval (Nadeau and Bengio) and of the naive one (the folds' SD over sqrt(J)), and
  how often each covers 0.5.
- **confound**: ``age`` drawn at random per case, each case's shape moved by age times the first
  principal mode (1 SD of it per SD of age), the group the older half (age plus noise of SD 0.5
  above its median): the group has no effect of its own. AUC and p without and with age as a
  nuisance column, over ``--replicates`` draws.
- **planted**: a Gaussian dent (``--amplitude`` mm, sigma ``--width`` mm) pushed inward along
  the normals at the tip of the hippocampal head (benchmarks/analysis.py's) in a random half of
  the cases, the shapes aligned again: AUC, balanced accuracy, p over ``--replicates`` halves.

Example (the table in docs/analysis.md)::

    python benchmarks/analysis_classify.py /tmp/classify-bench/hip20 --splits 40
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy import stats

from mdlshapemodel.analysis import align, classify, read_build
from mdlshapemodel.analysis.discriminant import principal_scores

sys.path.insert(0, str(Path(__file__).parent))
from analysis import _long_axis_tip, _planted  # noqa: E402  (the planted experiments' change)


def run(shapes, weights, labels, args, seed, nuisance=None):
    return classify(shapes, weights, labels, nuisance, args.folds, args.repeats,
                    args.permutations, seed)


def null(args, aligned, weights, rng):
    n = len(aligned)
    found = []
    for _ in range(args.splits):
        labels = rng.permutation(n) < n // 2
        found.append(run(aligned, weights, labels, args, int(rng.integers(1 << 30))))
    p = np.array([f.p for f in found])
    auc = np.array([f.auc for f in found])
    se = np.sqrt(args.alpha * (1 - args.alpha) / args.splits)
    rejected = np.mean(p <= args.alpha)
    corrected = np.array([f.auc_interval for f in found])
    j = args.folds * args.repeats
    naive = np.array([stats.t.ppf(0.975, j - 1) * np.std(f.fold_auc, ddof=1) / np.sqrt(j)
                      for f in found])
    print(f"\nnull: {args.splits} random half splits")
    print("| p <= alpha | KS p of the p-values | mean AUC | SD of AUC | corrected interval: "
          "half-width, covers 0.5 | naive interval: half-width, covers 0.5 |")
    print("|---|---|---|---|---|---|")
    print(f"| {rejected:.3f} ({(rejected - args.alpha) / se:+.1f} SE) | "
          f"{stats.kstest(p, 'uniform').pvalue:.2f} | {auc.mean():.3f} | {auc.std(ddof=1):.3f} | "
          f"{np.mean(corrected[:, 1] - corrected[:, 0]) / 2:.3f}, "
          f"{np.mean((corrected[:, 0] <= 0.5) & (0.5 <= corrected[:, 1])):.2f} | "
          f"{naive.mean():.3f}, {np.mean(np.abs(auc - 0.5) <= naive):.2f} |", flush=True)


def confound(args, aligned, weights, rng):
    n = len(aligned)
    mean, basis, scores = principal_scores(aligned, weights, max_modes=1)
    mode = (basis[0].reshape(-1, 3) / np.sqrt(weights)[:, None]) * scores[:, 0].std()
    rows = {"without age": [], "age adjusted for": []}
    for _ in range(args.replicates):
        age = rng.normal(size=n)
        shapes = aligned + age[:, None, None] * mode[None]
        group = age + 0.5 * rng.normal(size=n) > np.median(age)
        seed = int(rng.integers(1 << 30))
        rows["without age"].append(run(shapes, weights, group, args, seed))
        rows["age adjusted for"].append(run(shapes, weights, group, args, seed, age[:, None]))
    print(f"\nconfound: a group only confounded with age, {args.replicates} draws")
    print("| classification | mean AUC | SD of AUC | mean balanced accuracy | p <= alpha |")
    print("|---|---|---|---|---|")
    for name, found in rows.items():
        auc = np.array([f.auc for f in found])
        print(f"| {name} | {auc.mean():.3f} | {auc.std(ddof=1):.3f} | "
              f"{np.mean([f.balanced_accuracy for f in found]):.3f} | "
              f"{np.mean([f.p <= args.alpha for f in found]):.2f} |", flush=True)


def planted(args, built, rng):
    shapes, cells, weights = built.shapes, built.model.triangles, built.model.weights
    n = len(shapes)
    tip, _ = _long_axis_tip(align(shapes, weights).mean(axis=0))
    print(f"\nplanted: a dent at the head's tip (point {tip}), sigma {args.width} mm, in a random "
          f"half, {args.replicates} halves")
    print("| depth (mm) | mean AUC | its corrected interval (mean) | mean balanced accuracy | "
          "median p | p <= alpha |")
    print("|---|---|---|---|---|---|")
    for amplitude in args.amplitude:
        dented = _planted(shapes, cells, tip, None, "dent", amplitude, args.width)
        found = []
        for _ in range(args.replicates):
            labels = rng.permutation(n) < n // 2
            changed = np.where(labels[:, None, None], dented, shapes)
            found.append(run(align(changed, weights), weights, labels, args,
                             int(rng.integers(1 << 30))))
        interval = np.mean([f.auc_interval for f in found], axis=0)
        print(f"| {amplitude:g} | {np.mean([f.auc for f in found]):.3f} | "
              f"{interval[0]:.3f} - {interval[1]:.3f} | "
              f"{np.mean([f.balanced_accuracy for f in found]):.3f} | "
              f"{np.median([f.p for f in found]):.4f} | "
              f"{np.mean([f.p <= args.alpha for f in found]):.2f} |", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("build", help="a build's output folder")
    parser.add_argument("--splits", type=int, default=40)
    parser.add_argument("--replicates", type=int, default=10)
    parser.add_argument("--folds", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--permutations", type=int, default=199)
    parser.add_argument("--amplitude", type=float, nargs="+", default=[2.0, 1.0])
    parser.add_argument("--width", type=float, default=4.0)
    parser.add_argument("--alpha", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=2010)
    parser.add_argument("--part", choices=("null", "confound", "planted"), action="append")
    args = parser.parse_args()
    built = read_build(args.build)
    weights = built.model.weights
    aligned = align(built.shapes, weights)
    rng = np.random.default_rng(args.seed)
    print(f"{args.build}: {len(aligned)} cases, {aligned.shape[1]} points; {args.repeats} x "
          f"{args.folds}-fold, {args.permutations} permutations, alpha {args.alpha}; "
          f"{time.strftime('%Y-%m-%d')}")
    started = time.process_time()
    for part in args.part or ("null", "confound", "planted"):
        if part == "null":
            null(args, aligned, weights, rng)
        elif part == "confound":
            confound(args, aligned, weights, rng)
        else:
            planted(args, built, rng)
    print(f"\n{time.process_time() - started:.0f} s CPU")


if __name__ == "__main__":
    main()
