"""The model's evaluation (``evaluate``: compactness, generalization, specificity, surface to
surface) of an older commit and of this tree, in turn, on the same model; and whether they give
the same numbers.

The inputs are a finished build's: its prepared cases (from the preprocessing cache, or prepared
again) with the correspondence of its ``checkpoint.npz`` replayed, i.e. the aligned shapes, the
area weights, the triangles and the true surfaces in the model frame that the build evaluated.
The older commit's evaluation modules (``model/evaluation.py`` and, where it has them,
``evaluation_kernels.py``, ``space.py`` and ``surface_measures.py``: ``git show OLD:...``) are
loaded beside this tree's as ``mdlshapemodel.model._old_<name>``, their imports of each other
pointed at the older copies, so both versions run in the same process on the same library;
each run, as in a build, hands the surface generalization to a helper process (``--workers 2``)
with the build's settings (10 modes, 10,000 specificity samples, 200 surface samples, seed 0).
Printed per run: the seconds of each version, then their medians and ratio, then per measure
whether the numbers are identical or their largest relative difference. ``--parts``: instead,
each measure alone, in this process with one BLAS thread (the CPU time a build spends on it),
the two versions in turn.

    python benchmarks/evaluation_speed.py HEAD --build /tmp/ev82 --repeat 3
    python benchmarks/evaluation_speed.py HEAD --build /tmp/ev82 --repeat 2 --parts

``--build`` is a converged build (its checkpoint holds the correspondence of the build's
points), of the first 82 shared hippocampi by default, e.g. ``mdlshapemodel build $(ls -d
../shared/data/hippocampus/labels/* | head -82) -o /tmp/ev82 --label 1,2``; its inputs are the
files its cases.csv names (``--cases``: the first N of them, all by default), ``--label`` must
be the build's.
"""

from __future__ import annotations

import argparse
import atexit
import csv
import importlib.util
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FOLDER = "MDLShapeModel/mdlshapemodel/model"
# the modules of the evaluation, those that others import first
MODULES = ("evaluation_kernels", "space", "surface_measures", "evaluation")
# the folder of the older modules; set before the helper process starts, which loads them too
OLD_FOLDER = "EVALUATION_SPEED_OLD_FOLDER"


def old_name(module: str) -> str:
    return f"mdlshapemodel.model._old_{module}"


def pointed_at_older(source: str, present: list) -> str:
    """``source`` with its imports of the evaluation modules in ``present`` pointed at their
    older copies."""
    for module in present:
        source = re.sub(rf"from \.{module} import", f"from ._old_{module} import", source)
        source = re.sub(rf"from \. import {module}\b", f"from . import _old_{module} as {module}",
                        source)
    return source


def load_old():
    """The older evaluation module, its older siblings registered before it (the helper process
    unpickles their functions by those names)."""
    folder = os.environ.get(OLD_FOLDER)
    if old_name("evaluation") not in sys.modules and folder:
        import mdlshapemodel.model  # noqa: F401  (the package its relative imports resolve in)

        for module in MODULES:
            path = Path(folder) / f"{module}.py"
            if not path.is_file():
                continue
            spec = importlib.util.spec_from_file_location(old_name(module), path)
            loaded = importlib.util.module_from_spec(spec)
            sys.modules[old_name(module)] = loaded
            spec.loader.exec_module(loaded)
    return sys.modules.get(old_name("evaluation"))


load_old()    # in the helper process too (spawn runs this file's top level)


def inputs(build: Path, cases: int, labels: tuple) -> tuple:
    """(shapes, weights, triangles, surfaces) as the build evaluated them."""
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.correspondence.initial import initial_state
    from mdlshapemodel.correspondence.state import replay_record
    from mdlshapemodel.folders import load_checkpoint
    from mdlshapemodel.prepare.batch import preprocess

    config = BuildConfig(labels=labels, workers=1)
    # the build's own inputs, in its order (cases.csv names each case's file)
    files = [row["file"] for row in csv.DictReader(open(build / "cases.csv"))][:cases]
    prepared, _ = preprocess(files, config)
    state = initial_state(prepared, config)[0]
    replay_record(state, load_checkpoint(build / "checkpoint.npz"))
    surfaces = [(state.to_model_frame(i, vertices), faces)
                for i, (vertices, faces) in enumerate(case.surface() for case in prepared)]
    return state.aligned_shapes(), state.weights.copy(), state.triangles(), surfaces


