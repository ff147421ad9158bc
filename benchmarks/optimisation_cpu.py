"""CPU seconds of the optimisation's parts in one build: a build run in this process with the
functions below timed by the CPU clock of the thread that runs them (``time.thread_time``; the
optimisation's threads included), or of the whole process where marked.

    OPENBLAS_NUM_THREADS=1 python benchmarks/optimisation_cpu.py /tmp/cpu.txt -- \
        build $(ls -d ../shared/data/hippocampus/labels/* | grep -v _011 | head -40) \
        -o /tmp/cpu40 --no-cache --label 1,2 -q

Unlike py-spy's samples (``build_profile.py``), the seconds are of CPU, not of the wall: a thread
waiting for a core on a busy machine is not counted, and two trees measured one after the other
on the same machine compare. One BLAS thread (``OPENBLAS_NUM_THREADS=1``) keeps the BLAS work on
the calling thread, where its clock counts it. Run it on a tree whose kernels are compiled
(a build before): a first run counts the compilation in the functions that wait for it. Each
row: seconds, calls, what was timed (a call within another call of the same row is not counted
twice).
"""

from __future__ import annotations

import atexit
import functools
import sys
import threading
import time
from collections import defaultdict

_TOTALS = defaultdict(float)
_CALLS = defaultdict(int)
_LOCK = threading.Lock()
_DEPTH = threading.local()


def timed(owner, name: str, label: str, clock=time.thread_time) -> None:
    """Replace ``owner.name`` by a wrapper that adds the ``clock`` seconds of its outermost calls
    to the row ``label``."""
    function = getattr(owner, name)

    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        depth = getattr(_DEPTH, label, 0)
        setattr(_DEPTH, label, depth + 1)
        start = clock()
        try:
            return function(*args, **kwargs)
        finally:
            setattr(_DEPTH, label, depth)
            if depth == 0:
                with _LOCK:
                    _TOTALS[label] += clock() - start
                    _CALLS[label] += 1

    setattr(owner, name, wrapper)


def instrument() -> None:
    """Time the optimisation's parts (their modules as the build calls them)."""
    from mdlshapemodel import build
    from mdlshapemodel.correspondence import smoothness, state
    from mdlshapemodel.correspondence import strategies
    from mdlshapemodel.correspondence.strategies import blocks, fast

    process = time.process_time
    timed(build, "optimise", "optimisation (process)", process)
    timed(fast, "optimise_round", "its rounds (process)", process)
    timed(strategies, "_finish_coarse_stage", "fields replayed on the build's points (process)",
          process)
    timed(blocks.SphereBlock, "sample", "SphereBlock.sample")
    timed(blocks.SphereBlock, "gradient", "SphereBlock.gradient")
    timed(blocks.SphereBlock, "__init__", "SphereBlock made (its FieldBasis)")
    timed(fast, "gradient_at", "F and dF/dX (gradient_at)")
    timed(smoothness.SmoothnessTerms, "energy", "  the prior's energy and B~ D")
    timed(smoothness, "bending_matrix", "the prior's bending matrix")
    timed(fast.FieldRound, "trial", "FieldRound.trial (its own thread)")
    timed(fast.FieldRound, "gradient", "FieldRound.gradient (its own thread)")
    timed(state.PartState, "replay_unfolded", "PartState.replay_unfolded")
    timed(state.PartState, "on_grid", "PartState.on_grid (coarse views)")


def main() -> int:
    if len(sys.argv) < 3 or sys.argv[2] != "--":
        sys.exit(__doc__)
    output = sys.argv[1]
    from mdlshapemodel import cli

    instrument()

    @atexit.register
    def write():
        with open(output, "w") as out:
            for label in _TOTALS:
                print(f"{_TOTALS[label]:8.2f} s {_CALLS[label]:7d}  {label}", file=out)

    return cli.main(sys.argv[3:])


if __name__ == "__main__":      # (the build's worker processes import this file: no run there)
    sys.exit(main())
