"""The ``mdlshapemodel`` command line."""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import signal
import sys
import threading
import time
import typing
from dataclasses import MISSING, fields
from pathlib import Path
from typing import Callable

from .config import (ANALYSIS_SIZES, DISPLACEMENTS, FAMILY_WISE, PART_ALIGNMENTS, STRATEGIES,
                     SUPERIMPOSITIONS, TAILS, VARIANCES, AnalysisConfig, BuildConfig, parse_items)
from .correspondence.trace import stop_summary
from .errors import Cancelled, ConfigError, InternalError, MDLShapeModelError
from .options import BUILD_OPTIONS, OPTION_GROUPS
from .progress import ctrl_c
from .version import __version__

log = logging.getLogger("mdlshapemodel")


# The build options: the fields of BuildConfig that options.BUILD_OPTIONS offers, each with the
# field's type, default and choices (defined once, in config.py) and the option's flag and help.

def _command_line_fields() -> list:
    """The fields of :class:`BuildConfig` that the ``build`` command offers, in field order."""
    return [f for f in fields(BuildConfig) if f.name in BUILD_OPTIONS]


def _default_of(f):
    return f.default_factory() if f.default is MISSING else f.default


def _flag_of(f) -> str:
    return BUILD_OPTIONS[f.name].flag_of(f.name)


def _dest_of(flag: str) -> str:
    return flag.lstrip("-").replace("-", "_")


def _items(kind: type, metadata) -> Callable[[str], list]:
    """Parser of a list option's argument: :func:`~.config.parse_items` for argparse."""
    noun = metadata.get("item", "value")

    def parse(text: str) -> list:
        try:
            return parse_items(text, kind, noun, metadata.get("choices"),
                               metadata.get("nonempty", False))
        except ConfigError as error:
            raise argparse.ArgumentTypeError(str(error)) from None

    parse.__name__ = noun
    return parse


def _argument(f, annotation) -> dict:
    """argparse keywords of the option of field ``f`` (of type ``annotation``)."""
    metadata, offered = f.metadata, BUILD_OPTIONS[f.name]
    default = _default_of(f)
    keywords = {"dest": f.name, "default": default, "help": offered.help}
    if offered.metavar is not None:
        keywords["metavar"] = offered.metavar
    elif annotation is not bool and "choices" not in metadata:  # named after the flag
        keywords["metavar"] = _dest_of(_flag_of(f)).upper()
    origin, arguments = typing.get_origin(annotation), typing.get_args(annotation)
    if annotation is bool:
        if default and not _flag_of(f).startswith("--no-"):
            raise TypeError(f"{f.name}: a bool option that is on by default needs a --no- flag")
        keywords["action"] = "store_false" if default else "store_true"
    elif origin is list:
        (kind,) = arguments
        if offered.split:
            keywords.update(type=_items(kind, metadata),
                            action="extend" if offered.repeatable else "store")
        elif offered.repeatable:
            keywords.update(type=kind, action="append")
        else:
            raise TypeError(f"{f.name}: a list option must be split or repeatable")
    elif origin is tuple:
        keywords.update(type=arguments[0], nargs=len(arguments))
    else:
        kinds = [a for a in arguments if a is not type(None)] if arguments else [annotation]
        if len(kinds) != 1 or kinds[0] not in (int, float, str):
            raise TypeError(f"{f.name}: no command-line option for the type {annotation}")
        keywords["type"] = kinds[0]
        if "choices" in metadata:
            keywords["choices"] = metadata["choices"]
    return keywords


def _add_build_options(parser: argparse.ArgumentParser):
    annotations = typing.get_type_hints(BuildConfig)
    for name in OPTION_GROUPS:  # group by group, so that the usage line lists them so too
        group = parser.add_argument_group(name)
        for f in _command_line_fields():
            offered = BUILD_OPTIONS[f.name]
            if offered.group == name:
                group.add_argument(_flag_of(f), **_argument(f, annotations[f.name]))
                if offered.off_flag is not None:
                    group.add_argument(offered.off_flag, action="store_true",
                                       help=offered.off_help)
    group.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")


def _config_from(args) -> BuildConfig:
    """The :class:`BuildConfig` of parsed ``build`` options (fields without an option keep
    their defaults)."""
    annotations = typing.get_type_hints(BuildConfig)
    values = {}
    for f in _command_line_fields():
        value = getattr(args, f.name)
        offered = BUILD_OPTIONS[f.name]
        if offered.off_flag is not None and getattr(args, _dest_of(offered.off_flag)):
            value = offered.off_value
        if typing.get_origin(annotations[f.name]) is tuple:
            value = tuple(value)
        values[f.name] = value
    return BuildConfig(**values).validate()


