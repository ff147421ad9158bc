"""Repeated measures, signed and one-sided maps: calibrated under the null, and what pairing
buys where subjects differ more than their scans.

Synthetic independent points through the public API: a subjects table written to a CSV file and
read by :func:`mdlshapemodel.analysis.subjects`, the per-point test of the design by
:func:`mdlshapemodel.analysis.study.point_test` (the signed map of each covariate by
:func:`~mdlshapemodel.analysis.study.signed_maps`), as ``mdlshapemodel analyze`` runs them.

``null``: for each design ``--replicates`` data sets of ``--points`` points with no effect
anywhere; printed, the per-point rejection rate at alpha (the share of point p-values at or
below alpha; it should be alpha) and the family-wise error (the share of data sets with any
point family-wise significant by the maximum statistic; alpha within 2 SE, SE = sqrt(alpha
(1 - alpha) / replicates)). Errors normal or Student's t with 3 degrees of freedom (heavy
tails). The designs:

- ``change``: two scans per subject, each subject's own shape (SD 3) plus scan noise (SD 1):
  the mean change, by sign flips; ``+ age`` adds a subject column that moves the change (the
  mean change at the mean age is 0);
- ``change by group``: the change compared between 6 and 18 subjects whose changes' SDs differ
  by 3 (Welch's v, sign flips and permutations within the groups);
- ``time within``: three scans per subject, time tested with each subject adjusted for,
  permuted within the subjects;
- ``two cases per subject``: 4 against 12 subjects (an arm of each subject's own) on both
  cases of each subject (SD 3 between subjects, 1 within): ``whole subjects`` (``--subject``,
  the subjects' cases permuted together) and ``cases as independent`` (no ``--subject``);
- ``one-sided covariate``: a covariate's t, ``--tail less``, 30 cases;
- ``one-sided groups``: Welch's v of 6 against 24 cases (SD ratio 3), ``--tail less``;
- ``each covariate``: two covariates correlated 0.5 tested together, each its own signed map
  adjusted for the other (the rates of the first's map);
- ``interaction``: three stages (10 cases each) by age, both moving the data, their interaction
  tested;
- ``contrast``: the contrast severe-mild of the three stages, where only control differs.

``paired``: the power of the paired test: two scans of ``n`` subjects whose own shapes differ
with SD 3, scan noise SD 0.3, and in every other subject the second scan moved by ``--change``
at the first 10 points. The paired test (each subject's change, its mean by sign flips) and
the unpaired one (the second scans against the first as two independent groups, Welch's v):
the share of data sets with one of the changed points family-wise significant (power), the
mean share of changed points found and the share with any unchanged point found.

Examples (the tables in docs/analysis.md; seeds fixed)::

    python benchmarks/analysis_designs.py null --replicates 300
    python benchmarks/analysis_designs.py null --replicates 1000 --design "change by group"
    python benchmarks/analysis_designs.py paired --replicates 100
"""

from __future__ import annotations

import argparse
import csv
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mdlshapemodel.analysis import subjects
from mdlshapemodel.analysis.study import point_test, signed_maps
from mdlshapemodel.config import AnalysisConfig

ERRORS = ("normal", "t3")
# with ``paired``, the changed points
CHANGED_POINTS = 10


def write_table(folder: Path, name: str, header: list, rows: list) -> Path:
    path = folder / f"{name}.csv"
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        writer.writerows(rows)
    return path


def noise(rng, errors: str, size) -> np.ndarray:
    """Unit-variance errors, normal or Student's t3."""
    if errors == "normal":
        return rng.normal(size=size)
    return rng.standard_t(3, size=size) / np.sqrt(3.0)


