"""build_model(): files -> prepared cases -> correspondence -> optimisation -> model -> outputs.

Orchestration only: each stage is a room of its own (:mod:`.prepare`, :mod:`.correspondence`,
:mod:`.model`, :mod:`.outputs`, :mod:`.report`). Per-case work runs on the caller's executor, on
the Dask cluster of ``config.scheduler``, or by default on a pool of ``config.workers`` processes
for each stage that fans out over the cases (preprocessing, CPD registrations) and one helper
process for the evaluations that overlap the optimisation (:func:`.parallel.helper_for`). A case
that cannot be used is *rejected* with a one-line reason (logged, and listed in ``rejected.csv``)
and the build goes on; a bug stops the build with a message that names the case (traceback in
build.log). The optimisation state is checkpointed after every sweep or round, and an interrupted
optimisation (Ctrl-C, a cancelling progress callback, or the time limit) still writes a model of
the state reached. One that ended before it converged says so, and how to carry it on
(``--resume`` with a larger budget), in build.log, metrics.json, the report and the summary
(:class:`OptimisationEnd`). Ctrl-C is taken at the next progress report (:func:`.progress.ctrl_c`):
while preparing it stops the build, while optimising it ends the optimisation there, and after
the optimisation the outputs are finished; a second Ctrl-C aborts at once.
"""

from __future__ import annotations

import json
import logging
import math
import time
import traceback
from collections import Counter
from concurrent.futures import CancelledError, Executor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .config import HELPER_RESTS_FROM, BuildConfig
from .correspondence.cpd import cpd_state
from .correspondence.initial import initial_state
from .correspondence.state import CorrespondenceState, ObjectiveParts
from .correspondence.coarse import coarse_view
from .correspondence.strategies import optimise, runs_coarse
from .correspondence.strategies.base import PhasePoint, Resumption
from .correspondence.trace import Stop, Trace, stop_summary
from .errors import BuildError, Cancelled, ConfigError, InputError, InternalError
from .kernels import compile_ahead
from .memory import LOOP_RELEASE_SECONDS, release_freed_memory
from .model.evaluation import evaluate_state
from .model.landmarks import LandmarkCheck, landmark_array, transfer_errors
from .model.shape_model import ShapeModel
from .model.space import PrincipalAxes, principal_axes
from .folders import BuildFolder, Checkpoint, find_inputs
from .outputs import BuildResult, against_baselines, write_outputs, write_shapes
from .cluster import client_of, dask_executor
from .parallel import ProcessPool, Task, helper_for
from .prepare import io, preprocess
from .prepare.case import Rejection
from .prepare.duplicates import identical_files, refusal, same_shapes
from .prepare.landmarks import read_landmark_folder
from .prepare.mapped import CasesInFile
from .prepare.parts import case_inputs, read_manifest
from .progress import Interrupt, Progress, TimeLeft, ctrl_c, report

log = logging.getLogger("mdlshapemodel")

__all__ = ["BuildError", "BuildResult", "Correspondence", "OptimisationEnd", "build_model",
           "check_landmarks", "correspond", "shape_model_of"]


