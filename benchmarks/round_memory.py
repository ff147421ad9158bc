"""What the optimisation holds at its peak, per case: a build run in this process under
``tracemalloc``, a snapshot taken at the largest traced size reached while a round of the fast
strategy runs (``optimise_round``), and its largest holders, each named by the package's lines
that allocated it, in KB per case.

A thread polls the traced size every 20 ms while the build's main thread is inside
``optimise_round`` and takes a snapshot each time the size passes the last one's by 1 %. The build
stops once the correspondence is final (before the model and the outputs). ``--workers 1`` is
added: the baselines' evaluation then runs in this process before the optimisation, not beside
it. Tracing makes the build several times slower.

    python benchmarks/round_memory.py --data /tmp/pop2500/labels --label 1 --cases 200 \\
        --cache-dir /tmp/cache --output /tmp/rounds -- --max-time 3600
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
import tracemalloc
from pathlib import Path


class _Final(Exception):
    """Raised where the correspondence is final: the build stops there."""


def traced_peak(arguments: list, frames: int = 12) -> tuple[int, tracemalloc.Snapshot]:
    """Run ``mdlshapemodel`` with ``arguments`` (``build ...``) up to the end of its optimisation;
    the largest traced size inside a round and the snapshot taken there."""
    from mdlshapemodel.cli import main
    from mdlshapemodel.correspondence.state import CorrespondenceState

    builder = threading.get_ident()
    peak = {"size": 0, "snapshot": None}
    running = [True]

    def in_round() -> bool:
        frame = sys._current_frames().get(builder)
        while frame is not None:
            if frame.f_code.co_name == "optimise_round":
                return True
            frame = frame.f_back
        return False

    def poll():
        while running[0]:
            if in_round():
                size = tracemalloc.get_traced_memory()[0]
                if size > peak["size"] * 1.01:
                    peak["size"], peak["snapshot"] = size, tracemalloc.take_snapshot()
            time.sleep(0.02)

    def final(self):
        raise _Final

    release = CorrespondenceState.release_sampling
    CorrespondenceState.release_sampling = final
    tracemalloc.start(frames)
    watcher = threading.Thread(target=poll, daemon=True)
    watcher.start()
    try:
        main(arguments)
    except (_Final, SystemExit):
        pass
    finally:
        running[0] = False
        watcher.join()
        tracemalloc.stop()
        CorrespondenceState.release_sampling = release
    if peak["snapshot"] is None:
        raise SystemExit("no round of the fast strategy ran")
    return peak["size"], peak["snapshot"]


def holders(snapshot: tracemalloc.Snapshot, cases: int, top: int) -> list:
    """The ``top`` largest allocation sites: (KB per case, the package's last four lines)."""
    rows = []
    for statistic in snapshot.statistics("traceback")[:top]:
        ours = [frame for frame in statistic.traceback if "mdlshapemodel" in frame.filename]
        where = "; ".join(f"{Path(frame.filename).name}:{frame.lineno}" for frame in ours[-4:])
        rows.append((statistic.size / cases / 1024, where or "(outside the package)"))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="folder of label maps")
    parser.add_argument("--label", default="1")
    parser.add_argument("--cases", type=int, default=200)
    parser.add_argument("--cache-dir", default="")
    parser.add_argument("--output", required=True, help="the build's output folder")
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("build", nargs=argparse.REMAINDER, help="after --: more build options")
    args = parser.parse_args()
    inputs = sorted(str(p) for p in Path(args.data).glob("*.nii.gz"))[:args.cases]
    extra = args.build[1:] if args.build[:1] == ["--"] else args.build
    arguments = ["build", *inputs, "--label", args.label, "-o", args.output, "-q",
                 "--workers", "1", "--overwrite", *extra]
    if args.cache_dir:
        arguments += ["--cache-dir", args.cache_dir]
    size, snapshot = traced_peak(arguments)
    print(f"traced peak inside a round: {size / 2**20:.1f} MB, "
          f"{size / len(inputs) / 1024:.1f} KB per case ({len(inputs)} cases)")
    print("| KB per case | allocated at (the package's last lines) |\n|---|---|")
    for kb, where in holders(snapshot, len(inputs), args.top):
        print(f"| {kb:.1f} | {where} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
