"""Library work run in the background while Slicer stays responsive: a build, an analysis."""

from __future__ import annotations

import os
import pathlib
import queue
import shutil
import sys
import threading

from mdlshapemodel.config import AnalysisConfig, BuildConfig

from .records import ExportedInputs


class BackgroundJob:
    """Library work running in a background thread, so that Slicer stays responsive.

    The main thread polls :meth:`messages` (progress reports: (fraction or None, text)), may
    :meth:`cancel` (the work stops at its next report), and once :attr:`done` calls
    :meth:`finish` to load the results into the scene (MRML is touched only on the main thread).
    ``work(progress)`` is the library call; its result is kept in :attr:`result`.
    """

    def __init__(self, work, name: str):
        self.result = None
        self.error = None
        self._reports = queue.Queue()
        self._cancel = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(work,), daemon=True, name=name)
        self._thread.start()

    def _progress(self, fraction, message):
        self._reports.put((fraction, message))
        if self._cancel.is_set():
            # one False per Cancel: a build's optimisation stops there and the library goes on
            # to write the model of the state reached (elsewhere the work stops: Cancelled)
            self._cancel.clear()
            return False
        return True

    def _run(self, work):
        try:
            self.result = work(self._progress)
        except BaseException as error:  # handed to the main thread, which reports it
            self.error = error

    @property
    def done(self) -> bool:
        return not self._thread.is_alive()

    def wait(self, timeout: float | None = None) -> bool:
        self._thread.join(timeout)
        return self.done

    def cancel(self) -> None:
        self._cancel.set()

    def messages(self) -> list:
        """The progress reports since the last call, oldest first."""
        reports = []
        while True:
            try:
                reports.append(self._reports.get_nowait())
            except queue.Empty:
                return reports

    def finish(self):
        """The results in the scene (main thread, after :attr:`done`); re-raises the work's
        error."""
        if self.error is not None:
            raise self.error
        return self._load()

    def _load(self):
        return self.result


class BuildJob(BackgroundJob):
    """A build in a background thread (:class:`BackgroundJob`); Cancel stops the optimisation
    and the model of the state reached is written; :meth:`finish` loads the build's results."""

    def __init__(self, logic, exported: ExportedInputs, outputDirectory,
                 config: BuildConfig | None, overwrite: bool = False):
        self.logic = logic
        self.exported = exported
        self.outputDirectory = pathlib.Path(outputDirectory)
        super().__init__(lambda progress: logic.runBuild(exported.paths, self.outputDirectory,
                                                         config, progress, overwrite),
                         "MDLShapeModel build")

    @property
    def built(self):
        """The library's BuildResult (None until the build has ended)."""
        return self.result

    def _load(self):
        return self.logic.loadResults(self.outputDirectory, self.exported.rejected,
                                      self.result.interrupted)


class AnalysisJob(BackgroundJob):
    """An analysis in a background thread (:class:`BackgroundJob`); Cancel stops it (nothing is
    written); :meth:`finish` loads its effect map and table."""

    def __init__(self, logic, buildDirectory, table: pathlib.Path,
                 outputDirectory, config: AnalysisConfig):
        self.logic = logic
        self.outputDirectory = pathlib.Path(outputDirectory)
        super().__init__(lambda progress: logic.runAnalysis(buildDirectory, table,
                                                            self.outputDirectory, config,
                                                            progress),
                         "MDLShapeModel analysis")

    def _load(self):
        return self.logic.loadAnalysis(self.outputDirectory)


def workerPool(config: BuildConfig):
    """The executor for a build's per-case work. Inside the Slicer application, Python's
    ``sys.executable`` is the application itself, which cannot run worker processes: there the
    workers are started with Slicer's ``PythonSlicer`` interpreter. Elsewhere None: the library's
    own pools."""
    if config.workers <= 1 or not os.path.basename(sys.executable).lower().startswith("slicer"):
        return None
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    interpreter = shutil.which("PythonSlicer") or os.path.join(
        os.path.dirname(sys.executable), "PythonSlicer")
    context = multiprocessing.get_context("spawn")
    context.set_executable(interpreter)
    return ProcessPoolExecutor(max_workers=config.workers, mp_context=context)
