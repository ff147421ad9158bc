"""The stages of a build fitted against the number of shapes, and the whole build predicted at
larger sizes, from the stage rows that ``population.py --sizes`` writes (stages.md).

Each stage's CPU seconds (of the build and all its processes) are fitted by least squares as
a + b n_s (and the growth between the two largest sizes given as an exponent, n_s^k, so that
anything super-linear shows); its peak memory (all processes) as a + b n_s. The SVD of the
n_s x 3n_p aligned shapes (a model's PCA, the evaluation's model space) grows as n_s^2 3n_p up
to n_s = 3n_p: ``--svd-stages`` names the stages that make such SVDs and how many, whose cost
(``--svd``: CPU seconds of one at sizes, on one BLAS thread, interpolated linearly) is taken out
before the fit and added back at the predicted size. The optimisation is not fitted (the builds
measured are cut short): it is predicted as ``--evaluations`` evaluations at the cost of one,
eq. 14 with its gradient (``--objective``: CPU seconds at sizes, from
``evaluation_scaling.py``) plus the per-example part (sampling, chain rule) at
``--per-example`` ms per shape. Stages named in ``--skip`` (those the cut changes) are left out
of the time fits. The baseline's evaluation (the model's evaluation and one more SVD) runs in
the helper process during the optimisation: counted in the CPU, not in the wall time. The wall
time of a quiet 2-core machine is taken as the CPU time, halved for the preparation (two
workers).

    python benchmarks/stage_fit.py /tmp/stages/stages.md --predict 2500 5000 10000
"""

from __future__ import annotations

import argparse
import re
from collections import defaultdict

import numpy as np

STAGE = re.compile(r"([^|:]+): ([\d.]+) s \(([\d.]+) CPU-s\), ([\d.]+) GB")


def stage_rows(paths: list) -> dict:
    """stage name -> {n_s: (wall s, CPU s, peak GB)} from the stage rows of the tables (a later
    row of the same size replaces an earlier one)."""
    found = defaultdict(dict)
    for path in paths:
        for line in open(path):
            cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
            if len(cells) < 2 or not cells[0].isdigit() or not STAGE.fullmatch(cells[1]):
                continue
            for cell in cells[1:]:
                match = STAGE.fullmatch(cell)
                if match:
                    name, wall, cpu, peak = match.groups()
                    found[name.strip()][int(cells[0])] = (float(wall), float(cpu), float(peak))
    return found


def linear(sizes: np.ndarray, values: np.ndarray) -> tuple:
    """(a, b) of the least-squares line a + b n through the points."""
    design = np.column_stack([np.ones(len(sizes)), sizes])
    (a, b), *_ = np.linalg.lstsq(design, values, rcond=None)
    return round(float(a), 9) + 0.0, round(float(b), 12) + 0.0     # no "-0.0" in the table


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("tables", nargs="+", help="stages.md files of population.py --sizes")
    parser.add_argument("--predict", type=int, nargs="+", default=[2500, 5000, 10000])
    parser.add_argument("--skip", nargs="*", default=["optimisation",
                                                      "the baselines' evaluation awaited"])
    parser.add_argument("--evaluations", type=int, default=880)
    parser.add_argument("--objective", default="1000:0.40,2500:3.74,5000:4.65,10000:6.81",
                        help="n_s:CPU s of one evaluation of eq. 14 and its gradient, ...")
    parser.add_argument("--per-example", type=float, default=0.38,
                        help="ms per shape of an evaluation's per-example part")
    parser.add_argument("--svd", default="0:0,125:0.09,250:0.27,500:0.86,1000:2.7,2000:10.0,"
                                         "2500:17.4,4000:57.3,5000:100,10000:350",
                        help="n_s:CPU s of one SVD of the n_s x 3n_p shapes, ...")
    parser.add_argument("--svd-stages", default="model:1,evaluation:1",
                        help="stage:SVDs it makes, ...")
    args = parser.parse_args()
    svd_at = dict(tuple(map(float, item.split(":"))) for item in args.svd.split(","))

    def svd(n):
        return np.interp(n, sorted(svd_at), [svd_at[k] for k in sorted(svd_at)])

    svds = {name: int(count) for name, count in
            (item.rsplit(":", 1) for item in args.svd_stages.split(",") if item)}
    stages = stage_rows(args.tables)
    print(f"| stage | CPU s at n_s = {', '.join(map(str, sorted(next(iter(stages.values())))))}"
          " | fit, CPU s | growth between the largest two | peak GB, fit | "
          + " | ".join(f"{n}: CPU s, peak GB" for n in args.predict) + " |")
    print("|---" * (5 + len(args.predict)) + "|")
    totals, peaks = np.zeros(len(args.predict)), np.zeros(len(args.predict))
    wall, baseline = np.zeros(len(args.predict)), np.zeros(len(args.predict))
    for name, rows in stages.items():
        sizes = np.array(sorted(rows), dtype=float)
        cpu = np.array([rows[n][1] for n in sorted(rows)])
        peak = np.array([rows[n][2] for n in sorted(rows)])
        sampled = peak > 0              # a stage shorter than the sampling has no peak
        if sampled.sum() < 2:
            continue
        pa, pb = linear(sizes[sampled], peak[sampled])
        memory = [pa + pb * n for n in args.predict]
        peaks = np.maximum(peaks, memory)
        if name in args.skip:      # its memory only: the cut changes its time
            print(f"| {name} | (cut) | | | {pa:.2f} + {1000 * pb:.2f} per 1000 | "
                  + " | ".join(f", {m:.1f}" for m in memory) + " |")
            continue
        count = svds.get(name, 0)
        a, b = linear(sizes, cpu - count * svd(sizes))
        exponent = (np.log(max(cpu[-1], 1e-3) / max(cpu[-2], 1e-3)) / np.log(sizes[-1] / sizes[-2])
                    if len(sizes) > 1 else float("nan"))
        predicted = np.array([max(a + b * n, 0.0) + count * svd(n) for n in args.predict])
        totals += predicted
        wall += predicted / (2.0 if name == "preparing" else 1.0)
        if name == "evaluation":
            baseline = predicted + svd(np.array(args.predict, dtype=float))
        fit = f"{a:.1f} + {1000 * b:.1f} per 1000" + (f" + {count} SVD" if count else "")
        print(f"| {name} | {', '.join(f'{c:.0f}' for c in cpu)} | {fit} | n_s^{exponent:.2f} | "
              f"{pa:.2f} + {1000 * pb:.2f} per 1000 | "
              + " | ".join(f"{c:.0f}, {m:.1f}" for c, m in zip(predicted, memory)) + " |")
    known = dict(tuple(map(float, item.split(":"))) for item in args.objective.split(","))
    objective = np.interp(args.predict, sorted(known), [known[k] for k in sorted(known)])
    optimisation = args.evaluations * (objective
                                       + args.per_example * 1e-3 * np.array(args.predict))
    print(f"| optimisation ({args.evaluations} evaluations) | | | | | "
          + " | ".join(f"{c:.0f}" for c in optimisation) + " |")
    print(f"| the baseline's evaluation (helper, during the optimisation) | | | | | "
          + " | ".join(f"{c:.0f}" for c in baseline) + " |")
    print("| **in all**: CPU s; wall s of a quiet 2-core machine; peak GB | | | | | "
          + " | ".join(f"**{t:.0f}**; **{w:.0f}** ({w / 3600:.1f} h); **{p:.1f}**"
                       for t, w, p in zip(totals + optimisation + baseline,
                                          wall + optimisation, peaks)) + " |")


if __name__ == "__main__":
    main()
