"""Label maps -> model and report with the real CLI: wall time by stage and peak memory, for
several population sizes.

For each N in ``--cases`` the first N shared hippocampus label maps (labels 1+2) are built with
``mdlshapemodel build`` (default settings unless given after ``--``) in a subprocess, with an empty
preprocessing cache (``--cold``, the default; ``--warm`` reuses ``--cache-dir``). The resident
memory of the build and all its worker processes is sampled every 0.1 s; the peak of their *sum*
is reported, and that of the largest single process. Stage times: preprocessing (from the
build's log), optimisation (to convergence or the budget, from convergence.csv), and the rest
(evaluation of the model and baselines, renderings, report, files). The optimisation time per
shape shows whether it grows linearly with N.

    python benchmarks/end_to_end.py --cases 20 40 80 --output /tmp/e2e
    python benchmarks/end_to_end.py --cases 82 --output /tmp/e2e82
    python benchmarks/end_to_end.py --cases 100 --output /tmp/e2e100
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import threading
import time
from datetime import datetime
from pathlib import Path

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "hippocampus" / "labels"


def _children(pid: int) -> list:
    found = []
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as file:
                found += [int(c) for c in file.read().split()]
    except OSError:
        pass
    return found


def _rss_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as file:
            for line in file:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


TICK = os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> float:
    """CPU seconds of a process and of the children it has waited for (``/proc/PID/stat``)."""
    try:
        with open(f"/proc/{pid}/stat") as file:
            fields = file.read().rpartition(")")[2].split()
    except OSError:
        return 0.0
    return sum(int(f) for f in fields[11:15]) / TICK    # utime, stime, cutime, cstime


class MemoryWatch(threading.Thread):
    """Peak summed RSS of a process tree, and of its largest process (sampled), and when the
    summed peak was reached (``time.time()``); ``samples`` keeps every sample as (``time.time()``,
    summed RSS MB, CPU seconds of the tree so far) for :func:`stage_table`."""

    def __init__(self, pid: int, interval: float = 0.1):
        super().__init__(daemon=True)
        self.pid, self.interval = pid, interval
        self.peak_total = self.peak_single = self.peak_time = 0.0
        self.samples = []
        self.started = time.time()
        self.done = threading.Event()

    def run(self):
        cpu = 0.0
        while not self.done.is_set():
            pids, queue = [], [self.pid]
            while queue:
                pid = queue.pop()
                pids.append(pid)
                queue += _children(pid)
            sizes = [_rss_mb(p) for p in pids]
            # a worker's CPU moves to its parent's cutime when it is reaped: never count less
            cpu = max(cpu, sum(_cpu_s(p) for p in pids))
            self.samples.append((time.time(), sum(sizes), cpu))
            if sum(sizes) > self.peak_total:
                self.peak_total, self.peak_time = sum(sizes), time.time()
            self.peak_single = max(self.peak_single, max(sizes, default=0.0))
            self.done.wait(self.interval)


def watched(command: list) -> tuple:
    """Run ``command``: (exit code, wall s, CPU s of it and every process it waited for, the
    :class:`MemoryWatch` of its process tree)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    process = subprocess.Popen(command)
    watch = MemoryWatch(process.pid)
    watch.start()
    code = process.wait()
    wall = time.perf_counter() - start
    watch.done.set()
    watch.join()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return code, wall, cpu, watch


def _stamp(line: str) -> float:
    return datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f").timestamp()


def stage_at(log: Path, moment: float) -> str:
    """The last line of a build.log written before ``moment`` (``time.time()``)."""
    lines = [line for line in log.read_text().splitlines() if line[:4].isdigit()]
    before = [line for line in lines if _stamp(line) <= moment]
    return before[-1][24:] if before else "(before the first line)"


# the stages of a build, each ended by the first build.log line that matches its pattern
STAGE_ENDS = (("start-up", r"preprocessing \d+ cases"),
              ("preparing", r"prepared \d+ cases in"),
              ("initial correspondence", r"initial objective"),
              ("optimisation", r"final objective"),
              ("model", r"\] evaluating"),
              ("the baselines' evaluation awaited", r"waited [\d.]+ s for the baselines"),
              ("writing", r"wrote the model, meshes and tables"),
              ("evaluation", r"evaluated the model in"),
              ("report", r"wrote the report in"),
              ("exit", None))


