"""Time the CPD template correspondence (mdlshapemodel.correspondence.cpd) on the shared hippocampi.

The template is the 2,562-point equal-spacing correspondence of the first case (its sphere map
sampled on ``sphere_grid(points)``); it is registered onto each of the next cases. Prints, per case
and setting: seconds, EM iterations, the fit (distance of the deformed points to the target surface
before projection: mean, 95th percentile, max), the fidelity of the corresponded mesh (distance
from the target's vertices to the corresponded triangle mesh, as in cases.csv of a build) and the
share of its triangles folded over (normal against the target's).

    python benchmarks/cpd_baseline.py --cases 21
    python benchmarks/cpd_baseline.py --cases 8 --beta 0.2 --num-eig 300 --alpha 0.5 2 8
    python benchmarks/cpd_baseline.py --cases 8 --num-eig 150 0 --sigma2-factor 4 0

Arguments given several values are crossed (``--num-eig 0``: exact solves; ``--sigma2-factor 0``:
pycpd's initial sigma^2). Wider kernels need fewer eigenpairs: 150 for beta 0.3, 300 for 0.2. BLAS runs single-threaded unless the environment says
otherwise (as in a process pool); preprocessed surfaces come from the usual cache.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import itertools  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "hippocampus" / "labels"


def folded_fraction(points, triangles, vertices, faces, located) -> float:
    """Fraction of the corresponded mesh's triangles whose normal points against the target's
    normal at their first corner (``located``: the target face of each point): folds."""
    a, b, c = (points[triangles[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    p, q, r = (vertices[faces[located[triangles[:, 0]], k]] for k in range(3))
    target = np.cross(q - p, r - p)
    return float(np.mean(np.einsum("ij,ij->i", normals, target) < 0))


def main() -> int:
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.correspondence.state import PartState
    from mdlshapemodel.prepare import PreparedCase
    from mdlshapemodel.prepare.cache import default_cache_dir, prepare_case_cached
    from mdlshapemodel.prepare.surface import point_surface_distances
    from mdlshapemodel.correspondence.cpd import cpd_registration
    from mdlshapemodel.correspondence.sampling import sphere_grid

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=8, help="template + (cases - 1) targets")
    parser.add_argument("--data", default=str(DATA))
    parser.add_argument("--points", type=int, default=2562)
    parser.add_argument("--beta", type=float, nargs="+", default=[0.3])
    parser.add_argument("--alpha", type=float, nargs="+", default=[2.0])
    parser.add_argument("--num-eig", type=int, nargs="+", default=[150], help="0: exact solve")
    parser.add_argument("--max-target-points", type=int, nargs="+", default=[3000])
    parser.add_argument("--max-iterations", type=int, nargs="+", default=[150])
    parser.add_argument("--tolerance", type=float, nargs="+", default=[1e-6])
    parser.add_argument("--sigma2-factor", type=float, nargs="+", default=[4.0],
                        help="0: pycpd's initial sigma^2")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    paths = sorted(Path(args.data).glob("*.nii.gz"))[: args.cases]
    if len(paths) < 2:
        print(f"need at least 2 label maps in {args.data}", file=sys.stderr)
        return 2
    config = BuildConfig(labels=[1, 2])
    started = time.perf_counter()
    cases = []
    for path in paths:
        case, _ = prepare_case_cached(str(path), config, str(default_cache_dir()))
        if isinstance(case, PreparedCase):
            cases.append(case)
        else:
            print(f"rejected {path.name}: {case.reason}")
    print(f"prepared {len(cases)} surfaces in {time.perf_counter() - started:.1f} s "
          f"(BLAS threads: OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')})")
    grid, grid_triangles = sphere_grid(args.points)
    first = cases[0]
    template = PartState(first.map.vertices, first.map.faces, first.map.sphere, grid,
                         grid_triangles).points
    print(f"template: {first.name}, {len(template)} points; targets: "
          f"{', '.join(f'{c.name} ({len(c.map.vertices)} v)' for c in cases[1:])}\n")

    settings = list(itertools.product(args.beta, args.alpha, args.num_eig,
                                      args.max_target_points, args.max_iterations,
                                      args.tolerance, args.sigma2_factor))
    summary = []
    for beta, alpha, num_eig, max_target, max_iterations, tolerance, factor in settings:
        options = dict(beta=beta, alpha=alpha, num_eig=num_eig or None,
                       max_target_points=max_target, max_iterations=max_iterations,
                       tolerance=tolerance, sigma2_factor=factor or None, seed=args.seed)
        label = (f"beta={beta:g} alpha={alpha:g} num_eig={num_eig or 'exact'} "
                 f"max_target_points={max_target} max_iterations={max_iterations} "
                 f"tolerance={tolerance:g} sigma2_factor={factor or 'pycpd'}")
        print(label)
        rows = []
        for case in cases[1:]:
            result = cpd_registration(template, case.map.vertices, case.map.faces, **options)
            fit = result.fit_distance
            fidelity = point_surface_distances(case.map.vertices, result.points,
                                         grid_triangles)
            folded = 100 * folded_fraction(result.points, grid_triangles, case.map.vertices,
                                           case.map.faces, result.triangles)
            rows.append((result.seconds, result.iterations, fit.mean(), np.percentile(fit, 95),
                         fit.max(), fidelity.mean(), fidelity.max(), folded))
            print(f"  {case.name}: {result.seconds:5.2f} s, iterations {result.rigid_iterations:3d}"
                  f" rigid + {result.iterations:3d} deformable, sigma {result.sigma:.3f} mm | fit "
                  f"mean {fit.mean():.3f} p95 {np.percentile(fit, 95):.3f} max {fit.max():.2f} mm"
                  f" | surface -> mesh mean {fidelity.mean():.3f} max {fidelity.max():.2f} mm"
                  f" | folded {folded:.2f} %",
                  flush=True)
        mean = np.mean(rows, axis=0)
        summary.append((label, mean))
        print(f"  mean: {mean[0]:.2f} s/case, {mean[1]:.0f} iterations, fit mean {mean[2]:.3f} "
              f"p95 {mean[3]:.3f} max {mean[4]:.2f} mm, surface -> mesh mean {mean[5]:.3f} "
              f"max {mean[6]:.2f} mm, folded triangles {mean[7]:.2f} %\n")
    if len(summary) > 1:
        print("summary (means over cases): s/case, fit mean, fit p95, surface -> mesh mean, "
              "folded %")
        for label, mean in sorted(summary, key=lambda item: item[1][2]):
            print(f"  {mean[0]:5.2f} s  {mean[2]:.3f}  {mean[3]:.3f}  {mean[5]:.3f}  "
                  f"{mean[7]:.2f}   {label}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