def build_model(inputs, output, config: BuildConfig | None = None,
                progress: Progress | None = None, executor: Executor | None = None,
                overwrite: bool = False, resume: bool = False, manifest=None) -> BuildResult:
    """Build an optimised statistical shape model from label maps or meshes.

    Parameters
    ----------
    inputs : list of paths
        Label-map or mesh files, or folders of them: one file per case (with ``config.parts``,
        label maps split into the parts). May be empty when a ``manifest`` is given.
    output : path
        Output folder (created); see the README for its layout.
    config : BuildConfig, optional
        Every setting; the defaults are the paper's (Table I) and ours (the ``fast`` strategy).
    progress : callable(fraction or None, message), optional
        See :mod:`mdlshapemodel.progress`. Cancelling (returning False or raising
        :class:`Cancelled`) during the optimisation stops it early; the model of the state reached
        is still written. Cancelling in another stage raises :class:`Cancelled`. Called from the
        main thread where Ctrl-C raises ``KeyboardInterrupt`` (a script, a notebook), the build
        takes Ctrl-C as such a cancellation at its next report (:func:`.progress.ctrl_c`; the
        usual handler is back when it returns); once the optimisation has ended, Ctrl-C lets
        the outputs be finished. A second Ctrl-C raises ``KeyboardInterrupt`` at once.
    executor : concurrent.futures.Executor, optional
        Runs the per-case work (preprocessing, CPD registrations, evaluations); default: a pool
        of ``config.workers`` processes per stage (none when 1) and one helper process for the
        evaluations that overlap the optimisation, or with ``config.scheduler`` the Dask cluster
        there (:func:`.cluster.dask_executor`; not both). On a Dask client's executor
        (``Client.get_executor()``) each call runs as :class:`.cluster.InTurn`. The caller's
        executor is not shut down.
    overwrite : bool
        Replace an earlier finished or resumable build in ``output`` (:func:`.outputs.earlier_build`;
        its files only: :func:`.outputs.previous_build`); without it, a build into a folder that
        holds one raises :class:`BuildError` and touches nothing. What a failed or cancelled
        start left there is replaced without asking. The inputs are checked before anything is
        written: a missing path, a build's output folder given as input, fewer than 3 input
        files, identical input files (unless ``config.allow_duplicates``) raise and leave
        ``output`` as it was. Every file is written whole or not at all (a temporary name renamed into place).
    manifest : path, optional
        A CSV table of cases with the columns ``case``, ``part``, ``file``: one file per part
        (:func:`.prepare.parts.read_manifest`), added to ``inputs``.
    resume : bool
        Carry on from the checkpoint of an interrupted build in ``output`` (killed, out of power,
        cancelled, or stopped by ``max_time`` or ``max_sweeps`` before it converged: give those
        a larger value) and end with the model the uninterrupted build would have made; refused
        when the inputs or the settings that shape the result differ (:func:`fingerprint`).
        Without a checkpoint (interrupted while preparing) the build starts over, its prepared
        cases coming from the preprocessing cache.

    Returns
    -------
    BuildResult

    Examples
    --------
    ::

        from mdlshapemodel import BuildConfig, build_model
        result = build_model(["labels/"], "out", BuildConfig(labels=[1, 2]))
        result.final_objective, result.metrics["generalization"]
    """
    config = (config or BuildConfig()).validate()
    if executor is not None and config.scheduler is not None:
        raise ConfigError("scheduler: give an executor or a scheduler's address, not both")
    _refuse_unguarded_call(config, executor)
    output = Path(output)
    cases = _cases(inputs, config, manifest, output)      # before anything is written
    landmarks = (None if config.landmarks is None
                 else read_landmark_folder(config.landmarks, [case.name for case in cases]))
    folder = BuildFolder(output)
    io.refuse_earlier(output, [] if resume else folder.earlier_build(), overwrite, "build",
                      ", --resume to carry it on", BuildError)
    with ctrl_c() as interrupt:
        interrupt.check()    # Ctrl-C already (the command line's, as it started): nothing touched
        if resume:
            _refuse_other_settings(folder, config)         # before any case is prepared
            folder.remove_partial_files()
        else:
            folder.clear()
        output.mkdir(parents=True, exist_ok=True)    # its folders come with what goes in them
        handler = logging.FileHandler(folder.log_file, mode="a" if resume else "w")
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
        log.addHandler(handler)
        if log.level == logging.NOTSET or log.level > logging.INFO:
            log.setLevel(logging.INFO)
        try:
            # a cold cache: compiled before any worker starts, in a second process too where
            # the build starts worker processes itself (_refuse_unguarded_call's condition)
            compile_ahead(build_model, second_process=executor is None and config.workers > 1
                          and config.scheduler is None)
            return _build(cases, output, config, progress, executor, resume, landmarks, interrupt)
        except InternalError as error:
            # the user sees the one-line message; the traceback (a worker's too) goes to build.log
            handler.stream.write("".join(traceback.format_exception(error)))
            raise
        finally:
            log.removeHandler(handler)
            handler.close()


def fingerprint(prepared: list, config: BuildConfig, landmarks: dict | None = None) -> dict:
    """What a checkpoint is of: the settings that shape the result (all but ``workers``,
    ``scheduler``, ``cache_dir``, ``allow_duplicates`` (a permission) and the budget,
    ``max_time`` and ``max_sweeps``, which a resumed build may raise to carry on an
    optimisation that they stopped) and every prepared case's name and the digests of its
    files (and of its landmark file)."""
    settings = {key: value for key, value in config.to_dict().items()
                if key not in ("workers", "scheduler", "cache_dir", "allow_duplicates",
                               "max_time", "max_sweeps", "check_landmarks")}
    marks = landmarks or {}
    return {"settings": settings,
            "cases": [[case.name, *map(io.file_digest, case.paths)]
                      + ([io.file_digest(marks[case.name].path)] if case.name in marks else [])
                      for case in prepared]}


def _refuse_difference(path: Path, then: dict, now: dict):
    """Refuse to resume from the checkpoint ``path`` of fingerprint ``then`` when this build's
    ``now`` differs (``now`` may lack the cases: the settings alone are compared then)."""
    now = json.loads(json.dumps(now))   # as JSON gives it back
    differ = sorted(key for key in set(now["settings"]) | set(then["settings"])
                    if now["settings"].get(key) != then["settings"].get(key))
    if "cases" in now and now["cases"] != then["cases"]:
        differ.insert(0, "the input files")
    if differ:
        raise BuildError(f"{path} is of other inputs or settings ({', '.join(differ)}): resume "
                         "with the same ones, or build anew with --overwrite")


def _refuse_other_settings(folder: BuildFolder, config: BuildConfig):
    """On ``--resume``, the checkpoint's settings against this build's, before any work (the
    input files are compared once they are prepared: :func:`_resumption`)."""
    checkpoint = folder.checkpoint()
    if checkpoint is not None:
        settings = fingerprint([], config)["settings"]
        _refuse_difference(folder.checkpoint_file, checkpoint.fingerprint,
                           {"settings": settings})


def _resumption(folder: BuildFolder, print_of: dict) -> Checkpoint | None:
    """The checkpoint to resume from (None: there is none, start over), checked against this
    build's :func:`fingerprint` ``print_of``."""
    checkpoint = folder.checkpoint()
    path = folder.checkpoint_file
    if checkpoint is None:
        log.info("no checkpoint in %s: starting over (the prepared cases come from the cache)",
                 folder.path)
        return None
    _refuse_difference(path, checkpoint.fingerprint, print_of)
    log.info("resuming from %s (%s, step %d)", path, checkpoint.point.phase,
             checkpoint.point.sweep)
    return checkpoint