class Design:
    """One design of the null table: its subjects, its configuration and how its data are
    drawn."""

    def __init__(self, name: str, folder: Path, n: int, rng):
        self.name = name
        ages = rng.normal(size=n)
        if name.startswith("change") or name == "time within" or name.startswith("two cases"):
            times = 3 if name == "time within" else 2
            self.names = [f"s{s}_t{t}" for s in range(n) for t in range(times)]
            rows = [[f"s{s}_t{t}", f"s{s}", t, f"{ages[s]:.6f}", "small" if s < n // 4
                     else "large"] for s in range(n) for t in range(times)]
            table = write_table(folder, name.replace(" ", "_"),
                                ["case", "id", "time", "age", "arm"], rows)
            settings = {"subject": "id", "time": "time", "baseline": "0"}
            if name.startswith("two cases"):
                # the arm, each subject's own, on both of its cases
                settings = {"group": "arm", "reference": "large"}
                if name == "two cases per subject, whole subjects":
                    settings["subject"] = "id"
            if name == "change + age":
                settings["nuisance"] = ["age"]
            if name == "change by group":
                settings["group"] = "arm"
            self.config = AnalysisConfig(**settings)
            self.subjects_of(table, settings)
            self.times, self.ages = times, ages
        else:
            self.names = [f"c{k}" for k in range(n)]
            other = 0.5 * ages + np.sqrt(0.75) * rng.normal(size=n)
            small = 6 if name == "one-sided groups" else n
            stages = ["control", "mild", "severe"]
            rows = [[f"c{k}", f"{ages[k]:.6f}", f"{other[k]:.6f}",
                     "small" if k < small else "large", stages[k % 3]] for k in range(n)]
            table = write_table(folder, name.replace(" ", "_"),
                                ["case", "age", "height", "arm", "stage"], rows)
            settings = ({"covariates": ["age"], "tail": "less"} if name == "one-sided covariate"
                        else {"group": "arm", "tail": "less"} if name == "one-sided groups"
                        else {"group": "stage", "covariates": ["age"],
                              "interactions": ["stage:age"]} if name == "interaction"
                        else {"group": "stage", "variance": "pooled",
                              "contrasts": ["severe-mild"]} if name == "contrast"
                        else {"covariates": ["age", "height"]})
            self.ages, self.stages = np.array([float(row[1]) for row in rows]), [
                row[4] for row in rows]
            self.config = AnalysisConfig(**settings)
            self.subjects_of(table, settings)
            self.small = small

    def subjects_of(self, table: Path, settings: dict):
        keys = ("group", "covariates", "nuisance", "subject", "time", "baseline", "reference",
                "interactions")
        self.design = subjects(table, self.names, **{k: v for k, v in settings.items()
                                                     if k in keys})

    def draw(self, rng, errors: str, points: int) -> np.ndarray:
        """A null data set (cases, points)."""
        n = len(self.names)
        if (self.name.startswith("change") or self.name == "time within"
                or self.name.startswith("two cases")):
            subjects_n = n // self.times
            own = np.repeat(rng.normal(scale=3.0, size=(subjects_n, points)), self.times, axis=0)
            data = own + noise(rng, errors, (n, points))
            if self.name == "change + age":
                # the later scan moves with age, not on average
                later = np.tile(np.arange(self.times) > 0, subjects_n)
                data += (later * np.repeat(self.ages - self.ages.mean(), self.times))[:, None]
            if self.name == "change by group":
                # the small arm's scans vary 3 times as much: its changes too
                spread = np.where(np.repeat(np.arange(subjects_n) < subjects_n // 4,
                                            self.times), 3.0, 1.0)
                data = own + spread[:, None] * noise(rng, errors, (n, points))
            return data
        scale = np.where(np.arange(n) < self.small, 3.0, 1.0) if self.small < n else 1.0
        data = noise(rng, errors, (n, points)) * np.reshape(scale, (-1, 1))
        if self.name in ("interaction", "contrast"):
            # a main effect of the stage (control apart) and, with the interaction, of age:
            # in the model, not tested
            data += 1.5 * (np.array(self.stages) != "control")[:, None]
        if self.name == "interaction":
            data += self.ages[:, None]
        return data


