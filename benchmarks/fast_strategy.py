"""The fast strategy on the first N shared hippocampi: eq. 14 over time, phase by phase.

Preprocesses (or reuses the cache of) the first N label maps (labels 1+2), builds the initial
correspondence at 2562 points, then runs ``--strategy fast``'s rounds on the fixed-Delta objective
(eq. 13) for FIXED seconds and on eq. 14 for INTEGRATED seconds, printing the wall time, the round
and eq. 14 after every round, and the final value, evaluations and peak memory.

    python benchmarks/fast_strategy.py --cases 40 --fixed 200 --integrated 100
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "hippocampus" / "labels"


def main() -> int:
    from threadpoolctl import threadpool_limits

    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.correspond import CorrespondenceState, Example, PartState
    from mdlshapemodel.fast import optimise_fast
    from mdlshapemodel.mdl import Objective
    from mdlshapemodel.pipeline import preprocess
    from mdlshapemodel.sampling import sphere_grid
    from mdlshapemodel.sphere import align_parameterizations
    from mdlshapemodel.strategies import OptimisationSettings, Trace

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=40)
    parser.add_argument("--data", default=str(DATA))
    parser.add_argument("--fixed", type=float, default=200.0, help="seconds on eq. 13")
    parser.add_argument("--integrated", type=float, default=100.0, help="seconds on eq. 14")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    paths = sorted(Path(args.data).glob("*.nii.gz"))[: args.cases]
    if not paths:
        print(f"no label maps in {args.data}", file=sys.stderr)
        return 2
    prepared, _ = preprocess(paths, BuildConfig(labels=[1, 2], workers=args.workers))
    maps = align_parameterizations([case.map for case in prepared])
    grid, triangles = sphere_grid(2562)
    state = CorrespondenceState([Example(c.name, [PartState(m.vertices, m.faces, m.sphere, grid,
                                                            triangles)])
                                 for c, m in zip(prepared, maps)], [(grid, triangles)])
    data_range = float(np.ptp(state.aligned_shapes().reshape(-1, 3), axis=0).max())
    fixed = Objective("fixed", data_range, delta=0.1)
    integrated = Objective("integrated", data_range, delta_min=1e-4, delta_max=0.5)
    print(f"{len(prepared)} cases; eq. 14 initial {integrated(state.covariance()):.2f}")
    start = time.perf_counter()

    def report(_, message):
        print(f"{time.perf_counter() - start:7.1f} s  {message}  eq.14 "
              f"{integrated(state.covariance()):.2f}", flush=True)

    trace = Trace()
    with threadpool_limits(limits=1, user_api="blas"):
        optimise_fast(state, fixed, OptimisationSettings(), trace, "fixed",
                      time.perf_counter() + args.fixed, progress=report)
        optimise_fast(state, integrated, OptimisationSettings(), trace, "integrated",
                      time.perf_counter() + args.integrated, progress=report)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"final eq. 14 {integrated(state.covariance()):.2f} after "
          f"{time.perf_counter() - start:.0f} s, {state.evaluations} evaluations, "
          f"peak memory {peak:.0f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
