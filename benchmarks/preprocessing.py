"""Preprocessing census and cost: label map / mesh -> closed genus-0 surface -> bijective sphere map.

For the shared hippocampi (union of labels 1 and 2, and each label alone) and femurs (STL, the right
ones mirrored), prints how many cases give a sphere-like surface and a bijective map, the repairs
used, the rejection reasons, the sphere maps' area distortion, and per-case seconds and peak memory.
Each case runs in a fresh worker process (so the peak resident memory is that case's, including
about 0.2 GB of imported libraries; the baseline is printed).

    python benchmarks/preprocessing.py --workers 2
    python benchmarks/preprocessing.py --hippocampi 10 --no-femurs --surface slicer
    python benchmarks/preprocessing.py --no-femurs --union-only
    python benchmarks/preprocessing.py --hippocampi 0          # the femurs only
    python benchmarks/preprocessing.py --hippocampi 0 --no-femurs --workers 1 \\
        --folder /tmp/gt-femur/labels                            # 0.5 mm femur label maps
"""

from __future__ import annotations

import argparse
import multiprocessing
import resource
import statistics
import sys
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def _measure(path: str, labels: list, mirror: list, method: str):
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.prepare import prepare_case

    start = time.perf_counter()
    result = prepare_case(path, BuildConfig(labels=labels, mirror=mirror, cache_dir="",
                                            surface_method=method))
    seconds = time.perf_counter() - start
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    if hasattr(result, "reason"):
        return {"case": result.name, "reason": result.reason, "total_seconds": seconds,
                "peak_mb": peak_mb}
    return {"case": result.name, "total_seconds": seconds, "peak_mb": peak_mb,
            "vertices": len(result.map.vertices), "notes": result.record(),
            "sphere_seconds": result.map.quality["seconds"], **result.map.quality}


def _baseline_mb():
    import mdlshapemodel.build  # noqa: F401  (imports VTK, SimpleITK, SciPy, numba)

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run(title: str, paths: list, labels: list, mirror: list, workers: int, method: str) -> None:
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, mp_context=context, max_tasks_per_child=1) as pool:
        start = time.perf_counter()
        rows = list(pool.map(_measure, map(str, paths), [labels] * len(paths),
                             [mirror] * len(paths), [method] * len(paths)))
        wall = time.perf_counter() - start
    good = [r for r in rows if "reason" not in r]
    bad = [r for r in rows if "reason" in r]
    print(f"\n== {title}: {len(paths)} cases, {wall:.0f} s wall on {workers} workers")
    print(f"   sphere-like surface + bijective map: {len(good)}; rejected: {len(bad)}")
    for r in bad:
        print(f"     rejected {r['case']}: {r['reason']}")
    if not good:
        return
    smoothing = Counter(r["notes"].get("smoothing_sigma") for r in good)
    print("   Gaussian smoothing needed (voxels): "
          + ", ".join(f"{s}: {n}" for s, n in sorted(smoothing.items(), key=str)))
    repaired = [r for r in good if r["notes"].get("repair")]
    if repaired:
        print(f"   mask repairs: {len(repaired)} cases, e.g. {repaired[0]['case']}: "
              f"{repaired[0]['notes']['repair']}")
    if any(r["notes"].get("mirrored") for r in good):
        print(f"   mirrored: {sum(bool(r['notes'].get('mirrored')) for r in good)}")
    flips = sum(r["flipped_triangles"] for r in good)
    mean_log = [r["mean_abs_log_area_ratio"] for r in good]
    p95_log = [r["p95_abs_log_area_ratio"] for r in good]
    print(f"   flipped triangles in all maps: {flips}")
    print(f"   mean |ln area ratio| per case: median {statistics.median(mean_log):.3f}, "
          f"max {max(mean_log):.3f}; 95th percentile per case: median "
          f"{statistics.median(p95_log):.3f}, max {max(p95_log):.3f}")
    vertices = [r["vertices"] for r in good]
    print(f"   surface vertices: median {statistics.median(vertices):.0f}, "
          f"range {min(vertices)}-{max(vertices)}")
    seconds = [r["total_seconds"] for r in rows]
    sphere_seconds = [r["sphere_seconds"] for r in good]
    print(f"   seconds per case: median {statistics.median(seconds):.2f}, max {max(seconds):.2f}; "
          f"of which the sphere map: median {statistics.median(sphere_seconds):.2f}, "
          f"max {max(sphere_seconds):.2f}")
    peaks = [r["peak_mb"] for r in rows]
    print(f"   peak memory per case: median {statistics.median(peaks):.0f} MB, "
          f"max {max(peaks):.0f} MB")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(DATA))
    parser.add_argument("--hippocampi", type=int, default=100,
                        help="the first N hippocampus label maps (0: none, the femurs only)")
    parser.add_argument("--no-femurs", action="store_true")
    parser.add_argument("--union-only", action="store_true",
                        help="hippocampi: only the union of labels 1 and 2, not each label alone")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--surface", choices=("gaussian", "slicer"), default="gaussian",
                        help="label map -> surface method")
    parser.add_argument("--folder", action="append", default=[],
                        help="also every label map (*.nii.gz, label values > 0) in this folder, "
                             "e.g. a ground-truth population (repeatable)")
    args = parser.parse_args()
    data = Path(args.data)
    hippocampi = sorted((data / "hippocampus" / "labels").glob("*.nii.gz"))[: args.hippocampi]
    femurs = [] if args.no_femurs else sorted((data / "femurs").glob("*.stl"))
    folders = [(folder, sorted(Path(folder).glob("*.nii.gz"))) for folder in args.folder]
    if not hippocampi and not femurs and not any(paths for _, paths in folders):
        print(f"no hippocampus label maps or femurs to prepare under {data}", file=sys.stderr)
        return 2
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(1, mp_context=context) as pool:
        print(f"import baseline of a worker: {pool.submit(_baseline_mb).result():.0f} MB")
    populations = [("hippocampi, labels 1+2", [1, 2]), ("hippocampi, label 1", [1]),
                   ("hippocampi, label 2", [2])]
    if not hippocampi:
        populations = []
    for title, labels in populations[:1] if args.union_only else populations:
        run(f"{title} ({args.surface})", hippocampi, labels, [], args.workers, args.surface)
    if femurs:
        run("femurs (STL, right ones mirrored)", femurs, [], ["*_rfemur*"], args.workers,
            args.surface)
    for folder, paths in folders:
        run(f"{folder} ({args.surface})", paths, [], [], args.workers, args.surface)
    return 0


if __name__ == "__main__":
    sys.exit(main())