def null(args):
    folder = Path(tempfile.mkdtemp())
    rng = np.random.default_rng(args.seed)
    designs = [("change", 10), ("change", 24), ("change + age", 24), ("change by group", 24),
               ("time within", 10), ("two cases per subject, whole subjects", 16),
               ("two cases per subject, cases as independent", 16),
               ("one-sided covariate", 30), ("one-sided groups", 30), ("each covariate", 30),
               ("interaction", 30), ("contrast", 30)]
    se = np.sqrt(args.alpha * (1 - args.alpha) / args.replicates)
    print(f"{args.replicates} null data sets of {args.points} independent points, "
          f"{args.permutations} resamples, alpha {args.alpha}; FWER SE {se:.4f}")
    print("| design | n | errors | statistic, resampling | per point | FWER |")
    print("|---|---|---|---|---|---|")
    for name, n in designs:
        if args.design and name not in args.design:
            continue
        design = Design(name, folder, n, rng)
        for errors in ERRORS:
            started = time.process_time()
            found, label = [], ""
            for _ in range(args.replicates):
                data = design.draw(rng, errors, args.points)
                config = AnalysisConfig(**{**design.config.__dict__,
                                           "permutations": args.permutations,
                                           "seed": int(rng.integers(1 << 30))})
                if name == "each covariate":
                    result = signed_maps(data, design.design, config)[0].test
                elif name == "contrast":
                    result = signed_maps(data, design.design, config)[-1].test
                else:
                    result = point_test(data, design.design, config)
                statistic = (result.name if result.t is None else "Welch's v"
                             if result.variance == "groups" else "t")
                label = f"{statistic}, {result.resampling}" + (
                    f", {result.tail}" if result.tail != "both" else "")
                found.append((np.mean(result.p <= args.alpha),
                              bool(np.any(result.p_fwer <= args.alpha))))
            per_point, fwer = np.mean(found, axis=0)
            subjects_n = (len(design.design.repeated.subjects) if design.design.repeated
                          else n)
            print(f"| {name} | {subjects_n} | {errors} | {label} | {per_point:.4f} | "
                  f"{fwer:.3f} ({(fwer - args.alpha) / se:+.1f} SE) |", flush=True)
            print(f"    {time.process_time() - started:.1f} s CPU", file=sys.stderr)


def paired(args):
    folder = Path(tempfile.mkdtemp())
    rng = np.random.default_rng(args.seed)
    print(f"{args.replicates} data sets per row, {args.points} points, change {args.change} "
          f"in every other subject at {CHANGED_POINTS} points (subjects' SD 3, scans' 0.3), "
          f"{args.permutations} resamples")
    print("| subjects | test | power | changed points found | any unchanged point |")
    print("|---|---|---|---|---|")
    for n in args.subjects:
        names = [f"s{s}_{v}" for s in range(n) for v in ("pre", "post")]
        table = write_table(folder, f"visits{n}", ["case", "id", "visit"],
                            [[f"s{s}_{v}", f"s{s}", v] for s in range(n)
                             for v in ("pre", "post")])
        tests = {"paired (each subject's change)":
                 (subjects(table, names, subject="id", time="visit", baseline="pre"),
                  {"subject": "id", "time": "visit"}),
                 "unpaired (post against pre)":
                 (subjects(table, names, group="visit", reference="pre"), {"group": "visit"})}
        found = {name: [] for name in tests}
        for _ in range(args.replicates):
            own = np.repeat(rng.normal(scale=3.0, size=(n, args.points)), 2, axis=0)
            data = own + rng.normal(scale=0.3, size=(2 * n, args.points))
            changed = np.zeros(2 * n, dtype=bool)
            changed[1::4] = True                       # the post scan of every other subject
            data[np.ix_(changed, np.arange(CHANGED_POINTS))] += args.change
            seed = int(rng.integers(1 << 30))
            for name, (design, settings) in tests.items():
                result = point_test(data, design, AnalysisConfig(
                    **settings, permutations=args.permutations, seed=seed))
                hits = result.p_fwer <= args.alpha
                found[name].append((bool(np.any(hits[:CHANGED_POINTS])),
                                    np.mean(hits[:CHANGED_POINTS]),
                                    bool(np.any(hits[CHANGED_POINTS:]))))
        for name, values in found.items():
            power, share, far = np.mean(values, axis=0)
            print(f"| {n} | {name} | {power:.2f} | {share:.3f} | {far:.2f} |", flush=True)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mode", choices=("null", "paired"))
    parser.add_argument("--replicates", type=int, default=300)
    parser.add_argument("--points", type=int, default=100)
    parser.add_argument("--permutations", type=int, default=999)
    parser.add_argument("--alpha", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--change", type=float, default=3.0)
    parser.add_argument("--subjects", type=int, nargs="+", default=[8, 12, 16, 24, 32])
    parser.add_argument("--design", action="append", default=[],
                        help="null: only this design (repeatable), e.g. 'change by group'")
    args = parser.parse_args(argv)
    (null if args.mode == "null" else paired)(args)


if __name__ == "__main__":
    main()
