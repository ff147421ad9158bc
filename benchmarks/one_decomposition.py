"""CPU seconds of a build's model and evaluation stages on n_s corresponded shapes: the model of
the correspondence (its SVD), its evaluation (compactness, G, S and the jackknife that the
baselines' paired differences need; the surface measures are left out: no SVD), and a
baseline's evaluation, as a build makes them.

The shapes are the true surfaces of a drawn population (``population.py``: vertex k of every
mesh is vertex k of the model's mean), rigidly aligned to their mean; the baseline's are the
same shapes with 0.2 mm of noise. Run it with the package of each tree to compare (the tree
decides the route: where ``ShapeModel.from_axes`` exists the model and its evaluation share one
decomposition and the baseline's evaluation builds no model):

    PYTHONPATH=OLD/MDLShapeModel python benchmarks/one_decomposition.py --meshes /tmp/pop1000/meshes
    PYTHONPATH=NEW/MDLShapeModel python benchmarks/one_decomposition.py --meshes /tmp/pop1000/meshes

CPU seconds are the process's (every BLAS thread), so that a shared machine's waiting is not
counted; the SVD alone is timed too. On a loaded machine run it with ``OPENBLAS_NUM_THREADS=1``:
a threaded SVD's threads spin while they wait for each other, and count that as CPU time.
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import numpy as np


def cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def aligned(shapes: np.ndarray, rounds: int = 3) -> np.ndarray:
    """The shapes rigidly aligned (rotation and translation, Kabsch) to their mean."""
    shapes = shapes - shapes.mean(axis=1, keepdims=True)
    for _ in range(rounds):
        cross = np.einsum("spi,pj->sij", shapes, shapes.mean(axis=0))   # X^T Y per shape
        u, _, vt = np.linalg.svd(cross)
        u[:, :, -1] *= np.sign(np.linalg.det(u @ vt))[:, None]          # no reflection
        shapes = np.einsum("spi,sij->spj", shapes, u @ vt)
    return shapes


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--meshes", type=Path, required=True)
    parser.add_argument("--cases", type=int, nargs="+", default=[1000])
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args()
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.model.evaluation import evaluate
    from mdlshapemodel.model.shape_model import ShapeModel
    from mdlshapemodel.prepare.io import read_mesh

    config = BuildConfig()
    shared = hasattr(ShapeModel, "from_axes")
    files = sorted(args.meshes.glob("*.vtp"))[:max(args.cases)]
    everything = aligned(np.stack([read_mesh(f)[0] for f in files]).astype(np.float64))
    print(f"route: {'one decomposition' if shared else 'a decomposition each'}; "
          f"{everything.shape[1]} points")
    print("| n_s | SVD alone | model | evaluation | baseline's evaluation | in all |")
    print("|---|---|---|---|---|---|")
    for n_s in args.cases:
        shapes = everything[:n_s]
        weights = np.full(shapes.shape[1], 1.0 / shapes.shape[1])
        noisy = shapes + np.random.default_rng(1).normal(scale=0.2, size=shapes.shape)
        settings = dict(max_modes=config.evaluation_modes, n_samples=config.specificity_samples,
                        jackknife=True, generalization_cases=config.generalization_cases)
        for _ in range(args.repeats):
            started = cpu()
            np.linalg.svd(shapes.reshape(n_s, -1) - shapes.reshape(n_s, -1).mean(axis=0),
                          full_matrices=False)
            alone = cpu() - started
            started = cpu()
            if shared:
                from mdlshapemodel.model.space import principal_axes
                axes = principal_axes(shapes, weights)
                model = ShapeModel.from_axes(axes, weights)
            else:
                model = ShapeModel.from_shapes(shapes, weights)
            modelled = cpu() - started
            started = cpu()
            extra = {"axes": axes} if shared else {}
            evaluate(shapes, weights, model.variances, rng=np.random.default_rng(0), **settings,
                     **extra)
            evaluated = cpu() - started
            started = cpu()
            variances = None if shared else ShapeModel.from_shapes(noisy, weights).variances
            evaluate(noisy, weights, variances, rng=np.random.default_rng(0), **settings)
            baseline = cpu() - started
            print(f"| {n_s} | {alone:.1f} | {modelled:.1f} | {evaluated:.1f} | {baseline:.1f} | "
                  f"{modelled + evaluated + baseline:.1f} |", flush=True)


if __name__ == "__main__":
    main()
