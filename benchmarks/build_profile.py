"""Where the time of a build goes: py-spy samples of the build and of its worker processes,
summed per stage and per costly function.

    py-spy record --subprocesses -r 50 -f raw -o /tmp/build.raw -- \
        mdlshapemodel build INPUTS -o /tmp/profiled --no-cache --label 1,2
    python benchmarks/build_profile.py /tmp/build.raw

py-spy (in the test extras' environment: ``pip install py-spy``) samples every thread of every
process ``--rate`` times a second while it runs Python or compiled code it called; a sample is
counted once for each function on its stack, so a stage's seconds include its callees', and the
rows overlap. The seconds are of samples, not of the wall: a stage that runs in two processes
at once counts twice, and on a machine with other work a thread waiting for a core is sampled as
running.
"""

from __future__ import annotations

import argparse
from collections import Counter

# (row, function names whose samples it sums; the first found on a stack counts)
ROWS = [
    ("start-up imports (every process)", ("_find_and_load",)),
    ("preparing the cases (workers)", ("prepare_case",)),
    ("initial correspondence", ("initial_state",)),
    ("  sphere maps aligned", ("align_parameterizations",)),
    ("  surface grids placed", ("surface_grids",)),
    ("optimisation", ("optimise",)),
    ("  the sampling of the fields' rounds", ("SphereBlock.sample",)),
    ("the fields replayed on the build's points", ("carry_over.<locals>.replay",)),
    ("the smoothness prior (every stage)", ("SmoothnessTerms.energy",)),
    ("writing the model, meshes and tables", ("write_shapes",)),
    ("  mesh files", ("write_polydata",)),
    ("evaluating the model", ("_evaluate",)),
    ("  generalization jackknife", ("generalization_jackknife",)),
    ("  point specificity", ("specificity",)),
    ("  surface generalization", ("surface_generalization",)),
    ("  surface specificity", ("surface_specificity",)),
    ("the report", ("write_report",)),
]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("raw", help="py-spy's raw (collapsed stacks) output")
    parser.add_argument("--rate", type=float, default=50.0, help="py-spy's samples per second")
    parser.add_argument("--top", type=int, default=15, help="functions by their own samples")
    args = parser.parse_args()
    rows, own, total = Counter(), Counter(), 0
    for line in open(args.raw):
        stack, _, count = line.rstrip().rpartition(" ")
        count, frames = int(count), stack.split(";")
        total += count
        names = {frame.split(" (")[0] for frame in frames}
        for row, functions in ROWS:
            if any(name in names for name in functions):
                rows[row] += count
        name, _, place = frames[-1].partition(" (")
        own[f"{name} ({place.rpartition('/')[2]}" if place else name] += count
    print(f"{total / args.rate:.1f} s of samples in all")
    for row, _ in ROWS:
        print(f"{rows[row] / args.rate:8.1f} s  {row}")
    print("functions by their own samples:")
    for name, count in own.most_common(args.top):
        print(f"{count / args.rate:8.1f} s  {name}")


if __name__ == "__main__":
    main()
