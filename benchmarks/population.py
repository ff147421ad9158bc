"""A synthetic population of hippocampus-like label maps, as large as wanted, for scaling studies.

Shapes are drawn from a shape model built from the shared hippocampi: scores b_m ~ N(0, lambda_m)
on every mode (clipped at 3 SD), plus a small smooth per-case field along the mean's normals (a
few Gaussian bumps, largest displacement ``--noise`` mm), then a random rigid pose, and each shape
is voxelised at ``--spacing`` mm (the library's ``mesh_to_mask``), so a build sees only label
maps. Cases are written in parallel (``--workers`` processes).

The true surfaces are written too, in the layout of ``ground_truth.py``: ``meshes/<case>.vtp``
(vertex k of every case is vertex k of the model's mean, ``template.vtp``), so that
``ground_truth.py evaluate`` measures a build's correspondence against the truth.
``--meshes-only`` writes them (and ``truth.json``) for a population made before, without
voxelising again: every case is drawn from its own seeded generator.

    mdlshapemodel build ../shared/data/hippocampus/labels --label 1,2 -o /tmp/h100
    python benchmarks/population.py --model /tmp/h100/model.h5 --cases 1000 --output /tmp/pop1000
    python benchmarks/ground_truth.py evaluate /tmp/pop1000 BUILD [BUILD ...]

The label maps are ``labels/synth_0000.nii.gz`` ... (label 1), the shapes' scores and poses are in
``truth.json``.

``--build`` then builds the population end to end with the real command line in a subprocess
(an empty preprocessing cache; build options after ``--``) and prints one row: wall time, CPU
time of the build and all its processes, the peak of their summed resident memory (sampled every
0.1 s; the largest single process in brackets), the optimisation's evaluations and how it ended,
G(1) and S(1) with their standard errors (and how many cases G left out):

    nice -n 10 python benchmarks/population.py --model /tmp/h82/model.h5 --cases 1000 \
        --output /tmp/pop1000 --build -- --max-time 1700

``--sizes`` builds the first N cases for each N given, one after the other, each into
``BUILDS/nN`` (``--builds``, default ``OUTPUT/builds``), and appends each size's row to
``BUILDS/table.md`` and a row of its stages (wall and CPU seconds, peak memory: from its
build.log and the samples) to ``BUILDS/stages.md`` as soon as it is done, so that a night's run
keeps every finished size (``stage_fit.py`` fits the stages); a failed build gets a row saying
so and the next size runs. ``--drawn`` builds label maps drawn
before (``OUTPUT/labels``) without drawing; the builds may go elsewhere
(``--builds``), so that a shared population stays untouched:

    nice -n 10 python benchmarks/population.py --model /tmp/h82/model.h5 --cases 10000 \
        --output /tmp/pop10000 --sizes 2500 5000 10000 -- --max-time 7000
    python benchmarks/population.py --model /tmp/h82/model.h5 --output /tmp/pop1000 --drawn \
        --sizes 125 250 --builds /tmp/stages -- --max-sweeps 1
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals of an outward-oriented mesh."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    face_normals = np.cross(b - a, c - a)
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_normals)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)


def draw_case(model, rng: np.random.Generator, noise: float, bumps: int, width: float,
              rotation_deg: float, translation: float) -> tuple[np.ndarray, dict]:
    """One shape (n_p, 3) in mm and what made it."""
    from mdlshapemodel.geometry import rotation_from_vector

    scores = np.clip(rng.standard_normal(model.n_modes), -3.0, 3.0) * np.sqrt(model.variances)
    shape = model.instance(scores)
    normals = vertex_normals(model.mean, model.triangles)
    centres = shape[rng.choice(len(shape), bumps, replace=False)]
    d2 = np.sum((shape[:, None, :] - centres[None]) ** 2, axis=2)
    field = np.exp(-d2 / (2.0 * width ** 2)) @ rng.standard_normal(bumps)
    field *= noise / max(np.max(np.abs(field)), 1e-12)
    shape = shape + field[:, None] * normals
    pose = rotation_from_vector(rng.standard_normal(3) * np.radians(rotation_deg) / np.sqrt(3))
    shift = rng.standard_normal(3) * translation
    shape = (shape - shape.mean(axis=0)) @ pose.T + shape.mean(axis=0) + shift
    return shape, {"scores": scores.tolist(), "rotation": pose.tolist(), "shift": shift.tolist(),
                   "noise_rms_mm": float(np.sqrt(np.mean(field ** 2)))}


def write_case(arguments) -> dict:
    """Draw case ``index`` (its own generator: the same file whatever the worker) and write it."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import SimpleITK as sitk

    from mdlshapemodel.model.shape_model import ShapeModel
    from mdlshapemodel.prepare import surface

    from mdlshapemodel.prepare.io import write_polydata

    model_path, index, seed, output, spacing, noise, voxelise = arguments
    model = ShapeModel.load(model_path)
    rng = np.random.default_rng([seed, index])
    shape, record = draw_case(model, rng, noise, bumps=8, width=6.0, rotation_deg=10.0,
                              translation=3.0)
    name = f"synth_{index:04d}"
    write_polydata(Path(output) / "meshes" / f"{name}.vtp", shape, np.asarray(model.triangles))
    record.update(name=name)
    if not voxelise:
        return record
    mask, origin = surface.mesh_to_mask(shape, np.asarray(model.triangles), spacing)
    image = sitk.GetImageFromArray(mask)
    image.SetSpacing((spacing,) * 3)
    image.SetOrigin(tuple(float(o) for o in origin))
    sitk.WriteImage(image, str(Path(output) / "labels" / f"{name}.nii.gz"), useCompression=True)
    record.update(voxels=list(mask.shape[::-1]))
    return record