# Log records of progress reports carry this attribute, so that the terminal can leave them out
# while a bar shows the reports.
_PROGRESS_LINE = "mdlshapemodel_progress_line"


class _ProgressDisplay:
    """Shows the reports of :mod:`mdlshapemodel.progress` on stderr, stage by stage.

    A new stage starts when reports switch between a fraction and none, or the fraction falls
    back or starts again after reaching 1: preparing (``prepared k/n``), the CPD registrations,
    the optimisation (no fraction: its message carries the phase, the round or sweep and F) and
    the evaluation.

    Every report may become a log line (stderr and build.log): the first of a stage, the last
    (fraction 1) and otherwise at most one every ``interval`` seconds. With ``live`` (stderr is
    a terminal) the terminal shows a tqdm bar per stage instead, updated on every report: the
    log lines then go to build.log only (see :class:`_TerminalHandler`). Use it as a context
    manager: the bar is closed on the way out, also on errors and Ctrl-C.
    """

    def __init__(self, live: bool = False, stream=None, interval: float = 5.0):
        self.live = live
        self.stream = stream if stream is not None else sys.stderr
        self.interval = interval
        self.fraction = self.bar = None
        self.started = False
        self.logged = -math.inf

    def __enter__(self) -> "_ProgressDisplay":
        return self

    def __exit__(self, *exception) -> None:
        self.close()

    def __call__(self, fraction, message):
        previous = self.fraction
        new_stage = (not self.started or (fraction is None) != (previous is None)
                     or (fraction is not None and (fraction < previous or previous >= 1.0)))
        if new_stage:
            self.close()
            self.started = True
        self.fraction = fraction
        now = time.monotonic()
        if new_stage or fraction == 1.0 or now - self.logged >= self.interval:
            self.logged = now
            prefix = f"[{100 * fraction:3.0f}%] " if fraction is not None else ""
            log.info("%s%s", prefix, message, extra={_PROGRESS_LINE: True})
        if self.live:
            with _interrupt_deferred():
                self._draw(fraction, message)

    def _draw(self, fraction, message):
        if self.bar is None:  # a new bar shows its first report as it opens
            from tqdm import tqdm

            columns = _terminal_columns(self.stream)
            width = {"dynamic_ncols": True} if columns > 0 else {"ncols": 80}
            if fraction is None:
                self.bar = tqdm(total=None, desc=message, file=self.stream, leave=True,
                                bar_format="optimisation [{elapsed}] {desc}", **width)
            else:
                self.bar = tqdm(total=1.0, initial=fraction, desc=message, file=self.stream,
                                leave=True, bar_format="{percentage:3.0f}%|{bar}| {desc} "
                                                       "[{elapsed}<{remaining}]", **width)
        else:  # every report is drawn: the library reports per case, round, sweep or
            # hundred evaluations
            if fraction is not None:
                self.bar.n = fraction
            self.bar.set_description_str(message)
        if fraction == 1.0:
            self.close_bar()

    def close_bar(self):
        """End the current bar (left on screen as it stands)."""
        with _interrupt_deferred():
            bar, self.bar = self.bar, None
            if bar is not None:
                bar.close()

    def close(self):
        """End the current stage (and its bar)."""
        self.close_bar()
        self.started = False