# eq. 14 values closer than this (relative) are the same: what the rounding of the same
# correspondence measured twice may differ by
OBJECTIVE_RTOL = 1e-9

# the fewest cases a model is built of (a mean and one mode need three)
MIN_CASES = 3


def _cases(inputs, config: BuildConfig, manifest, output: Path) -> list:
    """The build's cases from its inputs and manifest, checked before the output folder is
    touched: a missing path, a build's output folder given as input (or the output folder
    itself), no input file, fewer than :data:`MIN_CASES` cases, and identical files (unless
    ``config.allow_duplicates``; :mod:`.prepare.duplicates`) are refused."""
    paths = [Path(p) for p in inputs]
    for path in paths:
        if path.is_dir() and path.resolve() == output.resolve():
            raise InputError(f"{path}: is the output folder; give the inputs' folder")
    cases = case_inputs(find_inputs(paths), config)
    if manifest is not None:
        cases += read_manifest(manifest, config)
    if not cases:
        raise BuildError("no input files found (label maps: .nii/.nii.gz/.nrrd/.mha...; meshes: "
                         ".vtk/.vtp/.stl/.ply/.obj)")
    if len(cases) < MIN_CASES:
        raise BuildError(f"{len(cases)} input file(s) found; a model needs at least {MIN_CASES}")
    same = [] if config.allow_duplicates else identical_files(cases)
    if same:
        raise BuildError(refusal(same))
    return cases


def _refuse_unguarded_call(config: BuildConfig, executor):
    """Refuse a build started by a script's top-level code outside ``if __name__ ==
    "__main__":`` when it would start worker processes: each spawned worker imports the script
    again, which would start the build again in every worker (and each of them dies)."""
    if executor is not None or config.workers <= 1 or config.scheduler is not None:
        return
    import inspect

    frame = inspect.currentframe().f_back.f_back            # build_model's caller
    if frame is None or frame.f_code.co_name != "<module>":
        return
    module = frame.f_globals.get("__name__")
    source = frame.f_globals.get("__file__")
    if module == "__mp_main__" or (module == "__main__" and source
                                   and not _guarded(source, frame.f_lineno)):
        raise BuildError(f"{source}: build_model is called by the script's top-level code; "
                         "worker processes import the script again, so put the call under "
                         "'if __name__ == \"__main__\":'")


def _guarded(source, line: int) -> bool:
    """Whether ``line`` of the script ``source`` lies inside an ``if __name__ ==
    "__main__":`` block (True when the script cannot be read: give it the benefit)."""
    import ast

    try:
        tree = ast.parse(Path(source).read_text())
    except (OSError, SyntaxError, ValueError):
        return True
    for node in ast.walk(tree):
        if (isinstance(node, ast.If) and isinstance(node.test, ast.Compare)
                and "__name__" in ast.unparse(node.test) and "__main__" in ast.unparse(node.test)
                and node.lineno <= line <= (node.end_lineno or node.lineno)):
            return True
    return False


def _build(cases: list, output: Path, config: BuildConfig, progress, executor,
           resume: bool, landmarks: dict | None, interrupt: Interrupt) -> BuildResult:
    started = time.perf_counter()
    # every report says how long its stage has left
    progress = interrupt.watch(None if progress is None else TimeLeft(progress, config.max_time))
    BuildFolder(output).write_settings(config)
    if config.scheduler is None:
        log.info("preprocessing %d cases with %d workers", len(cases), config.workers)
        return _build_from(cases, output, config, progress, executor, resume, started,
                           landmarks, interrupt)
    with dask_executor(config.scheduler) as cluster:   # connected and checked before any work
        log.info("preprocessing %d cases on the Dask cluster", len(cases))
        return _build_from(cases, output, config, progress, cluster, resume, started,
                           landmarks, interrupt)


