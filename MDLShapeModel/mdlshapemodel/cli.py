"""The ``mdlshapemodel`` command line."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from .config import BASELINES, CORRESPONDENCES, STRATEGIES, WARPS, BuildConfig
from .errors import MDLShapeModelError

log = logging.getLogger("mdlshapemodel")


def _labels(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"labels must be integers, got {text!r}") from None
    return values


def _baselines(text: str) -> list[str]:
    values = [v for v in text.replace(",", " ").split()]
    unknown = [v for v in values if v not in BASELINES]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown baseline {unknown[0]!r}; choose from "
                                         f"{', '.join(BASELINES)}")
    return values


def _warps(text: str) -> list[str]:
    values = [v for v in text.replace(",", " ").split()]
    unknown = [v for v in values if v not in WARPS]
    if unknown or not values:
        problem = f"unknown warp kind {unknown[0]!r}" if unknown else "no warp kind given"
        raise argparse.ArgumentTypeError(f"{problem}; choose from {', '.join(WARPS)}")
    return values


def _add_build_options(parser: argparse.ArgumentParser, defaults: BuildConfig):
    group = parser.add_argument_group("correspondence")
    group.add_argument("--points", type=int, default=defaults.points,
                       help="sample points per shape (icosphere when 10*4^k+2; default %(default)s)")
    group.add_argument("--correspondence", choices=CORRESPONDENCES, default=defaults.correspondence,
                       help="'mdl': optimised by minimum description length; 'cpd': a template "
                            "case registered onto every case by coherent point drift, the common "
                            "alternative, for comparison (default %(default)s)")
    group.add_argument("--baselines", type=_baselines, default=defaults.baselines, metavar="LIST",
                       help="other correspondences evaluated on the same cases and shown in the "
                            "report: comma-separated from none (the initial correspondence) and "
                            "cpd; '' for no baseline (default none)")
    group.add_argument("--strategy", choices=STRATEGIES, default=defaults.strategy,
                       help="optimisation strategy; 'none' keeps the initial (equal-spacing) "
                            "correspondence (default %(default)s)")
    group.add_argument("--warps", type=_warps, default=defaults.warps, metavar="LIST",
                       help="one-at-a-time strategies: the warps each step draws from, uniformly, "
                            "comma-separated from symmetric (the paper's theta kernel), asymmetric "
                            "and shear (the Appendix's asymmetric theta and shear/twist maps) and "
                            "rotation (a global rotation of the parameter sphere) "
                            "(default symmetric)")
    group.add_argument("--max-time", type=float, default=defaults.max_time, metavar="SECONDS",
                       help="time budget of the optimisation (default %(default)s)")
    group.add_argument("--max-sweeps", type=int, default=defaults.max_sweeps, metavar="N",
                       help="at most N sweeps over the examples (fast: rounds) per phase; unlike "
                            "--max-time, a budget that repeats exactly (default %(default)s)")
    group.add_argument("--seed", type=int, default=defaults.seed,
                       help="random seed of the paper's strategies (fast draws no random "
                            "numbers): the same seed and inputs give the same model bit for bit, "
                            "unless --max-time cuts the runs at different points "
                            "(default %(default)s)")
    group.add_argument("--delta-range", type=float, nargs=2, default=defaults.delta_range,
                       metavar=("MIN", "MAX"),
                       help="coding accuracy range of eq. 14 in voxels (default %(default)s)")
    group.add_argument("--fixed-delta", type=float, default=defaults.fixed_delta,
                       help="coding accuracy of the first phase (eq. 13), voxels "
                            "(default %(default)s)")
    group.add_argument("--fixed-fraction", type=float, default=defaults.fixed_fraction,
                       help="share of --max-time spent on the fixed-Delta phase before the full "
                            "objective; 0 skips it (default %(default)s)")
    group.add_argument("--sigma-g", type=float, default=defaults.sigma_g,
                       help="width distribution of random kernels (default 1/32)")
    group.add_argument("--no-scaling", action="store_true",
                       help="keep size: Procrustes and pose use rotation and translation only")
    group.add_argument("--tolerance", type=float, default=defaults.tolerance,
                       help="convergence: stop when a sweep gains less than this fraction of the "
                            "total gain, three times in a row (default %(default)s)")
    inputs = parser.add_argument_group("inputs and surfaces")
    inputs.add_argument("--label", type=_labels, action="extend", default=[], metavar="L",
                        help="label value(s) whose union is the object, e.g. --label 1,2 "
                             "(default: all non-zero)")
    inputs.add_argument("--mirror", action="append", default=[], metavar="PATTERN",
                        help="reflect inputs whose file name matches PATTERN (x -> -x), e.g. "
                             "--mirror '*_rfemur*' to model right and left sides together; "
                             "repeatable")
    inputs.add_argument("--voxel-size", type=float, default=None,
                        help="mm per voxel for mesh inputs (default: their mean edge length)")
    inputs.add_argument("--surface", choices=("gaussian", "slicer"), default=defaults.surface_method,
                        help="label map -> surface: Gaussian blur + flying edges, or 3D Slicer's "
                             "conversion (flying edges + windowed sinc); either blurs more when "
                             "the surface is not genus 0 (default %(default)s)")
    inputs.add_argument("--smoothing", type=float, default=defaults.smoothing_sigma,
                        help="gaussian: blur of masks before contouring, voxels (default %(default)s)")
    inputs.add_argument("--smoothing-factor", type=float, default=defaults.smoothing_factor,
                        help="slicer: smoothing factor 0..1 of the windowed-sinc filter "
                             "(default %(default)s)")
    inputs.add_argument("--decimation", type=float, default=defaults.decimation,
                        help="slicer: fraction of triangles removed before smoothing "
                             "(default %(default)s)")
    inputs.add_argument("--edge-length", type=float, default=defaults.edge_length,
                        help="edge length of the remeshed surfaces, voxels (default %(default)s)")
    inputs.add_argument("--target-vertices", type=int, default=defaults.target_vertices,
                        help="meshes with more vertices are decimated (default %(default)s)")
    run = parser.add_argument_group("running and evaluation")
    run.add_argument("--workers", type=int, default=defaults.workers,
                     help="processes for per-case work (default: all cores, %(default)s)")
    run.add_argument("--cache-dir", default=None, metavar="DIR",
                     help="where preprocessed cases are kept for rebuilds (default: "
                          "$MDLSHAPEMODEL_CACHE or ~/.cache/mdlshapemodel)")
    run.add_argument("--no-cache", action="store_true",
                     help="preprocess every case again and store nothing")
    run.add_argument("--strict", action="store_true", help="fail (exit 2) if any input is rejected")
    run.add_argument("--evaluation-modes", type=int, default=defaults.evaluation_modes,
                     help="measures are reported for M = 1..this (default %(default)s)")
    run.add_argument("--specificity-samples", type=int, default=defaults.specificity_samples,
                     help="model samples for specificity (default %(default)s)")
    run.add_argument("--surface-samples", type=int, default=defaults.surface_samples,
                     help="model samples for specificity measured surface to surface; 0 leaves "
                          "out the surface-to-surface measures (default %(default)s)")
    run.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")


def _config_from(args) -> BuildConfig:
    return BuildConfig(labels=args.label, voxel_size=args.voxel_size, mirror=args.mirror,
                       smoothing_sigma=args.smoothing, surface_method=args.surface,
                       smoothing_factor=args.smoothing_factor, decimation=args.decimation,
                       edge_length=args.edge_length, target_vertices=args.target_vertices,
                       max_smoothing_sigma=max(2.0, args.smoothing), points=args.points,
                       strategy=args.strategy, warps=args.warps, scaling=not args.no_scaling,
                       delta_range=tuple(args.delta_range), fixed_delta=args.fixed_delta,
                       sigma_g=args.sigma_g, max_time=args.max_time, tolerance=args.tolerance,
                       fixed_fraction=args.fixed_fraction, max_sweeps=args.max_sweeps,
                       seed=args.seed, evaluation_modes=args.evaluation_modes,
                       specificity_samples=args.specificity_samples, workers=args.workers,
                       correspondence=args.correspondence, baselines=args.baselines,
                       surface_samples=args.surface_samples,
                       cache_dir="" if args.no_cache else args.cache_dir,
                       strict=args.strict).validate()


class _Progress:
    """Prints progress messages to stderr, at most one every few seconds."""

    def __init__(self, interval: float = 5.0):
        self.interval = interval
        self.last = 0.0

    def __call__(self, fraction, message):
        now = time.monotonic()
        if now - self.last >= self.interval or fraction == 1.0:
            self.last = now
            prefix = f"[{100 * fraction:3.0f}%] " if fraction is not None else ""
            log.info("%s%s", prefix, message)


def _summary(result) -> str:
    m = result.metrics
    lines = [f"model of {m['n_shapes']} cases written to {result.output}",
             f"  objective (eq. 14): {result.initial_objective:.3f} -> {result.final_objective:.3f}"
             f" nats ({m['strategy']})"]
    for key, symbol in (("generalization", "G"), ("specificity", "S")):
        shown = ", ".join(f"{v:.3f}" for v in m[key][:3])
        for name, values in m.get("baselines", {}).items():
            shown += f" ({name}: " + ", ".join(f"{v:.3f}" for v in values[key][:3]) + ")"
        lines.append(f"  {key:<14} {symbol}(1..3): {shown} mm^2")
    lines += [f"  surface fidelity: mean {m['surface_distance_mm']['mean']:.3f} mm, "
              f"max {m['surface_distance_mm']['max']:.3f} mm",
              f"  report: {result.output / 'report.html'}"]
    if result.rejected:
        lines.append(f"  {len(result.rejected)} input(s) rejected: see {result.output / 'rejected.csv'}")
    return "\n".join(lines)


def _run_build(inputs, output, config) -> int:
    from .build import build_model

    result = build_model(inputs, output, config, progress=_Progress())
    print(_summary(result))
    return 0


def _run_compare(args) -> int:
    from .report.compare import (compare_populations, load_population, summary_lines,
                                 write_comparison)

    populations = [load_population(path) for path in args.outputs]
    labels = [p.label for p in populations]
    for k, population in enumerate(populations):  # labels must be unique keys
        if labels.count(population.label) > 1:
            population.label = f"{population.label} #{k + 1}"
    result = compare_populations(populations, args.modes, args.samples, args.seed)
    page = write_comparison(result, args.output)
    print("\n".join(summary_lines(result)))
    print(f"comparison of {len(populations)} models on {result['n_cases']} shared cases: {page}")
    return 0


def _run_fit(args) -> int:
    from .model.fitting import fit_cases

    results, rejected = fit_cases(args.model, args.inputs, args.output, args.label,
                                  args.max_time, args.max_sweeps, args.seed,
                                  strategy=args.strategy)
    for name, path, reason in rejected:
        log.warning("rejected %s: %s", path, reason)
    for result in results:
        print(f"{result.name}: reconstruction error with all modes "
              f"{result.squared_error[-1]:.4f} mm^2 ({result.distance_error[-1]:.3f} mm mean), "
              f"mean shape only {result.squared_error[0]:.4f} mm^2; objective "
              f"{result.objective['initial']:.3f} -> {result.objective['final']:.3f}")
    print(f"fitted {len(results)} case(s) to {args.model}: {Path(args.output) / 'fit.json'}")
    return 0 if results else 2


def main(argv=None) -> int:
    defaults = BuildConfig()
    parser = argparse.ArgumentParser(
        prog="mdlshapemodel",
        description="Statistical shape models with correspondence by minimum description length.")
    commands = parser.add_subparsers(dest="command", required=True)
    build = commands.add_parser("build", help="build a model from label maps or meshes")
    build.add_argument("inputs", nargs="+", help="label maps, meshes, or folders of them")
    build.add_argument("-o", "--output", required=True, help="output folder")
    _add_build_options(build, defaults)
    demo = commands.add_parser("demo", help="build a model of a generated population (about 30 s)")
    demo.add_argument("-o", "--output", default="mdlshapemodel-demo", help="output folder "
                      "(default %(default)s)")
    demo.add_argument("--subjects", type=int, default=12, help="population size (default 12)")
    demo.add_argument("--max-time", type=float, default=40.0, help="optimisation seconds (default 40)")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("-q", "--quiet", action="store_true")
    compare = commands.add_parser(
        "compare", help="evaluate several models of the same cases side by side",
        description="Evaluate models (build output folders) on the cases they share and say, for "
                    "each number of modes, whether they differ by more than two standard errors "
                    "(the first model is the reference). Writes compare.html/.csv/.json.")
    compare.add_argument("outputs", nargs="+", help="build output folders (or their model.h5)")
    compare.add_argument("-o", "--output", default="comparison", help="folder for the comparison "
                         "(default %(default)s)")
    compare.add_argument("--modes", type=int, default=defaults.evaluation_modes,
                         help="M = 1..this (default %(default)s)")
    compare.add_argument("--samples", type=int, default=defaults.specificity_samples,
                         help="specificity samples (default %(default)s)")
    compare.add_argument("--seed", type=int, default=0)
    compare.add_argument("-q", "--quiet", action="store_true")
    fit = commands.add_parser(
        "fit", help="fit new cases to an existing model: correspondence, scores, reconstruction",
        description="Find the correspondence of new cases against a model (optimising only each "
                    "new case's reparameterization and pose, with the model's training shapes "
                    "fixed) and write their scores and reconstructions.")
    fit.add_argument("model", help="model.h5 or the build output folder holding it")
    fit.add_argument("inputs", nargs="+", help="label maps, meshes, or folders of them")
    fit.add_argument("-o", "--output", required=True, help="output folder")
    fit.add_argument("--label", type=_labels, action="extend", default=[], metavar="L",
                     help="label value(s) of the object (default: those the model was built with)")
    fit.add_argument("--max-time", type=float, default=60.0, metavar="SECONDS",
                     help="optimisation time per case (default %(default)s)")
    fit.add_argument("--max-sweeps", type=int, default=10_000, metavar="N")
    fit.add_argument("--strategy", choices=[s for s in STRATEGIES if s != "none"],
                     help="optimisation strategy for the new cases (default: the model's own)")
    fit.add_argument("--seed", type=int, default=0)
    fit.add_argument("-q", "--quiet", action="store_true")
    args = parser.parse_args(argv)

    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("mdlshapemodel: %(message)s"))
    handler.setLevel(logging.WARNING if args.quiet else logging.INFO)
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    try:
        if args.command == "build":
            return _run_build(args.inputs, args.output, _config_from(args))
        if args.command == "compare":
            return _run_compare(args)
        if args.command == "fit":
            return _run_fit(args)
        if args.command == "demo":
            from .demo import write_demo_population

            output = Path(args.output)
            paths = write_demo_population(output / "inputs", args.subjects, args.seed)
            log.info("wrote %d demo label maps to %s", len(paths), output / "inputs")
            config = BuildConfig(points=642, max_time=args.max_time, seed=args.seed,
                                 specificity_samples=2000).validate()
            return _run_build(paths, output, config)
    except MDLShapeModelError as error:
        print(f"mdlshapemodel: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mdlshapemodel: interrupted", file=sys.stderr)
        return 130
    finally:
        log.removeHandler(handler)
    return 1


if __name__ == "__main__":
    sys.exit(main())
