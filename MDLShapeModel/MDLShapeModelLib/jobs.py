"""The library's long work in a process of its own (:mod:`.worker`), watched from Slicer's main
thread without ever blocking it: a build, an analysis, a fit.

A :class:`WorkerJob` starts the worker with Slicer's Python interpreter (``PythonSlicer``;
outside Slicer the running one) in a new process group, then only reads files: :meth:`poll`
returns the progress reports written since the last call (the Widget calls it from a timer,
a script from :meth:`wait`). :meth:`cancel` asks the work to stop at its next report (a build's
optimisation then writes the model of the state reached); :meth:`terminate` ends the worker and
every process it started at once (a build's folder keeps its checkpoint: the build resumes). A
worker that dies on its own (a crash in native code, killed) is reported by :meth:`finish` as
:class:`WorkerEnded` while Slicer goes on.
"""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass

from .resources import MODULE_DIRECTORY
from .worker import JOB_FILE, LOG_FILE, REPORTS_FILE, STOP_FILE


class WorkerEnded(RuntimeError):
    """The worker process ended without saying how its work ended (killed, or a crash of native
    code): the message names the work and how the process ended."""


@dataclass
class Report:
    """One record of the worker: a progress report (``fraction`` None where none is known;
    ``kind`` what it reports, such as :data:`mdlshapemodel.progress.OBJECTIVE`, or None) or a
    warning of the library (``warning`` True, the text in ``message``)."""

    fraction: float | None
    message: str
    warning: bool = False
    kind: str | None = None


def pythonInterpreter() -> str:
    """The Python that runs the worker: inside the Slicer application, whose ``sys.executable``
    is the application itself, Slicer's ``PythonSlicer``; elsewhere the running interpreter."""
    if not os.path.basename(sys.executable).lower().startswith("slicer"):
        return sys.executable
    return shutil.which("PythonSlicer") or os.path.join(os.path.dirname(sys.executable),
                                                        "PythonSlicer")


def workerEnvironment() -> dict:
    """The worker's environment: this one, with the module's folder (MDLShapeModelLib and, in an
    extension, the library beside it) first on the Python path."""
    environment = dict(os.environ)
    paths = [str(MODULE_DIRECTORY)] + [p for p in environment.get("PYTHONPATH", "").split(
        os.pathsep) if p]
    environment["PYTHONPATH"] = os.pathsep.join(paths)
    return environment


def _exitDescription(code: int) -> str:
    if code < 0:
        try:
            return f"killed by signal {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


