"""Shorter searches of the fast strategy against the default, on the first 82 shared hippocampi:
time, evaluations, eq. 14 and G, S (M = 1..3) of each.

Variants: ``default``; ``rounds2`` (at most two rounds per level instead of three); ``fixed1`` (one
pass over the levels in the fixed-Delta phase instead of two); ``finish3`` (the finishing phase
after the coarse stage at the finest level only); ``finish1`` (the finishing phase one round per
level); ``nofinish`` (no finishing phase: the coarse stage's maps on the build's points as they
are). The phase function registered for
``fast`` is wrapped for the variant; the preprocessing cache is reused between runs.

    python benchmarks/fast_variants.py default rounds2 fixed1
    python benchmarks/fast_variants.py default finish3 finish1 nofinish
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "hippocampus" / "labels"


def use_variant(name: str) -> None:
    from mdlshapemodel.correspondence import strategies
    from mdlshapemodel.correspondence.strategies import fast

    original = fast.optimise_fast
    if name == "rounds2":
        strategies.PHASES["fast"] = lambda *a, **k: original(*a, rounds_per_level=2, **k)
    elif name == "fixed1":
        def phase(state, objective, settings, *a, **k):
            if objective.kind == "fixed":
                settings = replace(settings, field_passes=1)
            return original(state, objective, settings, *a, **k)
        strategies.PHASES["fast"] = phase
    elif name == "finish3":
        strategies.FINISHING_LEVELS = (3,)
    elif name == "finish1":
        def phase(*a, levels=(0, 1, 2, 3), **k):
            rounds = 1 if levels == strategies.FINISHING_LEVELS else 3
            return original(*a, levels=levels, rounds_per_level=rounds, **k)
        strategies.PHASES["fast"] = phase
    elif name == "nofinish":
        from mdlshapemodel.correspondence.strategies.base import start_phase
        from mdlshapemodel.correspondence.trace import Stop

        def phase(state, objective, settings, rng, trace, name, deadline, *a,
                  levels=(0, 1, 2, 3), **k):
            if levels != strategies.FINISHING_LEVELS:
                return original(state, objective, settings, rng, trace, name, deadline, *a,
                                levels=levels, **k)
            value = start_phase(state, objective, trace, name)
            trace.stopped_by = Stop.CONVERGED
            return value
        strategies.PHASES["fast"] = phase
    elif name != "default":
        raise SystemExit(f"unknown variant {name!r}")


def run(name: str) -> dict:
    from mdlshapemodel.build import correspond
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.model.evaluation import generalization, specificity
    from mdlshapemodel.prepare.batch import preprocess

    use_variant(name)
    config = BuildConfig(labels=(1, 2), workers=2)
    prepared, _ = preprocess(sorted(DATA.glob("*.nii.gz"))[:82], config)
    started = time.perf_counter()
    state = correspond(prepared, config).state
    seconds = time.perf_counter() - started
    aligned = state.aligned_shapes()
    g = generalization(aligned, state.weights, 3)
    s = specificity(aligned, state.weights, 3, config.specificity_samples,
                    np.random.default_rng(config.seed))
    return {"variant": name, "seconds": round(seconds, 1), "evaluations": state.evaluations,
            "eq14": round(float(state.value()), 2),
            "G": [round(float(x), 4) for x in g["squared"]],
            "G_se": [round(float(x), 4) for x in g["squared_se"]],
            "S": [round(float(x), 4) for x in s["squared"]],
            "S_se": [round(float(x), 5) for x in s["squared_se"]]}


if __name__ == "__main__":
    if len(sys.argv) == 2:
        print(json.dumps(run(sys.argv[1])))
    else:   # each variant in a fresh process: the wrapped phase stays in its own run
        import subprocess
        for variant in sys.argv[1:] or ["default", "rounds2", "fixed1"]:
            subprocess.run([sys.executable, __file__, variant], check=True)