HEADER = ("| cases | wall | CPU | peak memory, all processes (largest) | evaluations | ended | "
          "G(1) mm² | S(1) mm² |\n|---|---|---|---|---|---|---|---|")


def build_row(output: Path, cases: int, extra: list, built: Path | None = None) -> tuple:
    """Build the first ``cases`` label maps of ``output/labels`` with the command line (into
    ``built``, default ``output/build``): the benchmark's table row and the row of its stages
    (:func:`end_to_end.stage_table`), or a row saying how the build failed."""
    from end_to_end import stage_table, watched

    inputs = sorted((output / "labels").glob("*.nii.gz"))[:cases]
    if len(inputs) < cases:
        raise SystemExit(f"only {len(inputs)} label maps in {output / 'labels'}, {cases} wanted")
    built = output / "build" if built is None else built
    with tempfile.TemporaryDirectory() as cache:
        # the cases drawn now: the folder may hold more from an earlier, larger draw
        command = [sys.executable, "-m", "mdlshapemodel.cli", "build", *map(str, inputs),
                   "--label", "1", "-o", str(built), "-q", "--cache-dir", cache, *extra,
                   *(["--overwrite"] if (built / "build.log").exists() else [])]
        code, wall, cpu, watch = watched(command)
    stages = stage_table(built / "build.log", watch) if (built / "build.log").exists() else []
    staged = (f"| {cases} | " + " | ".join(f"{name}: {seconds:.0f} s ({used:.0f} CPU-s), "
                                           f"{peak / 1024:.2f} GB"
                                           for name, seconds, used, peak in stages) + " |")
    if code != 0:
        return (f"| {cases} | {wall:.0f} s | {cpu:.0f} s | {watch.peak_total:.0f} MB "
                f"({watch.peak_single:.0f} MB) | the build failed (exit code {code}) "
                f"| | | |"), staged
    metrics = json.loads((built / "metrics.json").read_text())
    with open(built / "convergence.csv") as file:
        trace = list(csv.DictReader(file))
    evaluations = int(trace[-1]["evaluations"]) if trace else 0
    ending = metrics["optimisation"]["stopped_by"]
    left_out = metrics.get("generalization_cases", metrics["n_shapes"])
    return (f"| {metrics['n_shapes']} | {wall:.0f} s | {cpu:.0f} s | {watch.peak_total:.0f} MB "
            f"({watch.peak_single:.0f} MB) | {evaluations} | {ending} | "
            f"{metrics['generalization'][0]:.4f} ± {metrics['generalization_se'][0]:.4f} "
            f"({left_out} left out) | "
            f"{metrics['specificity'][0]:.4f} ± {metrics['specificity_se'][0]:.4f} |"), staged


