"""Peak memory and CPU of one model evaluation (compactness, G and S, M = 1..10) as a build's
helper makes it for the baseline, on drawn shapes, for one or more trees side by side.

Each measurement runs in a fresh process with ``PYTHONPATH`` naming a tree's package folder
(``TREE/MDLShapeModel``; ``.`` for this checkout), so that older code is measured in the same
run. The shapes: ``--cases`` shapes of ``--points`` points, the mean of a unit sphere's points
plus independent Gaussian displacements whose size falls over the coordinates (every one of the
3 n_p directions varies, as in a large population), uniform area weights; the evaluation is
``model.evaluation.evaluate`` with 10 modes, 10,000 specificity samples and G over a random 500
of the cases (the build's defaults; no surfaces: the surface measures are left out). It prints,
per tree, the CPU seconds of the evaluation, the process's peak resident memory (``ru_maxrss``)
and its resident memory once the shapes are made, and G(1) and S(1)::

    git worktree add --detach /tmp/older 89721b2
    python benchmarks/evaluation_memory.py --cases 10000 --points 2562 --trees /tmp/older .
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

MEASURE = """
import json, resource, sys, time
import numpy as np
from mdlshapemodel.model.evaluation import evaluate
from mdlshapemodel.correspondence.sampling import sphere_grid

cases, points = int(sys.argv[1]), int(sys.argv[2])
rng = np.random.default_rng(0)
mean = sphere_grid(points)[0] * 20.0
scale = np.linspace(1.0, 0.05, 3 * points).reshape(points, 3)
shapes = mean + rng.standard_normal((cases, points, 3)) * scale
weights = np.full(points, 1.0 / points)
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
start = time.process_time()
result = evaluate(shapes, weights, None, max_modes=10, n_samples=10_000,
                  rng=np.random.default_rng(1), generalization_cases=500)
print(json.dumps({"cpu_s": time.process_time() - start,
                  "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "shapes_mb": before, "G1": result["generalization"][0],
                  "S1": result["specificity"][0]}))
"""


def measure(tree: str, cases: int, points: int) -> dict:
    package = str(Path(tree).resolve() / "MDLShapeModel")
    env = dict(os.environ, PYTHONPATH=package, OPENBLAS_NUM_THREADS="1")
    done = subprocess.run([sys.executable, "-c", MEASURE, str(cases), str(points)], env=env,
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{tree}: {done.stderr.strip().splitlines()[-1:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", type=int, default=10_000)
    parser.add_argument("--points", type=int, default=2562)
    parser.add_argument("--trees", nargs="+", default=["."],
                        help="checkouts to measure, each in its own process (default: this one)")
    args = parser.parse_args()
    print(f"{args.cases} shapes of {args.points} points; one BLAS thread")
    print("| tree | evaluation CPU s | peak MB | MB once the shapes are made | G(1) | S(1) |")
    print("|---|---|---|---|---|---|")
    for tree in args.trees:
        row = measure(tree, args.cases, args.points)
        print(f"| {tree} | {row['cpu_s']:.1f} | {row['peak_mb']:.0f} | {row['shapes_mb']:.0f} "
              f"| {row['G1']:.6g} | {row['S1']:.6g} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