@contextlib.contextmanager
def _interrupt_deferred():
    """Ctrl-C (SIGINT) in the block takes effect when the block is done, so that a bar is never
    left half drawn, or drawn but not yet known (and so never closed). The main thread only
    (elsewhere Ctrl-C does not arrive)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received = []
    previous = signal.signal(signal.SIGINT, lambda number, frame: received.append(number))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if received:
            signal.raise_signal(signal.SIGINT)  # now, to the handler there was before


def _terminal_columns(stream) -> int:
    """Width of the terminal ``stream`` writes to, 0 when unknown."""
    try:
        return os.get_terminal_size(stream.fileno()).columns
    except (AttributeError, OSError, ValueError):
        return 0


class _TerminalHandler(logging.StreamHandler):
    """Log lines on stderr; ``live``: written around the progress bars (tqdm.write), without
    the progress lines that the bars show."""

    def __init__(self, stream, live: bool):
        super().__init__(stream)
        self.live = live
        if live:
            self.addFilter(lambda record: not getattr(record, _PROGRESS_LINE, False))

    def emit(self, record):
        if not self.live:
            super().emit(record)
            return
        try:
            from tqdm import tqdm

            with _interrupt_deferred():
                tqdm.write(self.format(record), file=self.stream)
        except Exception:  # as logging.StreamHandler: a failing log line is reported, not raised
            self.handleError(record)


def _summary(result) -> str:
    m = result.metrics
    measured = m["objective"].get("n_points", m["n_points"])
    lines = [f"model of {m['n_shapes']} cases written to {result.output}",
             f"  objective (eq. 14) + prior + guides: {result.initial_objective:.3f} -> "
             f"{result.final_objective:.3f}"
             f" nats ({m['strategy']}"
             f"{'' if measured == m['n_points'] else f', on {measured} sample points'})",
             f"  optimisation: {stop_summary(m['optimisation']['stopped_by'])}"]
    for key, symbol in (("generalization", "G"), ("specificity", "S")):
        shown = ", ".join(f"{v:.3f}" for v in m[key][:3])
        for name, values in m.get("baselines", {}).items():
            shown += f" ({name}: " + ", ".join(f"{v:.3f}" for v in values[key][:3]) + ")"
        lines.append(f"  {key:<14} {symbol}(1..3): {shown} mm^2")
    lines.append(f"  surface fidelity: mean {m['surface_distance_mm']['mean']:.3f} mm, "
                 f"max {m['surface_distance_mm']['max']:.3f} mm")
    check = m.get("landmark_check")
    if check and check["mean"]["held_out_mm"] is not None:
        lines.append("  landmarks, mean distance from the given ones: "
                     + (f"{check['mean']['held_out_mm']:.2f} mm left out of the guides, "
                        f"{check['mean']['guided_mm']:.2f} mm guiding" if check["guided"] else
                        f"{check['mean']['held_out_mm']:.2f} mm (not guiding)"))
    from .folders import CASES, BuildFolder

    folder = BuildFolder(result.output)
    lines.append(f"  report: {folder.report_file}")
    flagged = m.get("flagged_cases", {})
    if flagged:
        lines.append(f"  {len(flagged)} case(s) flagged, to look at (report, {CASES} 'flags'): "
                     + "; ".join(f"{name}: {', '.join(reasons)}"
                                 for name, reasons in flagged.items()))
    if result.rejected:
        lines.append(f"  {len(result.rejected)} input(s) rejected: see {folder.rejected_file}")
    lines += [f"  warning: {warning}" for warning in result.warnings]
    return "\n".join(lines)


def _abort(live: bool):
    """A build's second Ctrl-C: the process ends at once (exit code 130). Its files are whole
    (each is written under a temporary name, then renamed), and --resume carries it on, as
    after a kill. Written straight to file descriptor 2 (after a bar, ``live``, on a line of
    its own): this runs in the signal handler, which may have cut a write to sys.stderr short."""
    os.write(2, (b"\n" if live else b"")
             + b"mdlshapemodel: interrupted again: aborted (--resume carries the build on)\n")
    os._exit(130)


def _run_build(inputs, output, config, live: bool, overwrite: bool = False,
               resume: bool = False, manifest=None) -> int:
    # Ctrl-C from the start (the build's modules take a while to import) to the summary is
    # the build's to take at its next report (progress.ctrl_c): an interrupted build ends
    # with the model of the state reached, or while preparing with Cancelled; a second one
    # aborts at once
    with ctrl_c(abort=lambda: _abort(live)), _ProgressDisplay(live) as progress:
        from .build import build_model
        from .parallel import quiet_resource_tracker

        quiet_resource_tracker()       # _abort ends the process with its pools' semaphores

        result = build_model(inputs, output, config, progress=progress, overwrite=overwrite,
                             resume=resume, manifest=manifest)
        print(_summary(result))
    return 0


def _run_compare(args) -> int:
    from .compare import compare_builds
    from .report.compare import summary_lines

    result, page = compare_builds(args.outputs, args.output, args.modes, args.samples,
                                  args.seed, args.overwrite)
    print("\n".join(summary_lines(result)))
    print(f"comparison of {len(result['models'])} models on {result['n_cases']} shared cases: "
          f"{page}")
    return 0


def _run_fit(args) -> int:
    from .fit import fit_cases
    from .folders import FitFolder

    results, _ = fit_cases(args.model, args.inputs, args.output, args.label, args.max_time,
                           args.max_sweeps, args.seed, strategy=args.strategy,
                           manifest=args.manifest, overwrite=args.overwrite)
    for result in results:
        print(f"{result.name}: reconstruction error with all modes "
              f"{result.squared_error[-1]:.4f} mm^2 ({result.distance_error[-1]:.3f} mm mean), "
              f"mean shape only {result.squared_error[0]:.4f} mm^2; objective "
              f"{result.objective['initial']:.3f} -> {result.objective['final']:.3f}")
    print(f"fitted {len(results)} case(s) to {args.model}: {FitFolder(args.output).summary_file}")
    return 0


def _run_analyze(args, live: bool) -> int:
    from .analyze import analyze_build

    config = AnalysisConfig(group=args.group, covariates=args.covariate,
                            nuisance=args.nuisance,
                            categorical=[name.strip() for item in args.categorical
                                         for name in item.split(",") if name.strip()],
                            test=args.test, reference=args.reference,
                            subject=args.subject, time=args.time, baseline=args.baseline,
                            tail=args.tail, long_table=args.long_table,
                            contrasts=args.contrast, interactions=args.interaction,
                            permutations=args.permutations, size=args.size,
                            superimposition=args.superimposition, parts=args.parts,
                            displacement=args.displacement, variance=args.variance,
                            family_wise=args.family_wise, tfce=args.tfce, alpha=args.alpha,
                            folds=args.folds, repeats=args.repeats,
                            classification_permutations=args.classification_permutations,
                            seed=args.seed).validate()
    with _ProgressDisplay(live) as progress:
        result = analyze_build(args.build, args.table, args.output, config, progress,
                               args.overwrite)
    summary = result.summary
    counts, overall = summary["significant_points"], summary["global_test"]
    for case, reason in ((d["case"], d["reason"]) for d in summary["left_out"]):
        log.warning("left out %s: %s", case, reason)
    for note in summary["notes"]:
        log.warning("%s", note)
    if summary["unmatched_rows"]:
        log.warning("table rows matching no case: %s", ", ".join(summary["unmatched_rows"]))
    lines = [f"  tested: {', '.join(summary['tested'])}; adjusted for: "
             f"{', '.join(summary['adjusted_for']) or 'nothing'} "
             f"({summary['degrees_of_freedom']} residual degrees of freedom)",
             f"  design: {summary['design']['kind']}"
             + (f" ({summary['design']['n_subjects']} subjects, {summary['design']['time']} "
                f"{', '.join(summary['design']['times'])})" if summary["design"].get("time")
                else ""),
             f"  per point: {summary['point_test']['statistic']}, "
             f"{summary['point_test']['resampling']}, family-wise by "
             f"{summary['point_test']['family_wise']}"
             + (f", tail {summary['point_test']['tail']}"
                if summary['point_test']['tail'] != "both" else ""),
             f"  cases: {summary['n_cases']}"
             + (" (" + ", ".join(f"{k}: {v}" for k, v in summary["n_per_group"].items()) + ")"
                if summary["n_per_group"] else ""),
             f"  points significant at alpha {config.alpha}: {counts['fwer']} family-wise, "
             f"{counts['fdr']} FDR"
             + (f", {summary['point_test']['tfce']['significant_points']} TFCE"
                if summary['point_test']['tfce'] else "") + f", of {counts['of']}",
             f"  global test on {overall['modes']} principal scores: p = {overall['p']:.4g}"]
    for found in summary["effect_tests"]:
        if not found["the_point_test"]:
            lines.append(f"  signed map of {found['name']} ({found['statistic']}"
                         + (f", {found['tail']}" if found["tail"] != "both" else "")
                         + f"): {found['significant_points']['fwer']} points family-wise, "
                         f"{found['significant_points']['fdr']} FDR"
                         + (f", {found['tfce']['significant_points']} TFCE" if found["tfce"]
                            else ""))
    if summary["classification"]:
        c = summary["classification"]
        lines.append(f"  classification ({c['repeats']} x {c['folds']}-fold): AUC {c['auc']:.3f} "
                     f"[{c['auc_interval'][0]:.3f}, {c['auc_interval'][1]:.3f}]"
                     + (f", p = {c['p']:.3g}" if c["p"] is not None else "")
                     + f"; balanced accuracy {c['balanced_accuracy']:.3f} "
                     f"[{c['balanced_accuracy_interval'][0]:.3f}, "
                     f"{c['balanced_accuracy_interval'][1]:.3f}]")
    lines.append(f"  unusual cases (p < 0.01): {', '.join(summary['unusual']['flagged']) or 'none'}")
    lines.append(f"  page: {Path(args.output) / 'analysis.html'}")
    print("\n".join(lines))
    return 0


def _parse(parser, commands, argv):
    """Parse the command line; an unrecognized number right after a --label value gets the
    hint to separate labels by commas (``--label 1 2`` -> ``--label 1,2``)."""
    args, extra = parser.parse_known_args(argv)
    if extra:
        words = list(sys.argv[1:] if argv is None else argv)
        subcommand = commands.choices.get(getattr(args, "command", None), parser)
        for word in extra:
            index = words.index(word) if word in words else -1
            if (word.isdigit() and index >= 2 and words[index - 2] == "--label"
                    and words[index - 1].replace(",", "").isdigit()):
                subcommand.error(f"unrecognized argument: {word}; to give several labels, "
                                 f"write --label {words[index - 1]},{word}")
        subcommand.error(f"unrecognized arguments: {' '.join(extra)}")
    return args


def main(argv=None) -> int:
    defaults = BuildConfig()
    parser = argparse.ArgumentParser(
        prog="mdlshapemodel",
        description="Statistical shape models with correspondence by minimum description length.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)
    build = commands.add_parser(
        "build", help="build a model from label maps, meshes or 2-D curves",
        epilog="examples:\n"
               "  mdlshapemodel build labels/ -o out\n"
               "  mdlshapemodel build labels/ -o both --label 1,2 --points 642\n"
               "  mdlshapemodel build femurs/*.stl -o femur-model --mirror '*_right*'\n"
               "  mdlshapemodel build labels/ -o parts --part head=1 --part tail=2\n"
               "  mdlshapemodel build labels/ -o out --resume    (after an interruption)",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    build.add_argument("inputs", nargs="*", help="label maps, meshes, 2-D curves (point lists, "
                                                 "polylines, 2-D label images), or folders of "
                                                 "them")
    build.add_argument("-o", "--output", required=True, help="output folder")
    build.add_argument("--manifest", metavar="CSV",
                       help="a table of cases with the columns case,part,file: one file per part "
                            "of each case (paths relative to the table's folder), instead of or "
                            "besides INPUTS")
    again = build.add_mutually_exclusive_group()
    again.add_argument("--overwrite", action="store_true",
                       help="replace an earlier build in the output folder (its files only; "
                            "without this flag such a build is refused)")
    again.add_argument("--resume", action="store_true",
                       help="carry on from the checkpoint of an interrupted build in the output "
                            "folder, with the same inputs and settings; ends with the model the "
                            "uninterrupted build would have made. A build stopped by --max-time "
                            "or --max-sweeps before it converged carries on with a larger one")
    _add_build_options(build)
    demo = commands.add_parser(
        "demo", help="build a model of a generated population",
        epilog="examples:\n  mdlshapemodel demo -o demo\n  mdlshapemodel demo -o demo2d --2d",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    demo.add_argument("-o", "--output", default="mdlshapemodel-demo", help="output folder "
                      "(default %(default)s)")
    demo.add_argument("--subjects", type=int, default=12, help="population size (default 12)")
    demo.add_argument("--max-time", type=float, default=40.0, help="optimisation seconds (default 40)")
    demo.add_argument("--seed", type=int, default=0)
    kind = demo.add_mutually_exclusive_group()
    kind.add_argument("--parts", action="store_true",
                      help="a two-part population: each subject cut into two touching parts "
                           "(labels 1 and 2), modelled as --part left=1 --part right=2")
    kind.add_argument("--2d", dest="curves", action="store_true",
                      help="a population of 2-D outlines (CSV point lists): a 2-D model")
    demo.add_argument("-q", "--quiet", action="store_true")
    compare = commands.add_parser(
        "compare", help="evaluate several models of the same cases side by side",
        description="Evaluate models (build output folders) on the cases they share and say, for "
                    "each number of modes, whether they differ by more than two standard errors "
                    "(the first model is the reference). Writes compare.html/.csv/.json.",
        epilog="examples:\n  mdlshapemodel compare out both -o comparison",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    compare.add_argument("outputs", nargs="+", help="build output folders (or their model files)")
    compare.add_argument("-o", "--output", default="comparison", help="folder for the comparison "
                         "(default %(default)s)")
    compare.add_argument("--modes", type=int, default=defaults.evaluation_modes,
                         help="M = 1..this (default %(default)s)")
    compare.add_argument("--samples", type=int, default=defaults.specificity_samples,
                         help="specificity samples (default %(default)s)")
    compare.add_argument("--seed", type=int, default=0)
    compare.add_argument("--overwrite", action="store_true",
                         help="replace an earlier comparison in the output folder")
    compare.add_argument("-q", "--quiet", action="store_true")
    fit = commands.add_parser(
        "fit", help="fit new cases to an existing model: correspondence, scores, reconstruction",
        description="Find the correspondence of new cases against a model (optimising only each "
                    "new case's reparameterization and pose, with the model's training shapes "
                    "fixed) and write their scores and reconstructions.",
        epilog="examples:\n  mdlshapemodel fit out new/ -o fitted\n"
               "  mdlshapemodel fit out new/case.nii.gz -o fitted --overwrite",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    fit.add_argument("model", help="a build's output folder, or its model file")
    fit.add_argument("inputs", nargs="*", help="label maps, meshes, or folders of them")
    fit.add_argument("-o", "--output", required=True, help="output folder")
    fit.add_argument("--manifest", metavar="CSV",
                     help="a table of new cases with the columns case,part,file (one file per "
                          "part of a multi-part model), instead of or besides INPUTS")
    fit.add_argument("--label", type=_items(int, {"item": "label"}), action="extend", default=[],
                     metavar="L",
                     help="label value(s) of the object (default: those the model was built with)")
    fit.add_argument("--max-time", type=float, default=60.0, metavar="SECONDS",
                     help="optimisation time per case (default %(default)s)")
    fit.add_argument("--max-sweeps", type=int, default=10_000, metavar="N")
    fit.add_argument("--strategy", choices=[s for s in STRATEGIES if s != "none"],
                     help="optimisation strategy for the new cases (default: the model's own)")
    fit.add_argument("--seed", type=int, default=0)
    fit.add_argument("--overwrite", action="store_true",
                     help="replace an earlier fit in the output folder")
    fit.add_argument("-q", "--quiet", action="store_true")
    analysis_defaults = AnalysisConfig()
    analyze = commands.add_parser(
        "analyze", help="test group differences and covariates on a build's shapes",
        description="Where do groups differ, what changes with a covariate, which cases are "
                    "unusual: per-point tests on the corresponded shapes of a build with "
                    "permutation inference (family-wise and FDR corrected), a global test, the "
                    "discriminant of two groups and its cross-validated classification, "
                    "confidence intervals and effect sizes (Cohen's d, partial eta^2) per "
                    "point. Writes analysis.json, points.csv, effects.vtp, shapes/ (group "
                    "means, predicted shapes), unusual.csv and analysis.html.\n\n"
                    "One effect is tested: the --group, else the --covariate columns, or the "
                    "columns named by --test; every other column given is adjusted for, not "
                    "tested (so --covariate beside --group is adjusted for). A column's kind is "
                    "its role: --group categorical, --covariate and --nuisance numeric "
                    "unless named by --categorical. Empty cells, NA, nan, ? and other "
                    "non-numbers in a numeric column are missing values: the case is left out "
                    "and listed with the column and the value.",
        epilog="examples:\n  mdlshapemodel analyze out --table subjects.csv --group diagnosis "
               "--covariate age -o findings\n"
               "    (tested: diagnosis; adjusted for: age)\n"
               "  mdlshapemodel analyze out --table subjects.csv --group diagnosis "
               "--covariate age --test age -o aging\n"
               "    (tested: age; adjusted for: diagnosis)\n"
               "  mdlshapemodel analyze out --table subjects.csv --covariate age "
               "--nuisance site --categorical site -o by-age\n"
               "    (tested: age; adjusted for: site, a categorical column coded 1, 2, 3)\n"
               "  mdlshapemodel analyze out --table visits.csv --subject id --time visit "
               "--baseline pre --tail less -o change\n"
               "    (each subject's change, post minus pre; its mean tested one-sided, inward)",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    analyze.add_argument("build", help="a build's output folder")
    analyze.add_argument("--table", required=True, metavar="CSV",
                         help="subjects table: a 'case' column with the build's case names, "
                              "other columns variables")
    analyze.add_argument("-o", "--output", required=True, help="output folder")
    analyze.add_argument("--group", metavar="NAME", help="categorical column: the groups "
                                                         "compared")
    analyze.add_argument("--reference", metavar="LEVEL",
                         help="the group the others are compared with (default: the first in "
                              "sorted order)")
    analyze.add_argument("--covariate", metavar="NAME", action="append", default=[],
                         help="numeric column: tested without --group; beside --group it is "
                              "adjusted for, NOT tested, unless named by --test; repeatable")
    analyze.add_argument("--test", metavar="NAME", action="append", default=[],
                         help="the column tested, the --group or a --covariate; everything "
                              "else is adjusted for (default: the group, else the "
                              "covariates); repeatable")
    analyze.add_argument("--nuisance", metavar="NAME", action="append", default=[],
                         help="column adjusted for, never tested: numeric unless named by "
                              "--categorical; repeatable")
    analyze.add_argument("--categorical", metavar="NAME", action="append", default=[],
                         help="a --covariate or --nuisance column that is categorical "
                              "(coded by its levels, e.g. a site coded 1, 2, 3; a tested one is "
                              "one test over its levels); repeatable or comma-separated")
    analyze.add_argument("--subject", metavar="NAME",
                         help="repeated measures: the column naming each case's subject "
                              "(with --time)")
    analyze.add_argument("--time", metavar="NAME",
                         help="repeated measures: the column naming each case's time point. "
                              "Two times: each subject's change (later minus --baseline) is "
                              "tested, its mean by sign flips when nothing else is tested, "
                              "else the tested columns' effect on it; more times: the effect "
                              "of time within subjects, permuted within each subject")
    analyze.add_argument("--baseline", metavar="LEVEL",
                         help="the time the change is measured from (default: the first in "
                              "numeric or sorted order)")
    analyze.add_argument("--tail", choices=TAILS, default=analysis_defaults.tail,
                         help="one-sided tests of a single-column effect (a covariate, two "
                              "groups, the mean change) along the normal: greater, towards "
                              "positive (outward) values; less, towards negative (inward: "
                              "atrophy) (default %(default)s)")
    analyze.add_argument("--interaction", metavar="A:B", action="append", default=[],
                         help="test the product of two columns of the model (e.g. "
                              "diagnosis:age: does the effect of age differ between the "
                              "groups?), both adjusted for; repeatable")
    analyze.add_argument("--contrast", metavar="TEXT", action="append", default=[],
                         help="a comparison of the levels of the tested group (or of a tested "
                              "categorical column), such as 'patient-control' or "
                              "'mild+severe-2*control' (coefficients adding up to 0): its own "
                              "signed map along the normal; repeatable")
    analyze.add_argument("--permutations", type=int, default=analysis_defaults.permutations,
                         help="random permutations (default %(default)s)")
    analyze.add_argument("--size", choices=ANALYSIS_SIZES, default=analysis_defaults.size,
                         help="kept: aligned by rotation and translation, so size differences "
                              "show; removed: each case scaled to the mean size first "
                              "(default %(default)s)")
    analyze.add_argument("--superimposition", choices=SUPERIMPOSITIONS,
                         default=analysis_defaults.superimposition,
                         help="least-squares: generalized Procrustes; resistant: each case's "
                              "points reweighted by a biweight of their residuals, so that a "
                              "local change (a dent, a retracted tip) moves the poses little "
                              "(default %(default)s)")
    analyze.add_argument("--parts", choices=PART_ALIGNMENTS, default=analysis_defaults.parts,
                         help="multi-part objects: whole, aligned as one (the parts' relative "
                              "positions count); each, every part aligned on its own "
                              "(default %(default)s)")
    analyze.add_argument("--displacement", choices=DISPLACEMENTS,
                         default=analysis_defaults.displacement,
                         help="what is tested per point: normal, the displacement along the "
                              "mean surface's normal (not changed by sliding correspondence); "
                              "vector, the displacement vector (Hotelling's T^2) "
                              "(default %(default)s)")
    analyze.add_argument("--variance", choices=VARIANCES, default=analysis_defaults.variance,
                         help="a tested group's per-point statistic: groups, a variance per "
                              "group (Welch's v or G; James' statistic for --displacement "
                              "vector), valid when groups differ in spread and size; pooled, "
                              "one variance for all cases (t, F, Hotelling's T^2, Pillai's "
                              "trace), which assumes equal spread; covariates are always tested "
                              "pooled (default %(default)s)")
    analyze.add_argument("--family-wise", choices=FAMILY_WISE,
                         default=analysis_defaults.family_wise,
                         help="family-wise correction over the points: maximum, of the "
                              "per-point statistic; min-p, of the per-point p-values (no point "
                              "dominates whatever its tails; needs --permutations well above "
                              "the number of points / alpha) (default %(default)s)")
    analyze.add_argument("--tfce", action="store_true",
                         help="also threshold-free cluster enhancement of each map over the mean "
                              "surface (E 1, H 2), tested family-wise by the enhanced maps' "
                              "maximum over the same resamples: more power for effects that "
                              "spread over a region (columns tfce, tfce_p_fwer)")
    analyze.add_argument("--alpha", type=float, default=analysis_defaults.alpha,
                         help="significance level (default %(default)s)")
    analyze.add_argument("--folds", type=int, default=analysis_defaults.folds,
                         help="the classification of the groups: k of its stratified k-fold "
                              "cross-validation (at most the smallest group's size) "
                              "(default %(default)s)")
    analyze.add_argument("--repeats", type=int, default=analysis_defaults.repeats,
                         help="... repeated this many times with other folds "
                              "(default %(default)s)")
    analyze.add_argument("--classification-permutations", type=int, metavar="N",
                         default=analysis_defaults.classification_permutations,
                         help="labelings permuted, the cross-validation redone for each, for "
                              "the p-value of the AUC; all of them when there are fewer "
                              "(exact); 0: no p-value (default %(default)s)")
    analyze.add_argument("--seed", type=int, default=analysis_defaults.seed)
    analyze.add_argument("--long-table", action="store_true",
                         help="also write long.csv: one row per case and point (normal "
                              "displacement, principal scores, the table's columns) for R or "
                              "pandas")
    analyze.add_argument("--overwrite", action="store_true",
                         help="replace an earlier analysis in the output folder")
    analyze.add_argument("-q", "--quiet", action="store_true")
    args = _parse(parser, commands, argv)

    # a live progress display when a person watches stderr (a terminal), else plain log lines
    live = args.command in ("build", "demo", "analyze") and not args.quiet and sys.stderr.isatty()
    handler = _TerminalHandler(sys.stderr, live)
    handler.setFormatter(logging.Formatter("mdlshapemodel: %(message)s"))
    handler.setLevel(logging.WARNING if args.quiet else logging.INFO)
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    try:
        if args.command == "build":
            if not args.inputs and not args.manifest:
                build.error("give input files or folders, or --manifest")
            return _run_build(args.inputs, args.output, _config_from(args), live,
                              args.overwrite, args.resume, args.manifest)
        if args.command == "compare":
            return _run_compare(args)
        if args.command == "analyze":
            if args.group is None and not args.covariate and args.time is None:
                analyze.error("give --group, --covariate or both (or --subject and --time)")
            return _run_analyze(args, live)
        if args.command == "fit":
            if not args.inputs and not args.manifest:
                fit.error("give input files or folders, or --manifest")
            return _run_fit(args)
        if args.command == "demo":
            from .demo import DEMO_PARTS, write_demo_curves, write_demo_population

            output = Path(args.output)
            if args.curves:
                paths = write_demo_curves(output / "inputs", args.subjects, args.seed)
            else:
                paths = write_demo_population(output / "inputs", args.subjects, args.seed,
                                              args.parts)
            log.info("wrote %d demo %s to %s", len(paths),
                     "outlines" if args.curves else "label maps", output / "inputs")
            config = BuildConfig(points=None if args.curves else 642, max_time=args.max_time,
                                 seed=args.seed, specificity_samples=2000,
                                 parts=list(DEMO_PARTS) if args.parts else []).validate()
            return _run_build(paths, output, config, live, overwrite=True)  # the demo's own
    except MDLShapeModelError as error:
        print(f"mdlshapemodel: error: {error}", file=sys.stderr)
        return 2
    except InternalError as error:
        print(f"mdlshapemodel: internal error: {error}", file=sys.stderr)
        return 3
    except (KeyboardInterrupt, Cancelled, SystemError) as error:
        # SystemError: a KeyboardInterrupt (Ctrl-C of a command other than build) met
        # numba-compiled code, which returns with the exception set; Python reports that as a
        # SystemError caused by it
        if isinstance(error, SystemError) and not isinstance(error.__cause__, KeyboardInterrupt):
            raise
        print("mdlshapemodel: interrupted", file=sys.stderr)
        return 130
    finally:
        log.removeHandler(handler)
    return 1


if __name__ == "__main__":
    sys.exit(main())