def build_sizes(output: Path, sizes: list, extra: list, builds: Path) -> None:
    """Build the first N label maps for each N of ``sizes`` into ``builds/nN``, appending each
    size's row to ``builds/table.md`` and the row of its stages to ``builds/stages.md`` as soon
    as it is done."""
    builds.mkdir(parents=True, exist_ok=True)
    table, stages = builds / "table.md", builds / "stages.md"
    heading = (f"\n{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, build options: "
               f"{' '.join(extra) or '(defaults)'}\n\n")
    with open(table, "a") as file:
        file.write(heading + HEADER + "\n")
    with open(stages, "a") as file:
        file.write(heading + "| cases | each stage: wall s (CPU s of all processes), peak memory "
                   "of all processes |\n|---|---|\n")
    for cases in sizes:
        row, staged = build_row(output, cases, extra, builds / f"n{cases}")
        print(row, staged, sep="\n", flush=True)
        with open(table, "a") as file:
            file.write(row + "\n")
        with open(stages, "a") as file:
            file.write(staged + "\n")
    print(f"-> {table}, {stages}", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", help="model.h5 of a build of the hippocampi (to draw)")
    parser.add_argument("--cases", type=int, default=1000)
    parser.add_argument("--output", required=True)
    parser.add_argument("--spacing", type=float, default=1.0, help="voxel size, mm")
    parser.add_argument("--noise", type=float, default=0.5,
                        help="largest per-case displacement along the normals, mm")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--meshes-only", action="store_true",
                        help="write the true meshes (and truth.json) only, not the label maps")
    parser.add_argument("--build", action="store_true",
                        help="then build it end to end and print the benchmark's row")
    parser.add_argument("--sizes", type=int, nargs="+",
                        help="build the first N cases for each N, one table (BUILDS/table.md, "
                             "BUILDS/stages.md)")
    parser.add_argument("--builds", help="where --sizes builds (default OUTPUT/builds)")
    parser.add_argument("--drawn", action="store_true",
                        help="do not draw: build the label maps already in OUTPUT/labels")
    parser.add_argument("extra", nargs=argparse.REMAINDER, help="build options after --")
    args = parser.parse_args()
    output = Path(args.output)
    extra = [a for a in args.extra if a != "--"]
    if not args.drawn:
        if args.model is None:
            parser.error("--model is needed to draw the population (or --drawn)")
        draw(args, output)
    if args.sizes:
        build_sizes(output, args.sizes, extra,
                    Path(args.builds) if args.builds else output / "builds")
    elif args.build:
        print(HEADER)
        print(build_row(output, args.cases, extra)[0], flush=True)


def draw(args, output: Path) -> None:
    """Draw ``args.cases`` cases into ``output`` (label maps, true meshes, truth.json)."""
    from mdlshapemodel.model.shape_model import ShapeModel
    from mdlshapemodel.prepare.io import write_polydata

    for folder in ("labels", "meshes"):
        (output / folder).mkdir(parents=True, exist_ok=True)
    model = ShapeModel.load(args.model)
    write_polydata(output / "template.vtp", model.mean, np.asarray(model.triangles))
    started = time.perf_counter()
    jobs = [(args.model, i, args.seed, str(output), args.spacing, args.noise,
             not args.meshes_only) for i in range(args.cases)]
    with ProcessPoolExecutor(args.workers) as pool:
        records = list(pool.map(write_case, jobs, chunksize=8))
    if args.meshes_only:    # keep the voxel sizes recorded when the label maps were written
        before = {case["name"]: case for case in
                  json.loads((output / "truth.json").read_text())["cases"]}
        for record in records:
            record["voxels"] = before[record["name"]]["voxels"]
    (output / "truth.json").write_text(json.dumps({
        "model": str(args.model), "spacing_mm": args.spacing, "noise_mm": args.noise,
        "seed": args.seed, "cases": records}, indent=1))
    written = "true meshes" if args.meshes_only else "label maps and true meshes"
    print(f"{args.cases} cases' {written} in {time.perf_counter() - started:.0f} s -> {output}")


if __name__ == "__main__":
    main()
