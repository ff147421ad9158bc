"""The Slicer module's Logic against the command line, on shared hippocampus label maps.

Run in the virtualenv with slicer-core (see the README's "3D Slicer" section). The first N label
maps are loaded into a real MRML scene as segmentation nodes (Slicer's own segmentation reader),
built with ``MDLShapeModelLogic().buildModel`` (labels 1+2, every other setting the default), and
the same files with ``mdlshapemodel build --label 1,2`` in a subprocess, each with an empty
preprocessing cache. Printed: both wall times, the largest difference between the two models
(mean, modes, variances, scores) and between every case's corresponded points (the Logic's model
node, RAS, against the command line's .vtp, LPS), the objective of both, and how far the
corresponded points lie from the closed surface Slicer itself makes of each segmentation.

    python benchmarks/slicer_logic.py --cases 10 --output /tmp/slicer10
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "hippocampus" / "labels"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=10)
    parser.add_argument("--output", required=True)
    args = parser.parse_args()
    output = Path(args.output)
    files = sorted(SHARED.glob("*.nii.gz"))[:args.cases]

    sys.path.insert(0, str(ROOT / "Testing" / "Slicer"))
    import harness

    harness.install()
    import MDLShapeModel
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    from mdlshapemodel import BuildConfig, ShapeModel
    from mdlshapemodel.prepare import io
    from mdlshapemodel.prepare.surface import point_surface_distances

    os.environ["MDLSHAPEMODEL_CACHE"] = tempfile.mkdtemp(prefix="slicer-logic-cache-")
    reader = harness.segmentations_logic()
    nodes = [reader.LoadSegmentationFromFile(str(f), True, f.name.split(".")[0]) for f in files]
    started = time.perf_counter()
    result = MDLShapeModel.MDLShapeModelLogic().buildModel(nodes, output / "slicer",
                                                           BuildConfig(labels=[1, 2]))
    logic_seconds = time.perf_counter() - started

    environment = {**os.environ, "MDLSHAPEMODEL_CACHE": tempfile.mkdtemp(prefix="cli-cache-")}
    started = time.perf_counter()
    subprocess.run([sys.executable, "-m", "mdlshapemodel.cli", "build", *map(str, files),
                    "-o", str(output / "cli"), "--label", "1,2", "-q"], check=True,
                   env=environment)
    cli_seconds = time.perf_counter() - started

    ours, theirs = (ShapeModel.load(output / name / "model.h5") for name in ("slicer", "cli"))
    print(f"{len(files)} hippocampus label maps; Logic {logic_seconds:.0f} s (segmentation nodes "
          f"-> model and table nodes), command line {cli_seconds:.0f} s")
    print(f"case names equal: {ours.names == theirs.names}; "
          f"{len(result.correspondenceModelNodes)} corresponded model nodes with point counts "
          f"{sorted({n.GetPolyData().GetNumberOfPoints() for n in result.correspondenceModelNodes})}"
          f"; rejected {result.rejected}")
    for name in ("mean", "modes", "variances", "scores"):
        a, b = getattr(ours, name), getattr(theirs, name)
        print(f"  {name:9s} shape {a.shape}, identical: {np.array_equal(a, b)}, "
              f"largest difference {np.abs(a - b).max():.3g}")
    objectives = [json.loads((output / n / "metrics.json").read_text())["objective"]["final"]
                  for n in ("slicer", "cli")]
    print(f"  objective (eq. 14 + prior + guides): Logic {objectives[0]:.4f}, "
          f"command line {objectives[1]:.4f}")
    largest, distances = 0.0, []
    for node, segmentation in zip(result.correspondenceModelNodes, nodes):
        ras = vtk_to_numpy(node.GetPolyData().GetPoints().GetData()).astype(float)
        lps, _ = io.read_mesh(output / "cli" / "correspondence" / f"{node.GetName()}.vtp")
        largest = max(largest, float(np.abs(ras * [-1, -1, 1] - lps).max()))
        segmentation.CreateClosedSurfaceRepresentation()
        append = vtk.vtkAppendPolyData()
        for k in range(segmentation.GetSegmentation().GetNumberOfSegments()):
            surface = vtk.vtkPolyData()
            segmentation.GetClosedSurfaceRepresentation(
                segmentation.GetSegmentation().GetNthSegmentID(k), surface)
            append.AddInputData(surface)
        append.Update()
        vertices, triangles = io.mesh_arrays(append.GetOutput())
        distances.append(point_surface_distances(ras, vertices, triangles).mean())
    print(f"  corresponded points, Logic (RAS -> LPS) against the command line's files: largest "
          f"difference {largest:.3g} mm")
    print(f"  mean distance of the corresponded points to Slicer's own closed surface of each "
          f"segmentation: {np.mean(distances):.3f} mm (largest case {np.max(distances):.3f} mm)")


if __name__ == "__main__":
    main()