def _build_from(cases: list, output: Path, config: BuildConfig, progress, executor,
                resume: bool, started: float, landmarks: dict | None,
                interrupt: Interrupt) -> BuildResult:
    folder = BuildFolder(output)
    prepared, rejected = preprocess(cases, config, executor, progress)
    prepared, odd = one_kind(prepared)
    rejected = rejected + odd
    for line in io.rejection_lines((r.path, r.reason) for r in rejected):
        log.warning("rejected %s", line)            # the same reason once, with its count
    folder.write_rejected(rejected)
    if rejected and config.strict:
        raise BuildError(f"{len(rejected)} input(s) rejected and --strict is set")
    warnings = absent_labels(prepared, config)
    for warning in warnings:
        log.warning("%s", warning)
    log.info("prepared %d cases in %.1f s", len(prepared), time.perf_counter() - started)

    # the surfaces and sphere maps lie in a file, mapped: the optimisation does not read them,
    # and it runs without them in memory; the baselines are evaluated on the helper meanwhile
    with (CasesInFile(prepared, folder.surfaces_file) as prepared,
          helper_for(config.workers, executor) as pool):
        release_freed_memory()      # the arrays now in the file
        pending = {}   # baseline -> (objective and notes, its evaluation: running or done)
        print_of = fingerprint(prepared, config, landmarks)
        resumed = _resumption(folder, print_of) if resume else None
        # a resumed build takes the baselines' evaluations its first run kept (the same inputs,
        # settings and initial correspondence give the same ones)
        kept = folder.baselines(print_of) if resumed is not None else {}

        def evaluate_baseline(name, state, notes):
            if name in kept:
                log.info("the %s baseline's evaluation comes from %s", name,
                         folder.baselines_file)
                pending[name] = (notes, kept[name])
                return
            log.info("evaluating the %s baseline%s", name,
                     "" if pool is None else " beside the optimisation")
            pending[name] = (notes, evaluate_state(state, config, prepared, pool=pool,
                                                   jackknife=True))

        def keep_baselines(outcomes: dict) -> None:
            """The baselines' evaluations into the folder for --resume (once: not where they
            all came from it)."""
            if outcomes and not all(name in kept for name in outcomes):
                folder.write_baselines(outcomes, print_of)
                kept.update(outcomes)

        def settled() -> bool:
            """Whether the helper's evaluations of the baselines have just all come (each
            baseline's evaluation is kept once all are here)."""
            tasks = [evaluation for _, evaluation in pending.values()
                     if isinstance(evaluation, Task)]
            if not (pending and all([task.settle() for task in tasks])):
                return False
            for name, (notes, evaluation) in list(pending.items()):
                pending[name] = (notes, _outcome(evaluation))
            keep_baselines({name: outcome for name, (_, outcome) in pending.items()})
            return bool(tasks)

        def checkpoint(state, point, rng, trace):
            folder.save_checkpoint(state, point, rng, trace, print_of)
            # the baselines' evaluation over: it is kept for --resume, its arguments go, and in
            # a large build the build's own helper process ends (an idle process's memory
            # through the rest of the optimisation: about 0.3 GB at 10,000 cases); the model's
            # evaluation starts a fresh one
            if (settled() and len(prepared) >= HELPER_RESTS_FROM and executor is None
                    and isinstance(pool, ProcessPool) and pool.running()):
                pool.rest()
                log.info("the baselines are evaluated: the helper process ended until the "
                         "model's evaluation")
            # what the round and the checkpoint freed, most of it reused by the next round
            release_freed_memory(at_most_every=LOOP_RELEASE_SECONDS)

        corresponded = correspond(prepared, config, progress, executor, checkpoint,
                                  evaluate_baseline, resumed, landmarks)
        checked = None
        if config.checks_landmarks() and not corresponded.interrupted:
            checked = _checked_landmarks(prepared, config, landmarks, corresponded, progress)
            if checked is None:
                cut = "the landmark check was interrupted: the outputs have none"
                log.warning("%s", cut)
                warnings = [*warnings, cut]
        # from here on a Ctrl-C lets the outputs be finished (a second one aborts)
        if corresponded.interrupted:
            log.warning("optimisation interrupted: writing the model of the state reached%s",
                        interrupt.again)
        interrupt.finishing("interrupted after the optimisation: finishing the outputs")
        unfinished = corresponded.optimisation.warning(output)
        if unfinished is not None:
            log.warning("%s", unfinished)
            warnings = [*warnings, unfinished]
        folder.write_convergence(corresponded.trace)
        # the correspondence is final (the landmark check above was its last use of the point
        # locators): their memory goes before the wait for the baselines, not after it
        corresponded.state.release_sampling()
        release_freed_memory()
        # the evaluation in two steps (the fraction counts them): the baselines' (begun meanwhile),
        # then the model's, with the outputs
        report(progress, 0.0, "evaluating the baselines" if pending else "evaluating")
        waited = time.perf_counter()
        outcomes = {name: _outcome(evaluation) for name, (_, evaluation) in pending.items()}
        keep_baselines(outcomes)        # where they came after the last checkpoint
        baselines = {name: {**pending[name][0], **outcome} for name, outcome in outcomes.items()}
        if pending:
            log.info("waited %.1f s for the baselines' evaluation", time.perf_counter() - waited)

        report(progress, 0.5, "evaluating the model, writing outputs")
        release_freed_memory()   # the baselines' arguments, kept here until their results came
        waited = time.perf_counter()
        written = []                            # the files are written while the helper measures

        def files():
            written.append(write_shapes(output, corresponded, prepared))
            release_freed_memory()              # their temporaries, before this process measures

        quality = evaluate_state(
            corresponded.state, config, prepared, corresponded.model, pool=pool,
            background=False, jackknife=bool(baselines), axes=corresponded.axes, meanwhile=files)
        written = written[0]
        release_freed_memory()                  # the evaluation's arrays
        baselines = against_baselines(quality, baselines)
        log.info("evaluated the model in %.1f s (its files written meanwhile)",
                 time.perf_counter() - waited)
    # the helper process has ended (its memory with it) before the report is made
    result = write_outputs(output, corresponded, rejected, written, quality, baselines,
                           warnings, checked)
    report(progress, 1.0, "evaluated, outputs written")
    log.info("outputs written to %s in %.1f s total", output, time.perf_counter() - started)
    return result


def _checked_landmarks(prepared: list, config: BuildConfig, landmarks: dict,
                       corresponded, progress) -> LandmarkCheck | None:
    """:func:`check_landmarks` in a build, timed in build.log; None where a Ctrl-C or a
    cancelling progress callback stops it: the build's outputs do not wait for it."""
    started = time.perf_counter()
    try:
        checked = check_landmarks(prepared, config, landmarks, corresponded, progress)
    except Cancelled:
        checked = None
    if checked is None:
        return None
    log.info("landmark check: %d optimisations in %.1f s", len(checked.folds),
             time.perf_counter() - started)
    return checked