def stage_table(log: Path, watch: MemoryWatch) -> list:
    """Per stage of a build (:data:`STAGE_ENDS`): (name, wall s, CPU s of the whole process tree,
    peak summed RSS MB), from the build.log's time stamps and the watch's samples (the first
    stage begins when the watch does). A stage whose line is missing is left out."""
    lines = [line for line in log.read_text().splitlines() if line[:4].isdigit()]
    ends, begin = [], watch.started
    for name, pattern in STAGE_ENDS:
        if pattern is None:
            end = watch.samples[-1][0] if watch.samples else begin
        else:
            end = next((_stamp(line) for line in lines
                        if re.search(pattern, line) and _stamp(line) >= begin), None)
        if end is not None:
            ends.append((name, begin, end))
            begin = end

    def cpu_at(moment):
        before = [cpu for stamp, _, cpu in watch.samples if stamp <= moment]
        return before[-1] if before else 0.0

    rows = []
    for name, begin, end in ends:
        inside = [rss for stamp, rss, _ in watch.samples if begin <= stamp <= end]
        rows.append((name, end - begin, cpu_at(end) - cpu_at(begin), max(inside, default=0.0)))
    return rows


def preprocessing_seconds(log: Path) -> float:
    """Seconds from the start of a build to the end of its preprocessing, from its build.log."""
    lines = log.read_text().splitlines()
    for line in lines:
        if re.search(r"prepared \d+ cases in", line):
            return _stamp(line) - _stamp(lines[0])
    raise ValueError(f"{log}: no preprocessing line")


STAGES = (("waited", r"waited ([\d.]+) s for the baselines"),
          ("files", r"wrote the model, meshes and tables in ([\d.]+) s"),
          ("evaluation", r"evaluated the model in ([\d.]+) s"),
          ("report", r"wrote the report in ([\d.]+) s"))


def stage_seconds(log: Path) -> dict:
    """The seconds of the stages after the optimisation, from a build's build.log."""
    text = log.read_text()
    found = {}
    for name, pattern in STAGES:
        match = re.search(pattern, text)
        found[name] = float(match.group(1)) if match else 0.0
    return found


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, nargs="+", default=[20, 40, 80])
    parser.add_argument("--data", default=str(DATA))
    parser.add_argument("--label", default="1,2", help="labels of the object (default 1,2)")
    parser.add_argument("--output", default="end-to-end-benchmark")
    parser.add_argument("--warm", action="store_true",
                        help="reuse the preprocessing cache (default: an empty one per build)")
    parser.add_argument("extra", nargs=argparse.REMAINDER, help="build options after --")
    args = parser.parse_args()
    extra = [a for a in args.extra if a != "--"]
    inputs = sorted(Path(args.data).glob("*.nii.gz"))
    rows = []
    for n in args.cases:
        if n > len(inputs):
            print(f"only {len(inputs)} label maps in {args.data}", file=sys.stderr)
            return 2
        output = Path(args.output) / f"n{n}"
        with tempfile.TemporaryDirectory() as cache:
            command = [sys.executable, "-m", "mdlshapemodel.cli", "build",
                       *map(str, inputs[:n]), "--label", args.label, "-o", str(output), "-q",
                       *([] if args.warm else ["--cache-dir", cache]), *extra]
            code, wall, _, watch = watched(command)
        if code != 0:
            print(f"build of {n} cases failed (exit code {code})", file=sys.stderr)
            return 1
        metrics = json.loads((output / "metrics.json").read_text())
        with open(output / "convergence.csv") as file:
            trace = list(csv.DictReader(file))
        optimisation = float(trace[-1]["wall_seconds"]) if trace else 0.0
        prep = preprocessing_seconds(output / "build.log")
        stages = stage_seconds(output / "build.log")
        rows.append((n, wall, prep, optimisation, wall - prep - optimisation, watch.peak_total,
                     watch.peak_single, metrics["objective"]["initial"],
                     metrics["objective"]["final"], metrics["strategy"], metrics["n_points"]))
        other = wall - prep - optimisation - sum(stages.values())
        print(f"n_s={n}: {wall:.0f} s wall, peak {watch.peak_total:.0f} MB; seconds: "
              f"preprocessing {prep:.1f}, optimisation {optimisation:.1f}, "
              + ", ".join(f"{name} {value:.1f}" for name, value in stages.items())
              + f", the rest (start-up, initial correspondence, ...) {other:.1f}", flush=True)
        print(f"  the memory peak came after the log line: "
              f"{stage_at(output / 'build.log', watch.peak_time)}", flush=True)
    print(f"\n{'n_s':>4} {'points':>6} {'strategy':<20} {'wall s':>7} {'prep s':>7} {'opt s':>7} "
          f"{'opt s/shape':>11} {'rest s':>7} {'peak MB (all)':>13} {'(largest)':>9} "
          f"{'eq.14 initial':>13} {'final':>8}")
    for n, wall, prep, opt, rest, total, single, initial, final, strategy, points in rows:
        print(f"{n:>4} {points:>6} {strategy:<20} {wall:>7.0f} {prep:>7.0f} {opt:>7.0f} "
              f"{opt / n:>11.2f} {rest:>7.0f} {total:>13.0f} {single:>9.0f} {initial:>13.2f} "
              f"{final:>8.2f}")
    print("\nprep: preprocessing (cold cache unless --warm); opt: optimisation to convergence or "
          "--max-time; rest: baselines, evaluation, renderings, report and files.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
