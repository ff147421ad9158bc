"""Build a shape model from Python: the demo population, written as label maps, then modelled.

    python examples/build_model.py [OUTPUT]      (default OUTPUT: example-model)

Writes OUTPUT/labels/*.nii.gz (12 generated label maps) and the build's folder OUTPUT/model
(model.h5, mean.vtp, correspondence/, report.html, ...), then prints the model's first variances.
"""

import sys
from pathlib import Path

from mdlshapemodel import BuildConfig, ShapeModel, build_model
from mdlshapemodel.demo import write_demo_population


def main(output: Path) -> None:
    labels = write_demo_population(output / "labels", n_subjects=12, seed=0)
    config = BuildConfig(points=162,          # a coarse sampling grid: quick
                         max_time=20,         # seconds of optimisation at most
                         baselines=[],        # no baseline models to evaluate
                         specificity_samples=500, workers=2)
    result = build_model(labels, output / "model", config)
    print(f"{len(result.cases)} cases, {len(result.rejected)} rejected; objective "
          f"{result.initial_objective:.1f} -> {result.final_objective:.1f} nats")

    model = ShapeModel.load(output / "model" / "model.h5")    # what the build wrote
    print("variances of the first 3 modes (mm^2):", model.variances[:3].round(3))


if __name__ == "__main__":   # needed: build_model starts worker processes with "spawn"
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "example-model"))
