"""Shorter searches of the fast strategy against the default: time, evaluations, eq. 14 (initial
and final, on the points the optimisation measures it on) and G, S (M = 1..3) of each, on the
first 82 shared hippocampi (or ``--cases`` label maps of ``--data``).

Variants: ``default``; ``rounds2`` (at most two rounds per level instead of three); ``fixedN`` and
``integratedN`` (N passes over the levels in the fixed-Delta or the full objective's phase);
``iterationsN`` (at most N quasi-Newton iterations per round); ``toleranceX`` (a level's rounds,
and the passes, end once one gains less than X of the phase's gain; the default 0.001). Variants
joined by "+" apply together (``fixed1+integrated2``). Each variant runs in a fresh process; the
preprocessing cache is reused between runs.

    python benchmarks/fast_variants.py default rounds2 fixed1 iterations30+integrated3
    python benchmarks/fast_variants.py default --data /tmp/pop1000/labels --cases 250 --label 1

``cli VARIANT -- ARGUMENTS`` runs the command line in this process with the variant applied, so
that a whole build (its model, metrics.json and correspondence meshes) can be judged by
``ground_truth.py evaluate`` and ``landmarks.py evaluate``:

    python benchmarks/fast_variants.py cli iterations10 -- build /tmp/gt-femur/labels \
        -o /tmp/schedule/gt-iterations10 --baselines ""
"""

from __future__ import annotations

import json
import re
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "hippocampus" / "labels"


def use_variant(names: str) -> None:
    """Apply each of the variants joined by "+" (e.g. ``fixed1+integrated2``)."""
    for name in names.split("+"):
        _use(name)


def _use(name: str) -> None:
    from mdlshapemodel.correspondence import strategies

    original = strategies.PHASES["fast"]
    numbered = re.fullmatch(r"(fixed|integrated|iterations)(\d+)", name)
    tolerance = re.fullmatch(r"tolerance(\d*\.\d+)", name)
    if name == "rounds2":
        strategies.PHASES["fast"] = lambda *a, **k: original(*a, rounds_per_level=2, **k)
    elif numbered:
        kind, number = numbered.group(1), int(numbered.group(2))

        def phase(state, objective, settings, *a, **k):
            if kind == "iterations":
                settings = replace(settings, round_iterations=number)
            elif objective.kind == kind:
                settings = replace(settings, field_passes=number)
            return original(state, objective, settings, *a, **k)
        strategies.PHASES["fast"] = phase
    elif tolerance:
        value = float(tolerance.group(1))
        strategies.PHASES["fast"] = lambda state, objective, settings, *a, **k: original(
            state, objective, replace(settings, tolerance=value), *a, **k)
    elif name != "default":
        raise SystemExit(f"unknown variant {name!r}")


def run(name: str, data: Path = DATA, cases: int = 82, labels=(1, 2), max_time: float = 600.0) -> dict:
    from mdlshapemodel.build import correspond
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.model.evaluation import generalization, specificity
    from mdlshapemodel.prepare.batch import preprocess

    use_variant(name)
    config = BuildConfig(labels=tuple(labels), workers=2, max_time=max_time)
    prepared, _ = preprocess(sorted(Path(data).glob("*.nii.gz"))[:cases], config)
    started = time.perf_counter()
    result = correspond(prepared, config)
    seconds = time.perf_counter() - started
    state = result.state
    phases = {}
    for row in result.trace.rows:
        phases[row.phase] = [round(row.wall_seconds, 1), round(row.objective, 2)]
    aligned = state.aligned_shapes()
    g = generalization(aligned, state.weights, 3)
    s = specificity(aligned, state.weights, 3, config.specificity_samples,
                    np.random.default_rng(config.seed))
    return {"variant": name, "cases": len(prepared), "seconds": round(seconds, 1),
            "evaluations": state.evaluations, "phases_end": phases,   # seconds and F (on its grid) at the end
            "initial_eq14": round(float(result.initial_objective), 2),
            "eq14": round(float(state.value()), 2),
            "G": [round(float(x), 4) for x in g["squared"]],
            "G_se": [round(float(x), 4) for x in g["squared_se"]],
            "S": [round(float(x), 4) for x in s["squared"]],
            "S_se": [round(float(x), 5) for x in s["squared_se"]]}


if __name__ == "__main__":
    import argparse

    if sys.argv[1:2] == ["cli"]:
        if len(sys.argv) < 4 or sys.argv[3] != "--":
            raise SystemExit("usage: fast_variants.py cli VARIANT -- ARGUMENTS OF mdlshapemodel")
        from mdlshapemodel.cli import main
        use_variant(sys.argv[2])
        sys.exit(main(sys.argv[4:]))

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("variants", nargs="*", default=["default", "rounds2", "fixed1"])
    parser.add_argument("--data", default=str(DATA), help="a folder of label maps")
    parser.add_argument("--cases", type=int, default=82, help="the first N (default 82)")
    parser.add_argument("--label", default="1,2", help="labels of the object (default 1,2)")
    parser.add_argument("--max-time", type=float, default=600.0)
    args = parser.parse_args()
    labels = tuple(int(x) for x in args.label.split(","))
    if len(args.variants) == 1:
        print(json.dumps(run(args.variants[0], Path(args.data), args.cases, labels,
                             args.max_time)), flush=True)
    else:   # each variant in a fresh process: the wrapped phase stays in its own run
        import subprocess
        for variant in args.variants:
            subprocess.run([sys.executable, __file__, variant, "--data", args.data,
                            "--cases", str(args.cases), "--label", args.label,
                            "--max-time", str(args.max_time)], check=True)