def parts(module, shapes, weights, triangles, surfaces) -> tuple:
    """Seconds of each measure of ``module`` alone (as ``evaluate`` calls them), and its
    results."""
    seconds, keywords, results = {}, {}, {}
    if hasattr(module, "model_space"):      # measures that share one model space
        start = time.perf_counter()
        keywords["space"] = module.model_space(shapes, weights)
        seconds["model space"] = time.perf_counter() - start
    calls = {"generalization": lambda: module.generalization(shapes, weights, 10, **keywords),
             "specificity": lambda: module.specificity(shapes, weights, 10, 10_000,
                                                       np.random.default_rng(0), **keywords),
             "surface generalization": lambda: module.surface_generalization(
                 shapes, weights, triangles, surfaces, 10, module.SURFACE_GENERALIZATION_POINTS,
                 **keywords),
             "surface specificity": lambda: module.surface_specificity(
                 shapes, weights, triangles, surfaces, 10, 200, np.random.default_rng(0),
                 **keywords)}
    for name, call in calls.items():
        start = time.perf_counter()
        results[name] = call()
        seconds[name] = time.perf_counter() - start
    return seconds, results


def differences(old: dict, new: dict) -> list:
    rows = []
    for key in new:
        a, b = np.asarray(old[key], dtype=float), np.asarray(new[key], dtype=float)
        if np.array_equal(a, b):
            rows.append((key, "identical"))
        else:
            relative = np.max(np.abs(a - b) / np.maximum(np.abs(a), 1e-300))
            rows.append((key, f"largest relative difference {relative:.1e}"))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("old", help="the older commit, e.g. HEAD")
    parser.add_argument("--build", type=Path, default=Path("/tmp/ev82"))
    parser.add_argument("--cases", type=int, default=None)
    parser.add_argument("--label", default="1,2")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--workers", type=int, default=2, help="2: a helper process, as a build")
    parser.add_argument("--parts", action="store_true", help="each measure alone")
    args = parser.parse_args()

    folder = Path(tempfile.mkdtemp(prefix="evaluation_speed_"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    sources = {}
    for module in MODULES:
        shown = subprocess.run(["git", "show", f"{args.old}:{FOLDER}/{module}.py"], cwd=ROOT,
                               capture_output=True, text=True)
        if shown.returncode == 0:
            sources[module] = shown.stdout
    for module, source in sources.items():
        (folder / f"{module}.py").write_text(pointed_at_older(source, list(sources)))
    os.environ[OLD_FOLDER] = str(folder)
    old = load_old()
    from mdlshapemodel.model import evaluation as new
    from mdlshapemodel.model.shape_model import ShapeModel
    from mdlshapemodel.parallel import helper_for

    labels = tuple(int(x) for x in args.label.split(","))
    shapes, weights, triangles, surfaces = inputs(args.build, args.cases, labels)
    variances = ShapeModel.from_shapes(shapes, weights).variances
    print(f"{len(shapes)} shapes of {shapes.shape[1]} points, true surfaces of "
          f"{min(len(v) for v, _ in surfaces)}-{max(len(v) for v, _ in surfaces)} vertices")

    results = {}
    if args.parts:
        from threadpoolctl import threadpool_limits

        for module in (old, new):            # compile or load the numba code
            module.evaluate(shapes[:6], weights, variances[:5], 2, 20, None, triangles,
                            surfaces[:6], 4)
        with threadpool_limits(limits=1, user_api="blas"):
            for run in range(args.repeat):
                for name, module in (("old", old), ("new", new)):
                    seconds, results[name] = parts(module, shapes, weights, triangles, surfaces)
                    print(f"run {run + 1}, {name}: " + ", ".join(
                        f"{key} {value:.2f} s" for key, value in seconds.items())
                        + f"; {sum(seconds.values()):.1f} s in all")
        for measure, result in results["new"].items():
            for key, what in differences(results["old"][measure], result):
                print(f"  {measure}, {key}: {what}")
        return

    def evaluate(module, pool):
        return module.evaluate(shapes, weights, variances, 10, 10_000, np.random.default_rng(0),
                               triangles, surfaces, 200, pool=pool)

    seconds = {"old": [], "new": []}
    with helper_for(args.workers) as pool:
        # compile or load the numba code and start the helper before timing
        for module in (old, new):
            module.evaluate(shapes[:6], weights, variances[:5], 2, 20, None, triangles,
                            surfaces[:6], 4, pool=pool)
        for run in range(args.repeat):
            for name, module in (("old", old), ("new", new)):
                start = time.perf_counter()
                results[name] = evaluate(module, pool)
                seconds[name].append(time.perf_counter() - start)
            print(f"run {run + 1}: old {seconds['old'][-1]:.1f} s, new {seconds['new'][-1]:.1f} s")
    old_median, new_median = (statistics.median(seconds[k]) for k in ("old", "new"))
    print(f"median: old {old_median:.1f} s, new {new_median:.1f} s, "
          f"{old_median / new_median:.1f} times faster")
    for key, what in differences(results["old"], results["new"]):
        print(f"  {key}: {what}")


if __name__ == "__main__":
    main()