def check_landmarks(prepared: list, config: BuildConfig, landmarks: dict,
                    corresponded: "Correspondence", progress: Progress | None = None
                    ) -> LandmarkCheck | None:
    """How far the correspondence carries each landmark label where the label does not guide it
    (:class:`~.model.landmarks.LandmarkCheck`).

    Where the landmarks guide the correspondence, each fold of labels
    (:meth:`~.config.BuildConfig.landmark_folds`) is left out of the guides and the
    correspondence of the same prepared cases optimised again (:func:`correspond`, no baseline,
    no checkpoint): the fold's labels' transfer errors
    (:func:`~.model.landmarks.transfer_errors`) come from that correspondence, the guided
    errors from ``corresponded``. Where they do not guide it (``landmark_weight`` 0, the CPD
    correspondence), ``corresponded`` itself gives every label's error.

    Parameters
    ----------
    prepared : list of PreparedCase
        The cases of ``corresponded``, in its order (surfaces).
    config : BuildConfig
        The build's settings.
    landmarks : dict of case name -> Landmarks
        The landmarks given (all of them, guiding or not).
    corresponded : Correspondence
        The build's correspondence (:func:`correspond`).
    progress : callable(fraction or None, message), optional
        Each fold's optimisation reports here.

    Returns
    -------
    LandmarkCheck, or None where a fold's optimisation was interrupted.
    """
    from .prepare.landmarks import Landmarks

    labels = tuple(sorted({label for marks in landmarks.values() for label in marks.labels}))
    given = landmark_array(prepared, landmarks, labels)
    surfaces = [case.surface() for case in prepared]

    def errors(state) -> tuple[np.ndarray, np.ndarray]:
        # each optimisation's own triangles: with --placement surface the grid depends on the
        # initial correspondence, which the guides steer
        return transfer_errors(state.raw_shapes(), state.triangles(), given, surfaces,
                               single=False).per_label()

    built, cases = errors(corresponded.state)
    folds = config.landmark_folds(labels)
    if not folds:
        return LandmarkCheck(labels, built, None, cases, [])
    held_out = np.full(len(labels), np.nan)
    for k, fold in enumerate(folds):
        report(progress, None, f"landmark check {k + 1} of {len(folds)}: "
                               f"{', '.join(fold)} left out of the guides")
        kept = {}
        for name, marks in landmarks.items():
            rows = [m for m, label in enumerate(marks.labels) if label not in fold]
            if rows:
                kept[name] = Landmarks(tuple(marks.labels[m] for m in rows), marks.points[rows],
                                       marks.path)
        refit = correspond(prepared, config, progress, landmarks=kept or None)
        if refit.interrupted:
            return None
        mine = [labels.index(label) for label in fold]
        held_out[mine] = errors(refit.state)[0][mine]
    return LandmarkCheck(labels, held_out, built, cases, folds)


def absent_labels(prepared: list, config: BuildConfig) -> list:
    """A warning for the labels asked for (``--label``, ``--part``) that none of the prepared
    label maps holds (a case needs only one of its labels, so such a label is otherwise
    silently left out of every case)."""
    wanted = set(config.labels) | {label for spec in config.part_specs() for label in spec.labels}
    known = [case.labels for case in prepared if case.labels is not None]
    if not wanted or not known:
        return []
    found = set().union(*known)
    absent = sorted(wanted - found)
    if not absent:
        return []
    return [f"label {', '.join(map(str, absent))} is in none of the {len(known)} label maps "
            f"(labels found: {', '.join(map(str, sorted(found)))})"]


def one_kind(prepared: list) -> tuple[list, list]:
    """The prepared cases of the kind most of them are (surfaces or 2-D curves: a model is of
    one), and a :class:`Rejection` for each of the others (a stray 2-D image among label maps)."""
    curves = [case for case in prepared if case.is_curve]
    if not curves or len(curves) == len(prepared):
        return prepared, []
    keep_curves = len(curves) > len(prepared) - len(curves)
    kind, other = ("2-D curves", "a surface") if keep_curves else ("surfaces", "a 2-D curve")
    return ([case for case in prepared if case.is_curve == keep_curves],
            [Rejection(case.name, case.path, f"{other}, but most inputs are {kind} (a model "
                                             "is of one kind)")
             for case in prepared if case.is_curve != keep_curves])


