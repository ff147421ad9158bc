"""Many inputs -> prepared cases (every part of every case one task), on an executor, through the
cache; bugs named, not hidden."""

from __future__ import annotations

import logging
from concurrent.futures import Executor

from ..config import BuildConfig
from ..errors import InternalError
from ..parallel import executor_for, map_cases
from ..progress import Progress
from . import io
from .cache import cache_dir_of, prepare_case_cached
from .case import PreparedCase, Rejection
from .parts import CaseInput, case_inputs, joined, part_config

log = logging.getLogger("mdlshapemodel")


def _prepare_or_bug(path: str, config: BuildConfig, cache_dir: str | None):
    """:func:`cache.prepare_case_cached`, with a bug turned into an :class:`InternalError` that
    names the input (run in worker processes too; the traceback travels with the error)."""
    try:
        return prepare_case_cached(path, config, cache_dir)
    except Exception as error:
        raise InternalError(f"{path}: a bug in mdlshapemodel while preparing this input "
                            f"({type(error).__name__}: {error}); the traceback is in the log; "
                            "please report it") from error


def preprocess(inputs, config: BuildConfig, executor: Executor | None = None,
               progress: Progress | None = None) -> tuple[list, list]:
    """Prepare every case on ``executor`` (default: a process pool of ``config.workers``, none
    when 1; see :mod:`mdlshapemodel.parallel`), reusing cached results (:mod:`.cache`).

    ``inputs`` are files (each one case; with ``config.parts`` each split into its parts, see
    :func:`.parts.case_inputs`) or :class:`.parts.CaseInput` records (e.g. of a manifest,
    :func:`.parts.read_manifest`). Every part of every case is one task; a case whose part is
    rejected is rejected whole, the part named (:func:`.parts.joined`).

    A case whose worker process dies while preparing it (a crash in a native library, a kill)
    and again when it is prepared alone in a fresh process is rejected, "worker process died
    (signal 9) while preparing <file>"; the pool is replaced and the other cases go on
    (:func:`~mdlshapemodel.parallel.map_cases`). Such a rejection is not cached.

    Returns (prepared, rejected), each in input order. Raises :class:`InternalError` (naming the
    case) when preparing an input meets a bug rather than a problem of the input.
    """
    inputs = list(inputs)
    cases = (inputs if all(isinstance(item, CaseInput) for item in inputs) and inputs
             else case_inputs(inputs, config))
    tasks = [(case, part) for case in cases if not case.problem for part in case.parts]
    cache_dir = cache_dir_of(config)

    def died(index: int, how: str):
        path = tasks[index][1].path
        return Rejection(io.case_name(path), path, f"{how} while preparing {path}"), False

    with executor_for(config.workers, executor) as pool:
        results = map_cases(_prepare_or_bug, [(part.path, part_config(config, part), cache_dir)
                                              for _, part in tasks], pool,
                            progress, "prepared", died, config.workers)
    reused = sum(hit for _, hit in results)
    if reused:
        log.info("reused %d of %d preprocessed %s from the cache %s", reused, len(tasks),
                 "parts" if len(tasks) > len(cases) else "cases", cache_dir)
    done = iter(result for result, _ in results)
    outcomes = [Rejection(case.name, case.path, case.problem) if case.problem
                else joined(case, [next(done) for _ in case.parts]) for case in cases]
    prepared = [r for r in outcomes if isinstance(r, PreparedCase)]
    rejected = [r for r in outcomes if isinstance(r, Rejection)]
    return prepared, rejected
