"""Shapes of a model as meshes: the mean and +/-2 standard deviations along the first mode.

    python examples/instances.py MODEL.h5 [OUTPUT]     (default OUTPUT: instances)

Writes OUTPUT/mean.vtp, OUTPUT/mode1_minus2sd.vtp and OUTPUT/mode1_plus2sd.vtp, each with the
model's triangles, in the model's frame (open them in ParaView or 3D Slicer).
"""

import sys
from pathlib import Path

from mdlshapemodel import ShapeModel


def main(model_path: Path, output: Path) -> None:
    model = ShapeModel.load(model_path)
    output.mkdir(parents=True, exist_ok=True)
    model.save_shape(output / "mean.vtp")                        # the mean by default
    for sd, name in ((-2.0, "mode1_minus2sd"), (2.0, "mode1_plus2sd")):
        points = model.instance(standard_deviations=[sd])       # (n_points, 3)
        model.save_shape(output / f"{name}.vtp", points)
    print(f"wrote 3 shapes of {len(model.mean)} points to {output}")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2] if len(sys.argv) > 2 else "instances"))
