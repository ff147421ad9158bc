"""``mdlshapemodel fit``: new cases fitted to a build's model -> the fit's folder, whole or absent.

The command's orchestration: the model read through :class:`~.folders.BuildFolder`, each case
fitted by :func:`~.model.fitting.fit_case` (the computing) and the results written through
:class:`~.folders.FitFolder` (the corresponded points and reconstructions, scores.csv and
landmarks.csv as a build writes them, rejected.csv and fit.json).
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np

from .errors import InputError, MDLShapeModelError
from .folders import FIT_FILES, BuildFolder, CorrespondedLandmark, FitFolder, find_inputs
from .model.fitting import build_config_of, fit_case, unusual_fit
from .prepare import io
from .prepare.case import Rejection
from .prepare.parts import case_inputs, read_manifest

log = logging.getLogger("mdlshapemodel")


def fit_cases(model_path, inputs, output, labels=None, max_time: float = 60.0,
              max_sweeps: int = 10_000, seed: int = 0, progress=None,
              strategy: str | None = None, manifest=None,
              overwrite: bool = False) -> tuple[list, list]:
    """Fit every input to the model and write the results to ``output``.

    ``model_path`` is a build's folder or its model file. ``inputs`` are files or folders (one
    case per file; a multi-part model's parts are split by its labels) and ``manifest`` a table
    of one file per part (case,part,file; see :func:`~.prepare.parts.read_manifest`; each file
    is its part: all its labels). Writes (:class:`~.folders.FitFolder`) each case's
    corresponded points (its own coordinates) and the model's reconstruction with all modes
    (same coordinates), both in a sub-folder per part for a multi-part model, the scores, the
    errors for M = 0..n_modes and the objective, the rejections and, for a model built with
    landmarks, every case's landmarks where its fitted correspondence puts them (its own
    coordinates). Returns (results, rejections as (name, path, reason)); the rejections'
    reasons are logged, each once with its count (:func:`~.prepare.io.rejection_lines`).

    The output folder's rule is build's (:func:`~.prepare.io.refuse_earlier`): one that holds an
    earlier fit is refused unless ``overwrite``, and a build's folder always (their files
    would mix). Everything is written into a folder beside it that takes its place at the end
    (:func:`~.prepare.io.written_folder`): the output holds a whole fit or nothing. No usable
    case raises :class:`InputError` with the reasons, and nothing is written.
    """
    build = BuildFolder(model_path)
    model = build.model()
    output = Path(output)
    if ((output.is_dir() and BuildFolder(output).model_file.is_file())
            or output.resolve() == build.path.resolve()):
        raise InputError(f"{output}: is a build's output folder; give the fit another one")
    io.refuse_earlier(output, FitFolder(output).earlier_fit(), overwrite, "fit")
    config = build_config_of(model)
    if labels:
        config.labels = list(labels)
        config.validate()
    cases = case_inputs(find_inputs(inputs), config)
    if manifest is not None:   # a file per part holds that part: no labels select within it
        names_only = replace(config, parts=[spec.name for spec in config.part_specs()])
        cases += read_manifest(manifest, names_only)
    if not cases:
        raise InputError("no input files found")
    with io.written_folder(output, FIT_FILES) as folder:
        results, rejected = _fit_into(FitFolder(folder), model, cases, config, max_time,
                                      max_sweeps, seed, progress, strategy)
    return results, rejected


def _fit_into(folder: FitFolder, model, cases, config, max_time, max_sweeps, seed, progress,
              strategy) -> tuple[list, list]:
    """Fit ``cases`` and write the outputs of :func:`fit_cases` into ``folder``."""
    meshes = model.part_meshes()
    results, rejected = [], []
    for case in cases:
        try:
            result = fit_case(model, case, config, max_time, max_sweeps, seed, progress,
                              strategy=strategy)
        except MDLShapeModelError as error:
            reason = str(error).removeprefix(f"{case.path}: ")
            rejected.append((case.name, case.path, reason))
            continue
        results.append(result)
        folder.write_meshes(meshes, [result.name], [result.corresponded],
                            [result.reconstruction(model)])
    reasons = io.rejection_lines((path, reason) for _, path, reason in rejected)
    if not results:
        raise InputError(f"no usable case: every one of the {len(cases)} input(s) was "
                         f"rejected ({'; '.join(reasons)})")
    for line in reasons:
        log.warning("rejected %s", line)            # the same reason once, with its count
    landmarks = [CorrespondedLandmark(r.name, label, point) for r in results
                 for label, point in model.landmark_points(r.corresponded).items()]
    summary = {r.name: {"file": r.path, "modes": list(range(model.n_modes + 1)),
                        "reconstruction_squared_mm2": r.squared_error.tolist(),
                        "reconstruction_distance_mm": r.distance_error.tolist(),
                        "mahalanobis": float(np.sqrt(np.sum(r.scores ** 2 / model.variances))),
                        "unusual": unusual_fit(model, r),
                        "objective": r.objective, "notes": r.notes} for r in results}
    folder.write_tables([r.name for r in results], [r.scores for r in results],
                        [Rejection(*r) for r in rejected], landmarks, summary)
    return results, rejected
