"""Build a model of the first N shared hippocampi with the real CLI and print what it measured.

Prints wall time, the objective before and after optimisation, compactness / generalization /
specificity (area-weighted mm^2, +- 1 standard error; and surface to surface, mm, when measured) of
the optimised model and of every baseline evaluated in the same build (``--baselines``: the initial
equal-spacing correspondence = ``--strategy none``, and the CPD template correspondence) for
M = 1..10, how many standard errors apart they are, and the surface fidelity of the corresponded
meshes.

    python benchmarks/hippocampus_build.py --cases 40 --output /tmp/hippocampus40 -- --baselines none,cpd
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "hippocampus" / "labels"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=40)
    parser.add_argument("--output", default="hippocampus-benchmark")
    parser.add_argument("--data", default=str(DATA))
    parser.add_argument("extra", nargs=argparse.REMAINDER,
                        help="further build options after --, e.g. -- --max-time 300")
    args = parser.parse_args()
    inputs = sorted(Path(args.data).glob("*.nii.gz"))[: args.cases]
    if not inputs:
        print(f"no label maps in {args.data}", file=sys.stderr)
        return 2
    extra = [a for a in args.extra if a != "--"]
    command = [sys.executable, "-m", "mdlshapemodel.cli", "build", *map(str, inputs),
               "--label", "1,2", "-o", args.output, "-q", *extra]
    start = time.perf_counter()
    subprocess.run(command, check=True)
    wall = time.perf_counter() - start
    metrics = json.loads((Path(args.output) / "metrics.json").read_text())
    print(f"\n{metrics['n_shapes']} hippocampi, {metrics['n_points']} points, strategy "
          f"{metrics['strategy']}, {metrics['n_rejected']} rejected; wall time {wall:.0f} s")
    print(f"objective (eq. 14 + prior + guides): initial {metrics['objective']['initial']:.2f}, "
          f"final {metrics['objective']['final']:.2f} nats")
    for name, base in metrics["baselines"].items():
        print(f"\n=== optimised against baseline '{name}' (objective {base['objective']:.2f}) ===")
        for key in ("compactness", "generalization", "specificity", "generalization_surface_mm",
                    "specificity_surface_mm"):
            if key not in metrics or key not in base:
                continue
            print(f"\n{key}   optimised          {name:<18} ({name} - optimised)/SE")
            # the build's difference and SE where it records them (compare's rule: for G the
            # paired jackknife), else the two errors together
            found = base.get("differences", {}).get(key)
            for k, m in enumerate(metrics["modes"]):
                a, sa = metrics[key][k], metrics[key + "_se"][k]
                b, sb = base[key][k], base[key + "_se"][k]
                gap = ((b - a) / max((sa * sa + sb * sb) ** 0.5, 1e-300) if found is None
                       else -found["difference"][k] / max(found["se"][k], 1e-300))
                print(f"  M={m:<3d}  {a:.4f} +- {sa:.4f}   {b:.4f} +- {sb:.4f}   {gap:+.2f}")
    fidelity = metrics["surface_distance_mm"]
    print(f"\nsurface -> corresponded mesh distance: mean {fidelity['mean']:.3f} mm, "
          f"max {fidelity['max']:.3f} mm (voxel {metrics['voxel_size_mm']:.2f} mm)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