@dataclass(frozen=True)
class OptimisationEnd:
    """How a build's optimisation ended: whether it converged, what stopped it, and its budget
    (metrics.json ``optimisation``).

    Converged means the strategy's own stopping rule ended the full objective's phase (the
    fixed-Delta phase before it ends at its share of the time by design:
    :mod:`~.correspondence.strategies`). A limit reached, or an interruption, leaves the
    checkpoint of the last step, from which ``--resume`` with a larger budget carries on.
    """

    stopped_by: Stop | None   # None: nothing was optimised (strategy none, CPD correspondence)
    max_time: float           # s, the budget (``--max-time``), the time before a resume included
    max_sweeps: int           # ``--max-sweeps``
    seconds: float            # the optimisation's wall time, the time before a resume included

    @property
    def converged(self) -> bool | None:
        """Whether the strategy's stopping rule ended it (None: nothing was optimised)."""
        return None if self.stopped_by is None else self.stopped_by is Stop.CONVERGED

    def to_json(self) -> dict:
        """metrics.json's ``optimisation``: converged (true, false, or null when nothing was
        optimised), stopped_by (:class:`Stop`'s value or null) and the budget; not the seconds,
        so that the same build gives the same metrics.json wherever it runs (build.log has
        them)."""
        return {"converged": self.converged,
                "stopped_by": None if self.stopped_by is None else self.stopped_by.value,
                "max_time": self.max_time, "max_sweeps": self.max_sweeps}

    def warning(self, output) -> str | None:
        """What the user is told of an optimisation that ended before it converged, with how to
        carry it on into the build folder ``output``; None when it converged or nothing was
        optimised."""
        if self.converged is not False:
            return None
        carry_on = f"run the same build (inputs and options) with -o {output} --resume"
        if self.stopped_by is Stop.TIME_LIMIT:
            # --max-time counts the time before a resume: the new budget must exceed it
            larger = max(2.0 * self.max_time, BuildConfig.max_time)
            cause = f"stopped at the time limit (--max-time {self.max_time:g} s)"
            carry_on += f" --max-time {larger:g}"
        elif self.stopped_by is Stop.SWEEP_LIMIT:
            cause = f"stopped at the sweep limit (--max-sweeps {self.max_sweeps})"
            carry_on += f" --max-sweeps {2 * self.max_sweeps}"
        else:
            cause = "was interrupted"
            carry_on += (f" (with a --max-time larger than {self.max_time:g} s if most of it "
                         "is spent)")
        return (f"the optimisation {cause} after {self.seconds:.1f} s, before it converged: the "
                f"model is of the correspondence reached so far; to carry it on, {carry_on}")


@dataclass
class Correspondence:
    """The correspondence of prepared cases and its model: what :func:`correspond` returns."""

    state: CorrespondenceState   # every example's warps and pose, in the order of the cases
    model: ShapeModel            # the model of ``state`` (:func:`shape_model_of`)
    initial: ObjectiveParts      # F of the initial correspondence (cpd: of the CPD one)
    final: ObjectiveParts        # F of ``state``: eq. 14, the prior and the guides' term
    voxel_size: float            # mm, the mean over the cases: the unit of the coding accuracy
    data_range: float            # mm, of the initially aligned shapes
    trace: Trace                 # the optimisation's rows (convergence.csv)
    optimisation: OptimisationEnd   # converged or what stopped it
    objective_points: int        # the sample points (all parts) the objectives are measured on
    landmarks: dict | None = None   # case name -> the Landmarks that guided it (None: unguided)
    axes: PrincipalAxes | None = None   # the decomposition ``model`` was made from, which its
    #                                     evaluation's measures share (None: not known)

    @property
    def initial_objective(self) -> float:
        """F (eq. 14 with the prior and the guides' term) of the initial correspondence."""
        return self.initial.total

    @property
    def final_objective(self) -> float:
        """F of ``state``, as the optimisation minimised it."""
        return self.final.total

    @property
    def interrupted(self) -> bool:
        """The optimisation was cancelled; ``state`` is the one reached."""
        return self.optimisation.stopped_by is Stop.INTERRUPTED


