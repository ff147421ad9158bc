"""The process that runs the library's long work for the module: a build, an analysis, a fit.

Started by :class:`.jobs.WorkerJob` as ``python -m MDLShapeModelLib.worker FOLDER`` (inside Slicer
with ``PythonSlicer``), so that the work never holds Slicer's main thread and a crash of native
code ends this process, not Slicer. It talks through files in ``FOLDER`` only:

- ``job.json`` (read): the command and its arguments, settings as the library's config records
  written as dicts;
- ``reports.jsonl`` (appended, a line per record, flushed at once): the library's progress
  reports ``{"fraction", "message"}`` (and ``"kind"`` where the report has one, see
  :class:`mdlshapemodel.progress.Message`), its warnings ``{"warning"}``, and last the end
  ``{"end": "done" | "cancelled" | "error" | "internal", ...}``;
- ``stop`` (made by the module to cancel): at its next report the work stops as a Ctrl-C stops
  the command line (a build's optimisation ends with the model of the state reached written).

Only the standard library is imported here before the job is read, and only the library's
public modules after: the worker is a face of the library like the command line.
"""

from __future__ import annotations

import json
import logging
import sys
import traceback
from pathlib import Path

JOB_FILE = "job.json"
REPORTS_FILE = "reports.jsonl"
STOP_FILE = "stop"
LOG_FILE = "worker.log"      # the process's stdout and stderr (tracebacks), written by the module


class Reports:
    """The progress callback of the library's protocol (:mod:`mdlshapemodel.progress`) writing
    each report to ``reports.jsonl``; it asks to stop, once, when ``stop`` appears."""

    def __init__(self, folder: Path):
        self.stop = folder / STOP_FILE
        self.stream = open(folder / REPORTS_FILE, "a", encoding="utf-8")

    def write(self, record: dict) -> None:
        self.stream.write(json.dumps(record) + "\n")
        self.stream.flush()

    def __call__(self, fraction, message):
        from mdlshapemodel.progress import kind_of    # (reports come once the job is read)

        record = {"fraction": fraction, "message": str(message)}
        kind = kind_of(message)
        if kind is not None:
            record["kind"] = kind
        self.write(record)
        if self.stop.exists():
            # one stop per request: a build's optimisation ends there and the library goes on
            # to write the model of the state reached (elsewhere the work ends: Cancelled)
            self.stop.unlink(missing_ok=True)
            return False
        return True


class WarningRecords(logging.Handler):
    """The library's warnings (a label in no case, an optimisation out of time, ...) as records
    of ``reports.jsonl``."""

    def __init__(self, reports: Reports):
        super().__init__(logging.WARNING)
        self.reports = reports

    def emit(self, record):
        self.reports.write({"warning": record.getMessage()})


def run(job: dict, reports: Reports) -> dict:
    """The job's command through the library's public functions; the end record's fields."""
    command = job["command"]
    if command == "build":
        from mdlshapemodel import BuildConfig, build_model

        result = build_model(job["inputs"], job["output"], BuildConfig.from_dict(job["config"]),
                             progress=reports, overwrite=job["overwrite"],
                             resume=job["resume"])
        return {"interrupted": bool(result.interrupted)}
    if command == "analyze":
        from mdlshapemodel.analyze import analyze_build
        from mdlshapemodel.config import AnalysisConfig

        config = AnalysisConfig(**job["config"]).validate()
        analyze_build(job["build"], job["table"], job["output"], config, progress=reports,
                      overwrite=True)
        return {}
    if command == "fit":
        from mdlshapemodel.fit import fit_cases

        results, rejected = fit_cases(job["model"], job["inputs"], job["output"],
                                      max_time=job["max_time"], progress=reports,
                                      overwrite=True)
        return {"cases": [result.name for result in results],
                "rejected": [[name, reason] for name, _, reason in rejected]}
    raise ValueError(f"unknown command {command!r}")


def main(argv) -> int:
    folder = Path(argv[1])
    job = json.loads((folder / JOB_FILE).read_text(encoding="utf-8"))
    reports = Reports(folder)
    from mdlshapemodel.errors import Cancelled, MDLShapeModelError

    logging.getLogger("mdlshapemodel").addHandler(WarningRecords(reports))
    try:
        outcome = run(job, reports)
    except Cancelled as error:
        reports.write({"end": "cancelled", "message": str(error)})
        return 1
    except MDLShapeModelError as error:   # a rejected input or setting: its one line
        reports.write({"end": "error", "kind": type(error).__name__, "message": str(error),
                       "setting": getattr(error, "setting", None),
                       "problem": getattr(error, "problem", None)})
        return 2
    except Exception as error:           # a bug: the traceback goes to worker.log
        traceback.print_exc()
        reports.write({"end": "internal", "kind": type(error).__name__, "message": str(error)})
        return 3
    reports.write({"end": "done", **outcome})
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
