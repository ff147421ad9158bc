"""Where a build's resident memory goes: each process's resident set and the C allocator's
bytes in use and free, at every build.log line and twice a second.

``run`` builds with the command line's own ``main`` in this process (so that the allocator's
figures are the build's), started by this script, and writes one JSON line per sample to
SAMPLES: the build process's resident MB (``rss``), glibc's bytes in use (``malloc_used``: the
heaps' and the separately mapped blocks', NumPy's arrays among them) and the free bytes its
heaps keep (``malloc_free``, resident or not), and the resident MB of each process the build
started (``kids``: the preparation workers, the helper that evaluates the baselines). Linux
with glibc (``/proc``, ``mallinfo2``) only.

``table`` prints, for each SAMPLES file, each stage's wall seconds, the build process's and all
processes' peak resident memory, the largest child's, and the allocator's peak in use, the
stages cut at build.log's lines, and says where the build compiled the numerical kernels (a
cold cache: the compiler's memory stays with the build process, about 0.5 GB, so such a run's
peaks are not those of a warm one). ``rounds`` prints the same peaks for each round of the
optimisation (the samples up to its build.log line), to see which rounds hold the peak::

    nice -n 10 python benchmarks/build_memory.py run /tmp/m250.jsonl -- \\
        build $(ls /tmp/pop1000/labels/*.nii.gz | head -250) --label 1 -o /tmp/m250 -q \\
        --cache-dir /tmp/cache --max-sweeps 1
    python benchmarks/build_memory.py table /tmp/m250.jsonl /tmp/m500.jsonl
    python benchmarks/build_memory.py rounds /tmp/m500.jsonl
"""

from __future__ import annotations

import argparse
import ctypes
import json
import logging
import os
import sys
import threading
import time

from end_to_end import _children, _rss_mb      # (this folder's /proc readers)

# each stage from the first log line with one of its openings to the next with one of its
# endings (an optimisation that converged logs no "stopped", a short evaluation no 50 % line)
STAGES = (("initial correspondence", ("cases in",), ("initial objective",)),
          ("optimisation", ("initial objective",), ("final objective",)),
          ("the baselines awaited", ("evaluating the baselines",),
           ("evaluating the model", "evaluated, outputs written")),
          ("evaluation and files", ("evaluating the model",), ("evaluated, outputs written",)))


class MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
                 "uordblks", "fordblks", "keepcost")]


def descendants(pid: int) -> list:
    found = _children(pid)
    return found + [grandchild for child in found for grandchild in descendants(child)]


def run(samples: str, arguments: list) -> int:
    libc = ctypes.CDLL(None)
    libc.mallinfo2.restype = MallInfo2
    me, start, lock = os.getpid(), time.time(), threading.Lock()
    out = open(samples, "w")

    def sample(kind: str, message: str = ""):
        info = libc.mallinfo2()
        row = {"t": round(time.time() - start, 2), "kind": kind, "msg": message[:120],
               "rss": round(_rss_mb(me), 1),
               "malloc_used": round((info.uordblks + info.hblkhd) / 2 ** 20, 1),
               "malloc_free": round(info.fordblks / 2 ** 20, 1),
               "kids": {str(kid): round(_rss_mb(kid), 1) for kid in descendants(me)}}
        with lock:
            out.write(json.dumps(row) + "\n")
            out.flush()

    class Sampled(logging.Handler):
        def emit(self, record):
            sample("log", record.getMessage())

    def ticking():
        while True:
            time.sleep(0.5)
            sample("tick")

    logging.getLogger("mdlshapemodel").addHandler(Sampled())
    threading.Thread(target=ticking, daemon=True).start()
    from mdlshapemodel.cli import main

    sys.argv = ["mdlshapemodel", *arguments]      # the report's command: the build's own
    code = main(arguments)
    sample("end")
    return code


#: build.log's line where a build compiles the numerical kernels (a cold cache)
COMPILING = "compiling numerical kernels"


def samples(path: str) -> list:
    """The samples of a SAMPLES file (a line cut short by a killed run is left out)."""
    rows = []
    with open(path, errors="ignore") as file:
        for line in file:
            try:
                rows.append(json.loads(line))
            except ValueError:
                pass
    return rows


def peaks(inside: list) -> tuple:
    """The build process's and all processes' resident peak (MB) over ``inside``, the largest
    child's and the allocator's peak in use."""
    return (max(r["rss"] for r in inside),
            max(r["rss"] + sum(r["kids"].values()) for r in inside),
            max(max(r["kids"].values(), default=0) for r in inside),
            max(r["malloc_used"] for r in inside))


def rounds(path: str) -> None:
    """Each optimisation round's peaks: the samples after the previous build.log line up to the
    round's own (``... round N, F = ...``)."""
    rows = samples(path)
    logged = [row for row in rows if row["kind"] == "log"]
    print(f"{path}\n| round | ends at s | build process peak MB | all processes peak MB "
          "| largest child MB | allocator in use, peak MB |\n|---|---|---|---|---|---|")
    for before, line in zip(logged, logged[1:]):
        if ", round " not in line["msg"]:
            continue
        inside = [row for row in rows if before["t"] <= row["t"] <= line["t"]]
        name = line["msg"].split(", F =")[0]
        print(f"| {name} | {line['t']:.0f} | " + " | ".join(f"{v:.0f}" for v in peaks(inside))
              + " |")


def table(paths: list) -> None:
    print("| samples | stage | wall s | build process peak MB | all processes peak MB "
          "| largest child MB | allocator in use, peak MB |\n|---|---|---|---|---|---|---|")
    compiled = []
    for path in paths:
        rows = samples(path)
        logged = [row for row in rows if row["kind"] == "log"]
        if any(COMPILING in row["msg"] for row in logged):
            compiled.append(path)
        stages = []
        for name, openings, endings in STAGES:
            begin = next((row["t"] for row in logged
                          if any(word in row["msg"] for word in openings)), None)
            end = None if begin is None else next(
                (row["t"] for row in logged
                 if row["t"] > begin and any(word in row["msg"] for word in endings)), None)
            if end is not None:
                stages.append((name, begin, end))
        if rows:
            stages.append(("the whole build", rows[0]["t"], rows[-1]["t"]))
        for name, begin, end in stages:
            inside = [row for row in rows if begin <= row["t"] <= end]
            print(f"| {path} | {name} | {end - begin:.0f} | "
                  + " | ".join(f"{v:.0f}" for v in peaks(inside)) + " |")
    for path in compiled:
        print(f"\n{path}: the build compiled the numerical kernels (a cold cache); its build "
              "process's peaks include the compiler's memory")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    running = commands.add_parser("run", help="build, sampling memory into SAMPLES")
    running.add_argument("samples")
    running.add_argument("arguments", nargs=argparse.REMAINDER,
                         help="after --: the command line's arguments (build ...)")
    tabled = commands.add_parser("table", help="each stage's peaks, from SAMPLES files")
    tabled.add_argument("paths", nargs="+")
    by_round = commands.add_parser("rounds", help="each optimisation round's peaks")
    by_round.add_argument("path")
    args = parser.parse_args()
    if args.command == "table":
        table(args.paths)
        return 0
    if args.command == "rounds":
        rounds(args.path)
        return 0
    arguments = args.arguments[1:] if args.arguments[:1] == ["--"] else args.arguments
    return run(args.samples, arguments)


if __name__ == "__main__":
    sys.exit(main())