def correspond(prepared: list, config: BuildConfig, progress: Progress | None = None,
               executor: Executor | None = None, checkpoint=None, baselines=None,
               resume: Checkpoint | None = None, landmarks: dict | None = None
               ) -> Correspondence:
    """Prepared cases -> their optimised correspondence and its shape model (the middle of a build).

    The initial correspondence (:func:`~.correspondence.state.initial_state`), then either the
    optimisation of ``config.strategy`` or (``config.correspondence`` "cpd") the CPD template
    correspondence, then the model (:func:`shape_model_of`). Nothing is written: ``build_model``
    and :class:`~mdlshapemodel.vtkmodel.ShapeModelBuilder` both call this.

    Parameters
    ----------
    prepared : list of PreparedCase
        At least three cases (:func:`~.prepare.case.prepare_case`) with distinct names and
        distinct shapes (:func:`~.prepare.duplicates.same_shapes` in the initial
        correspondence, unless ``config.allow_duplicates``), in the model's order (else
        :class:`BuildError`).
    config : BuildConfig
        The correspondence settings (validated by the caller).
    progress : callable(fraction or None, message), optional
        See :mod:`mdlshapemodel.progress`. Cancelling during the optimisation stops it and keeps
        the state reached (``interrupted``); cancelling elsewhere raises :class:`Cancelled`.
    executor : concurrent.futures.Executor, optional
        Runs the CPD registrations (default: a pool of ``config.workers`` processes); a Dask
        client's executor also the fast strategy's per-example work
        (:mod:`.correspondence.strategies.spread`).
    checkpoint : callable(state, point, rng, trace), optional
        Called after every sweep or round of the optimisation with the
        :class:`~.correspondence.strategies.base.PhasePoint` reached, the random generator and
        the trace (what :func:`~.outputs.save_checkpoint` keeps), and once at its end
        (``PhasePoint.DONE``) if it converged: otherwise the last step's checkpoint stays, to
        be carried on from.
    baselines : callable(name, state, notes), optional
        Called with each baseline correspondence of ``config.baselines`` as soon as it is made,
        before the optimisation moves anything (``notes``: its objective, the CPD template);
        None: no baseline is made.
    resume : Checkpoint, optional
        Carry on from this checkpoint (of the same cases and settings) instead of starting the
        optimisation: the same result as the uninterrupted run.
    landmarks : dict of case name -> Landmarks, optional
        Landmarks that guide the correspondence (surfaces; :mod:`.correspondence.guides`): the
        initial alignment and the optimisation keep each label at one place across the cases;
        with ``config.landmark_weight`` 0 they guide nothing
        (:meth:`~.config.BuildConfig.landmarks_guide`).

    Returns
    -------
    Correspondence

    Examples
    --------
    ::

        from mdlshapemodel import BuildConfig
        from mdlshapemodel.build import correspond
        from mdlshapemodel.prepare import preprocess
        config = BuildConfig(points=642)
        prepared, rejected = preprocess(paths, config)
        result = correspond(prepared, config)
        result.final_objective, result.model.variances
    """
    files = [io.case_file("", case.name).name for case in prepared]   # names as file names
    counts = Counter(files)
    duplicates = {case.name for case, file in zip(prepared, files) if counts[file] > 1}
    if duplicates:
        raise BuildError("several inputs have the same case name: "
                         f"{', '.join(sorted(map(io.printable, duplicates)))}")
    if len(prepared) < 3:
        raise BuildError(f"only {len(prepared)} usable case(s); at least 3 are needed")
    parts = prepared[0].part_names
    other = next((case for case in prepared if case.part_names != parts), None)
    if other is not None:
        raise BuildError(f"the cases have different parts: {prepared[0].name} has "
                         f"{parts}, {other.name} has {other.part_names}")
    curves = [case.name for case in prepared if case.is_curve]
    if curves and len(curves) != len(prepared):
        surface = next(case.name for case in prepared if not case.is_curve)
        raise BuildError(f"2-D curves and surfaces in one build: {curves[0]} is a curve, "
                         f"{surface} a surface")
    if curves and landmarks:
        raise BuildError("--landmarks guides surfaces; these inputs are 2-D curves")
    if curves and config.smoothness_for(curves=True) > 0:
        raise BuildError("--smoothness is a prior for surfaces; these inputs are 2-D curves")
    if curves and config.correspondence == "cpd":
        raise BuildError("--correspondence cpd registers surfaces; these inputs are 2-D curves")
    guiding = landmarks if landmarks and config.landmarks_guide(True) else None
    if landmarks and guiding is None:
        log.info("the landmarks of %d cases measure the correspondence, they do not guide it "
                 "(landmark weight 0)", len(landmarks))
    state, (fixed, integrated), voxel, data_range = initial_state(prepared, config, guiding)
    same = same_shapes(state.raw_shapes(), state.weights,
                       [case.path or case.name for case in prepared])
    if same and not config.allow_duplicates:
        raise BuildError(refusal(same))
    release_freed_memory()     # the temporaries of the initial correspondence (sphere maps aligned)
    for duplicates in same:
        log.warning("%s: modelled as they are (--allow-duplicates)", duplicates.line())
    if state.guides is not None:
        log.info("%d landmark labels guide the correspondence (%d landmarks of %d cases; weight "
                 "%g): %s", len(state.guides.labels), int(state.guides.present.sum()),
                 int(state.guides.present.any(axis=1).sum()), config.landmark_weight,
                 ", ".join(state.guides.labels))
        for name, label, distance in state.guides.far_from_surface([c.name for c in prepared]):
            log.warning("landmark %s of %s is %.1f mm from the case's surface (moved onto it): "
                        "are its coordinates those of the case's file (LPS, or RAS where the "
                        "file says so)?", label, name, distance)
    settings = config.optimisation_settings()
    # F is measured where the optimisation minimises it (the fast strategy's coarse grid)
    coarse = (settings.coarse_points if config.correspondence != "cpd"
              and runs_coarse(state, settings) else None)

    def measured(current: CorrespondenceState) -> ObjectiveParts:
        """The F the optimisation's last phase minimises (eq. 14, the prior, the guides)."""
        return (current if coarse is None
                else coarse_view(current, coarse)).objective_parts(integrated)

    # one pool of threads for every measure of F past the covariance route: before, of the
    # CPD baseline, throughout the optimisation (whose pooled objective nests in it) and after
    with integrated.pooled():
        initial_parts = measured(state)
        initial = initial_parts.total
        log.info("initial objective %.4f (%s; n_s=%d, n_p=%d%s, voxel %.3f mm, range %.2f mm)",
                 initial, described(initial_parts), state.n_shapes, state.n_points,
                 "" if coarse is None else f", measured on {coarse} points per part", voxel,
                 data_range)
        wanted = config.baselines if baselines is not None else []
        if "none" in wanted and (config.strategy != "none" or config.correspondence == "cpd"):
            log.info("the initial (equal-spacing) correspondence is the none baseline")
            baselines("none", state, {"objective": initial})
        cpd = None
        if "cpd" in wanted and curves:
            log.warning("no CPD baseline for 2-D curves (it registers surfaces)")
            wanted = [name for name in wanted if name != "cpd"]
        if config.correspondence == "cpd" or "cpd" in wanted:
            cpd, template = cpd_state(state, prepared, config, executor, progress)
            if config.correspondence != "cpd":
                log.info("the CPD template correspondence is the cpd baseline")
                try:
                    objective = measured(cpd).total
                except ValueError:      # the coarse grid is not within the build's (not icospheres)
                    objective = cpd.objective_parts(integrated).total
                    log.info("the CPD baseline's objective is measured on its %d points per part",
                             len(cpd.grids[0][0]))
                baselines("cpd", cpd, {"objective": objective,
                                       "template": template})

        trace = Trace()
        if config.correspondence == "cpd":
            state = cpd
            state.objective = integrated
            initial_parts = final_parts = state.objective_parts()
            initial = final = final_parts.total
            trace.record(state, final, "integrated", 0)
            log.info("CPD correspondence (template %s): objective %.4f", template, final)
        else:
            rng = np.random.default_rng(config.seed)
            resumption = None
            if resume is not None:
                rng.bit_generator.state = resume.rng_state
                trace.rows = list(resume.trace_rows)
                elapsed = trace.rows[-1].wall_seconds if trace.rows else 0.0
                trace.start_wall -= elapsed
                trace.start_cpu -= trace.rows[-1].cpu_seconds if trace.rows else 0.0
                resumption = Resumption(resume.point, resume.record, resume.evaluations, elapsed)

            def save(point, current=None):
                """Checkpoint ``point``, reached in ``current`` (the optimisation's coarse stage's
                own state; by default ``state``)."""
                if checkpoint is not None:
                    checkpoint(state if current is None else current, point, rng, trace)

            try:
                optimise(state, (fixed, integrated), settings, rng, trace, progress, save,
                         resume=resumption, cluster=client_of(executor))
            except (KeyboardInterrupt, Cancelled):
                trace.stopped_by = Stop.INTERRUPTED
            if resume is None or resume.point.phase != PhasePoint.DONE:
                state.rebuild()  # also makes the state consistent after an interruption mid-step
            final_parts = measured(state)
            final = final_parts.total
            log.info("final objective %.4f (%s) after %.1f s, %d evaluations; optimisation %s",
                     final, described(final_parts),
                     trace.last.wall_seconds if trace.rows else 0.0, state.evaluations,
                     stop_summary(trace.stopped_by))
            if final > initial and not math.isclose(final, initial, rel_tol=OBJECTIVE_RTOL):
                log.info("F ended above the initial correspondence's (%.4f): the fixed-Delta "
                         "phase trades the smallest modes' description length for a more "
                         "compact model; generalization and specificity against the initial "
                         "correspondence's (the report) say which model is better", initial)
            if trace.stopped_by in (None, Stop.CONVERGED):   # else the last step's checkpoint stays
                save(PhasePoint(PhasePoint.DONE, trace.last.sweep if trace.rows else 0))
    named = parts if len(parts) > 1 else ()
    ending = OptimisationEnd(trace.stopped_by, config.max_time, config.max_sweeps,
                             trace.last.wall_seconds if trace.rows else 0.0)
    axes = principal_axes(state.aligned_shapes(), state.weights)   # one SVD: model, evaluation
    return Correspondence(state, shape_model_of(state, config, final, voxel, data_range, named,
                                                axes),
                          initial_parts, final_parts, voxel, data_range, trace, ending,
                          state.n_points if coarse is None else coarse * len(state.grids),
                          landmarks if state.guides is not None else None, axes)


