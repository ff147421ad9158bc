"""The cost of preparing inputs as a build pays it: a pool of worker processes started for the
stage, every case through ``preprocess`` (no cache), wall time from the pool's start to the last
case; for one or more source trees of the package, in turn, in one run.

Each tree is run in a fresh Python process with the tree's ``MDLShapeModel`` folder first on
``PYTHONPATH`` (the same virtualenv otherwise), ``--repeat`` times, the trees interleaved (A, B,
A, B, ...), so that other work on the machine weighs on each alike. Printed per run: the wall
time, the cases prepared and rejected, the seconds per case per core (wall x workers / cases,
the worker processes' start-up included as a build pays it) and the processor seconds per case
(the workers' and the pool's own, which other work on the machine changes less than the wall
time); then the medians of each tree. An older commit's tree comes from ``git worktree add``:

    git worktree add /tmp/prep-old HEAD~3
    python benchmarks/preparation_speed.py --trees /tmp/prep-old . --cases 82 --workers 2
    python benchmarks/preparation_speed.py --trees /tmp/prep-old . --folder /tmp/gt-femur/labels \\
        --workers 1

The first run of a tree compiles its numba kernels into that tree's caches; ``--warm-up`` runs
one case per tree first, not counted.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "hippocampus" / "labels"


def prepare_all(paths: list, labels: list, workers: int) -> dict:
    """Run in the tree's own process: ``preprocess`` of every path, timed."""
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.prepare.batch import preprocess

    config = BuildConfig(labels=labels, workers=workers, cache_dir="")
    start = time.perf_counter()
    before = resource.getrusage(resource.RUSAGE_CHILDREN), resource.getrusage(
        resource.RUSAGE_SELF)
    prepared, rejected = preprocess(paths, config)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN), resource.getrusage(
        resource.RUSAGE_SELF)
    cpu = sum(a.ru_utime + a.ru_stime - b.ru_utime - b.ru_stime for a, b in zip(after, before))
    quality = [case.map.quality for case in prepared]
    return {"wall": wall, "cpu": cpu, "prepared": len(prepared), "rejected": len(rejected),
            "mean_abs_log_area_ratio": statistics.median(
                q["mean_abs_log_area_ratio"] for q in quality) if quality else None}


def run_tree(tree: Path, paths: list, labels: list, workers: int) -> dict:
    environment = dict(os.environ, PYTHONPATH=str(tree / "MDLShapeModel"))
    code = ("import json, sys; sys.path.insert(0, %r); import preparation_speed as p; "
            "print(json.dumps(p.prepare_all(%r, %r, %d)))"
            % (str(Path(__file__).parent), [str(p) for p in paths], labels, workers))
    result = subprocess.run([sys.executable, "-c", code], env=environment, text=True,
                            capture_output=True, check=True)
    return json.loads(result.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trees", nargs="+", default=[str(ROOT)],
                        help="source trees (repository roots) to compare")
    parser.add_argument("--data", default=str(DATA), help="folder of label maps")
    parser.add_argument("--folder", help="prepare every *.nii.gz of this folder instead "
                                         "(e.g. ground-truth femur label maps), all labels")
    parser.add_argument("--cases", type=int, default=82, help="the first N files")
    parser.add_argument("--label", default="1,2", help="labels of the hippocampi")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--warm-up", action="store_true")
    args = parser.parse_args()
    folder = Path(args.folder or args.data)
    paths = sorted(folder.glob("*.nii.gz"))[: args.cases]
    labels = [] if args.folder else [int(v) for v in args.label.split(",")]
    if not paths:
        print(f"no label maps in {folder}", file=sys.stderr)
        return 2
    trees = [Path(tree).resolve() for tree in args.trees]
    if args.warm_up:
        for tree in trees:
            run_tree(tree, paths[:1], labels, 1)
    print(f"{len(paths)} cases of {folder}, {args.workers} worker(s), {args.repeat} runs per "
          f"tree, in turn")
    seconds = {tree: [] for tree in trees}
    processor = {tree: [] for tree in trees}
    for repeat in range(args.repeat):
        for tree in trees:
            result = run_tree(tree, paths, labels, args.workers)
            per_case = result["wall"] * args.workers / len(paths)
            seconds[tree].append(per_case)
            processor[tree].append(result["cpu"] / len(paths))
            print(f"  {tree}: {result['wall']:.1f} s wall, {result['prepared']} prepared, "
                  f"{result['rejected']} rejected, median mean |ln area ratio| "
                  f"{result['mean_abs_log_area_ratio']:.4f}; {per_case:.3f} s per case per core, "
                  f"{processor[tree][-1]:.3f} processor s per case", flush=True)
    for tree in trees:
        print(f"{tree}: median {statistics.median(seconds[tree]):.3f} s per case per core, "
              f"{statistics.median(processor[tree]):.3f} processor s per case")
    return 0


if __name__ == "__main__":
    sys.exit(main())