class WorkerJob:
    """A job of :mod:`.worker` running in its own process (see the module's description).

    Parameters
    ----------
    job : dict
        The worker's ``job.json``: ``command`` and its arguments.
    name : str
        What the work is called in messages ("build", "analysis", "fit").
    load : callable(end record) -> result
        Makes the results (the scene's nodes) once the work is done; run by :meth:`finish` on
        the main thread.
    folder : path, optional
        The job's folder (``job.json``, ``reports.jsonl``, ``worker.log``); default a new
        temporary one.
    """

    def __init__(self, job: dict, name: str, load, folder=None):
        self.name = name
        self._load = load
        self.folder = pathlib.Path(folder or tempfile.mkdtemp(prefix="MDLShapeModel-job-"))
        self.folder.mkdir(parents=True, exist_ok=True)
        (self.folder / JOB_FILE).write_text(json.dumps(job), encoding="utf-8")
        self.end = None            # the worker's end record, once read
        self.cancelled = False
        self._read = 0             # bytes of reports.jsonl read so far
        self._reapedGroup = False
        with open(self.folder / LOG_FILE, "wb") as log:
            posix = os.name != "nt"
            self.process = subprocess.Popen(
                [pythonInterpreter(), "-m", "MDLShapeModelLib.worker", str(self.folder)],
                stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                env=workerEnvironment(), start_new_session=posix,
                creationflags=0 if posix else subprocess.CREATE_NEW_PROCESS_GROUP)

    @property
    def pid(self) -> int:
        """The worker's process id (on POSIX also its process group's)."""
        return self.process.pid

    @property
    def done(self) -> bool:
        """Whether the worker process has ended."""
        return self.process.poll() is not None

    def poll(self) -> list:
        """The worker's reports (:class:`Report`) written since the last call, oldest first;
        never waits."""
        path = self.folder / REPORTS_FILE
        if not path.exists():
            return []
        with open(path, "rb") as stream:
            stream.seek(self._read)
            data = stream.read()
        complete = data[:data.rfind(b"\n") + 1]    # a line being written is read next time
        self._read += len(complete)
        reports = []
        for line in complete.decode("utf-8").splitlines():
            record = json.loads(line)
            if "end" in record:
                self.end = record
            elif "warning" in record:
                reports.append(Report(None, record["warning"], warning=True))
            else:
                reports.append(Report(record["fraction"], record["message"],
                                      kind=record.get("kind")))
        return reports

    def wait(self, timeout: float | None = None, progress=None) -> bool:
        """Block until the worker ends (at most ``timeout`` seconds): the headless way. With
        ``progress``, each progress report is read (:meth:`poll`) and goes to
        ``progress(fraction, message)`` (the library's protocol: returning False cancels; the
        message a :class:`mdlshapemodel.progress.Message` of the report's kind); without, the
        reports are left to :meth:`poll`. Returns :attr:`done`."""
        from mdlshapemodel.progress import Message

        stop = None if timeout is None else time.monotonic() + timeout
        while True:
            ended = self.done
            for report in self.poll() if progress is not None else ():
                if report.warning:
                    continue
                if progress(report.fraction, Message(report.message, report.kind)) is False:
                    self.cancel()
            if ended or (stop is not None and time.monotonic() >= stop):
                return ended
            time.sleep(0.1)

    def cancel(self) -> None:
        """Ask the work to stop at its next report (a build's optimisation writes the model of
        the state reached; elsewhere the work ends with nothing written)."""
        self.cancelled = True
        if not self.done:
            (self.folder / STOP_FILE).touch()

    def terminate(self) -> None:
        """End the worker and every process it started, now (a build's folder resumes from its
        checkpoint)."""
        self.cancelled = True
        self._killGroup()
        self.process.wait()

    def _killGroup(self):
        """Kill the worker's process group (the worker and its pools). Its id stays this job's
        while the worker runs or any process of the group lives; :meth:`finish` kills it once,
        as soon as the job is finished, never later."""
        if self._reapedGroup:
            return
        if os.name == "nt":
            subprocess.run(["taskkill", "/F", "/T", "/PID", str(self.pid)],
                           capture_output=True, check=False)
        else:
            try:
                os.killpg(self.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass

    def finish(self):
        """The results (main thread, once :attr:`done`): ``load`` of the end record. Raises the
        library's error of a rejected input or setting (its class, with ``setting`` for a
        ``ConfigError``), :class:`~mdlshapemodel.errors.Cancelled` for work cancelled before it
        had a result, :class:`WorkerEnded` for a worker that ended without a word."""
        if not self.done:
            raise RuntimeError(f"the {self.name} is still running")
        self.poll()
        if self.end is None:          # it died: what it started may live on in its group
            self._killGroup()
        self._reapedGroup = True
        from mdlshapemodel import errors

        end = self.end or {}
        kind = end.get("end")
        if kind == "done":
            return self._load(end)
        if kind == "cancelled":
            raise errors.Cancelled(f"the {self.name} was cancelled")
        if kind == "error":
            error = getattr(errors, end["kind"], errors.MDLShapeModelError)
            if error is errors.ConfigError:
                raise errors.ConfigError(end["message"], setting=end.get("setting"),
                                         problem=end.get("problem"))
            raise error(end["message"])
        if kind == "internal":
            raise errors.InternalError(f"the {self.name} met a bug ({end['kind']}: "
                                       f"{end['message']}); see {self.folder / LOG_FILE}")
        how = ("it was stopped (Cancel twice)" if self.cancelled
               else f"it ended unexpectedly ({_exitDescription(self.process.returncode)})")
        raise WorkerEnded(f"The {self.name} process did not finish: {how}. See "
                          f"{self.folder / LOG_FILE}.")