def described(parts: ObjectiveParts) -> str:
    """The parts of F for the log."""
    return (f"description length {parts.description_length:.4f}, prior {parts.prior:.4f}, "
            f"guides {parts.guides:.4f}")


def shape_model_of(state: CorrespondenceState, config: BuildConfig, objective: float,
                   voxel_size: float, data_range: float, part_names=(),
                   axes: PrincipalAxes | None = None) -> ShapeModel:
    """The shape model of a correspondence: the area-weighted PCA of its aligned shapes (from
    their :func:`~.model.space.principal_axes` ``axes``, when known), with the
    sampling grid's triangles and sphere positions, the case names, the part names of a
    multi-part object, the guided landmarks' rows, and as metadata the
    objective, the method (the strategy, or "cpd"), the voxel size, the data range and the
    configuration (JSON), with the prior's weight as applied."""
    method = "cpd" if config.correspondence == "cpd" else config.strategy
    # the prior's weight as applied, so that ``fit`` applies the same whatever the default
    config = replace(config, smoothness=config.smoothness_for(curves=state.planar,
                                                              guided=state.guides is not None))
    if axes is None:
        axes = principal_axes(state.aligned_shapes(), state.weights)
    model = ShapeModel.from_axes(axes, state.weights,
                                 names=[e.name for e in state.examples],
                                 triangles=state.triangles(),
                                 part_sizes=[len(p) for p, _ in state.grids],
                                 part_names=part_names,
                                 objective=objective, strategy=method, voxel_size_mm=voxel_size,
                                 data_range_mm=data_range,
                                 config=json.dumps(config.to_dict()))
    model.parameters = np.concatenate([points for points, _ in state.grids])
    if state.guides is not None:
        model.landmarks = {label: int(row) for label, row in zip(state.guides.labels,
                                                                 state.guides.indices)}
    return model


def _outcome(evaluation):
    """The result of an evaluation that may have run on the executor; one interrupted there
    (Ctrl-C reaches the worker processes of a caller's executor too), cancelled, or lost with its
    worker process is done again here. Any other exception is a bug and propagates."""
    if not isinstance(evaluation, Task):
        return evaluation
    return evaluation.result(redo=(KeyboardInterrupt, CancelledError))
