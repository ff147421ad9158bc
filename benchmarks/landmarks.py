"""Landmark transfer: expert landmarks carried from case to case through a build's correspondence.

What it measures. Every case has expert landmarks; every build writes its corresponded sample
points as one triangle mesh per case (``correspondence/<case>.vtp``, the same triangles for every
case). For a template case i, a target case j != i and a landmark l: the landmark of i is located
on i's corresponded mesh (its closest point: a triangle and barycentric coordinates), carried to
the same triangle and barycentric coordinates of j's corresponded mesh, and projected to the
closest point of j's own input surface; the error is the distance (mm) to j's landmark l. Reported
per build:

* single template: mean and median over all (i, j, l);
* median of templates: for each (j, l) the coordinate-wise median of the n - 1 predictions,
  projected to j's surface, against the truth; mean and median over (j, l);
* per label, the median-of-templates mean error of every build, next to the raters' spread (each
  rater's mean over trials against the mean of the other raters, mean over the evaluated cases):
  what one expert differs from the others;
* each case's mean error as a target (median of templates) and as a template (single), to show
  outliers; and ``located``: the mean distance of the landmarks from their own case's
  corresponded mesh (how closely the sample points' triangles cover the surface).

Only the cases that every build holds are evaluated. The builds: ``mdl`` (the defaults),
``initial`` (``--strategy none``: the initial correspondence from the sphere maps), ``cpd``
(``--correspondence cpd``: a template case registered to every case by coherent point drift),
and ``guided-even``, ``guided-odd``, ``guided-3`` and ``guided-6`` (the defaults with
``--landmarks``: every other label of every case, or 3 or 6 labels, guide the correspondence,
the others are held out; the evaluation then reports each guided build's error on the labels it
held out, beside the unguided builds' on the same labels).

Data: the femurs of VSDFullBodyBoneModels (github.com/RWTHmediTEC/VSDFullBodyBoneModels, commit
ee5c4f0 = v2.0, Fischer et al., Sci. Rep. 2019 and 2020; licence CC BY-NC-SA: benchmarks only,
never commit the data), extracted by ``landmark_data.py``: 19 whole femurs in mm (right ones
mirrored to look left) with 22 landmarks each, the mean of 5 raters x 4 trials. Two femurs (z055,
z057) have a handle (not genus 0); a build rejects them with a message and carries on. The
vertebrae and pelvises that ``landmark_data.py`` also writes are not genus 0 (a vertebra has a
hole, the pelvis is three bones), so this tool cannot model them: the benchmark covers the
femurs only.

    python benchmarks/landmark_data.py --output /tmp/landmarks
    python benchmarks/landmarks.py run /tmp/landmarks/femur --output /tmp/lm-femur

or step by step (options after ``--`` go to every build):

    python benchmarks/landmarks.py build /tmp/landmarks/femur --output /tmp/lm-femur \\
        --points 2562 -- --max-time 600
    python benchmarks/landmarks.py evaluate /tmp/landmarks/femur /tmp/lm-femur/mdl \\
        /tmp/lm-femur/initial /tmp/lm-femur/cpd /tmp/lm-femur/guided-even \\
        /tmp/lm-femur/guided-odd /tmp/lm-femur/guided-3 /tmp/lm-femur/guided-6
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

#: the guided builds' landmarks, chosen from the labels in the data's order: every other label
#: from the first (even) or the second (odd), and 3 or 6 labels spread over the order; the
#: others are held out
SPLITS = {"even": lambda labels: labels[0::2], "odd": lambda labels: labels[1::2],
          "3": lambda labels: [labels[k] for k in np.linspace(0, len(labels) - 1, 3).round()
                               .astype(int)],
          "6": lambda labels: [labels[k] for k in np.linspace(0, len(labels) - 1, 6).round()
                               .astype(int)]}
BUILDS = {"mdl": [], "initial": ["--strategy", "none"], "cpd": ["--correspondence", "cpd"],
          **{f"guided-{split}": ["--landmarks", f"{{output}}/guides-{split}"]
             for split in SPLITS}}


def write_guides(data: Path, output: Path) -> None:
    """``guides-<split>`` in ``output`` for every split of :data:`SPLITS`: every case's landmark
    file cut to the split's labels."""
    from mdlshapemodel.prepare.landmarks import read_landmarks

    for split, choose in SPLITS.items():
        folder = output / f"guides-{split}"
        folder.mkdir(parents=True, exist_ok=True)
        for path in sorted((data / "landmarks").glob("*.csv")):
            marks = read_landmarks(path)
            with open(folder / path.name, "w", newline="") as handle:
                writer = csv.writer(handle)
                writer.writerow(["label", "x", "y", "z"])
                chosen = choose(list(marks.labels))
                for label, point in zip(marks.labels, marks.points):
                    if label not in chosen:
                        continue
                    writer.writerow([label, *(f"{value:.6f}" for value in point)])


def guide_labels(build_folder: Path) -> list[str]:
    """The labels that guided a build (none: an unguided build), from its config.json."""
    from mdlshapemodel.prepare.landmarks import read_landmarks

    config = json.loads((build_folder / "config.json").read_text())
    if not config.get("landmarks"):
        return []
    labels = set()
    for path in Path(config["landmarks"]).glob("*.csv"):
        labels.update(read_landmarks(path).labels)
    return sorted(labels)


# ---------------------------------------------------------------- data


def rater_spread(data: Path, cases: list[str], labels: list[str]) -> dict:
    """The between-rater spread per label (mm) over ``cases``, from ``raters.json``: per case,
    the mean over raters of the distance from the rater's mean over trials to the mean of the
    other raters (landmark_data.py's definition); mean and median over the cases. Also the
    stored summary over all extracted cases."""
    raters = json.loads((data / "raters.json").read_text())
    values = []
    for case in cases:
        row = []
        for label in labels:
            points = np.array(raters["cases"][case]["points"][label], dtype=float)   # (R, T, 3)
            per_rater = np.nanmean(points, axis=1)
            n = len(per_rater)
            others = (per_rater.sum(axis=0)[None] - per_rater) / max(n - 1, 1)
            row.append(float(np.linalg.norm(per_rater - others, axis=1).mean()))
        values.append(row)
    values = np.array(values)
    spread = {label: {"mean": float(values[:, k].mean()), "median": float(np.median(values[:, k]))}
              for k, label in enumerate(labels)}
    spread["overall"] = {"mean": float(values.mean()), "median": float(np.median(values))}
    return {"evaluated_cases": spread,
            "all_cases": raters.get("spread", {}).get("inter_rater"),
            "definition": "mean over raters of |rater's mean over trials - mean of the other "
                          "raters|, mm; mean and median over cases"}


# ---------------------------------------------------------------- build


def build(args) -> int:
    """The three builds through the command line, one after the other; existing ones are kept."""
    data, output = Path(args.data), Path(args.output)
    output.mkdir(parents=True, exist_ok=True)
    write_guides(data, output)
    for name, options in BUILDS.items():
        options = [option.format(output=output) for option in options]
        folder = output / name
        if (folder / "model.h5").exists():
            print(f"{name}: {folder / 'model.h5'} exists, kept", flush=True)
            continue
        command = [sys.executable, "-m", "mdlshapemodel.cli", "build", str(data / "meshes"),
                   "-o", str(folder), "-q", "--points", str(args.points), *options, *args.extra]
        if folder.exists():
            command.append("--overwrite")     # an earlier build that did not finish
        print(f"{name}: python {' '.join(command[1:])}", flush=True)
        started = time.perf_counter()
        run = subprocess.run(command)
        seconds = time.perf_counter() - started
        if run.returncode != 0:
            print(f"{name}: build failed (exit {run.returncode}) after {seconds:.0f} s",
                  file=sys.stderr)
            return run.returncode
        held = len(list((folder / "correspondence").glob("*.vtp")))
        print(f"{name}: built in {seconds:.0f} s wall, {held} cases", flush=True)
    return 0


# ---------------------------------------------------------------- evaluate


def evaluate_build(data: Path, build_folder: Path, cases: list[str], labels: list[str],
                   landmarks: dict, surfaces: dict) -> dict:
    """The landmark-transfer errors of one build on ``cases`` (see the module docstring)."""
    from mdlshapemodel.prepare import io

    from mdlshapemodel.model.landmarks import transfer_errors

    points, triangles = {}, None
    for case in cases:
        vertices, faces = io.read_mesh(build_folder / "correspondence" / f"{case}.vtp")
        if triangles is None:
            triangles = faces
        elif not np.array_equal(faces, triangles):
            raise ValueError(f"{build_folder}: {case} has other triangles than {cases[0]}")
        points[case] = vertices
    n = len(cases)
    stacked = np.stack([points[c] for c in cases])                          # (n, n_p, 3)
    errors = transfer_errors(stacked, triangles, np.stack([landmarks[c] for c in cases]),
                             [surfaces[c] for c in cases])
    single, median, located = errors.single, errors.median, errors.located
    off_diagonal = ~np.eye(n, dtype=bool)
    values = single[off_diagonal]                                            # (n(n-1), L)
    return {
        "cases": n, "points": int(stacked.shape[1]),
        "single": {"mean": float(values.mean()), "median": float(np.median(values))},
        "median_of_templates": {"mean": float(median.mean()), "median": float(np.median(median))},
        "located": {"mean": float(located.mean()), "max": float(located.max())},
        "per_label": {label: {"median_of_templates_mean": float(median[:, k].mean()),
                              "median_of_templates_median": float(np.median(median[:, k])),
                              "single_mean": float(values[:, k].mean()),
                              "single_median": float(np.median(values[:, k]))}
                      for k, label in enumerate(labels)},
        "per_case": {case: {"as_target_median_of_templates_mean": float(median[j].mean()),
                            "as_target_single_mean": float(np.nanmean(single[:, j])),
                            "as_template_single_mean": float(np.nanmean(single[j])),
                            "located_mean": float(located[j].mean())}
                     for j, case in enumerate(cases)},
        "errors_median_of_templates": {case: median[j].round(4).tolist()
                                       for j, case in enumerate(cases)},
    }


def evaluate(args) -> int:
    """Landmark transfer through every build, on the cases that all of them hold; tables printed
    and ``landmarks.json`` written."""
    from mdlshapemodel.prepare import io
    from mdlshapemodel.prepare.landmarks import read_landmarks

    data = Path(args.data)
    builds = [Path(b) for b in args.builds]
    output = Path(args.output) if args.output else builds[0].parent
    inputs = {p.stem for p in (data / "meshes").glob("*.vtp")}
    held = [{p.stem for p in (b / "correspondence").glob("*.vtp")} for b in builds]
    cases = sorted(set.intersection(*held) & inputs)
    print(f"{len(cases)} cases held by every build, of {len(inputs)} inputs", end="")
    missing = {b.name: sorted(inputs - h) for b, h in zip(builds, held) if inputs - h}
    print("".join(f"; {name} lacks {', '.join(m)}" for name, m in missing.items()) or "")
    rejected = {}
    for b in builds:
        if (b / "rejected.csv").exists():
            with open(b / "rejected.csv", newline="") as handle:
                rejected[b.name] = {row["case"]: row["reason"] for row in csv.DictReader(handle)}
            for case, reason in rejected[b.name].items():
                print(f"  {b.name}: {case} rejected: {reason}")
    if len(cases) < 2:
        print("need at least two cases", file=sys.stderr)
        return 1
    labels, landmarks = None, {}
    for case in cases:
        read = read_landmarks(data / "landmarks" / f"{case}.csv")
        if labels is not None and list(read.labels) != labels:
            raise ValueError(f"{case}: landmark labels differ from {cases[0]}'s")
        labels, landmarks[case] = list(read.labels), read.points
    surfaces = {case: io.read_mesh(data / "meshes" / f"{case}.vtp") for case in cases}
    results = {}
    for build_folder in builds:
        started = time.perf_counter()
        results[build_folder.name] = evaluate_build(data, build_folder, cases, labels, landmarks,
                                                    surfaces)
        results[build_folder.name]["evaluation_seconds"] = time.perf_counter() - started
    spread = rater_spread(data, cases, labels)

    names = list(results)
    print(f"\nlandmark transfer error, mm ({len(cases)} cases, {len(labels)} landmarks; single: "
          f"over {len(cases) * (len(cases) - 1) * len(labels)} (i, j, l); median of templates: "
          f"over {len(cases) * len(labels)} (j, l))")
    print(f"{'build':<12} {'points':>6} {'single mean':>11} {'median':>7} "
          f"{'med-of-templ mean':>17} {'median':>7} {'located':>7}")
    for name in names:
        r = results[name]
        print(f"{name:<12} {r['points']:>6} {r['single']['mean']:>11.2f} "
              f"{r['single']['median']:>7.2f} {r['median_of_templates']['mean']:>17.2f} "
              f"{r['median_of_templates']['median']:>7.2f} {r['located']['mean']:>7.2f}")
    between = spread["evaluated_cases"]
    print(f"{'raters':<12} {'':>6} {'':>11} {'':>7} {between['overall']['mean']:>17.2f} "
          f"{between['overall']['median']:>7.2f}   (between-rater spread)")

    print("\nper label: median-of-templates mean error (mm) and the between-rater spread "
          "(mean over the cases)")
    print(f"{'label':<8}" + "".join(f" {name:>9}" for name in names) + f" {'raters':>9}")
    for label in labels:
        print(f"{label:<8}" + "".join(
            f" {results[n]['per_label'][label]['median_of_templates_mean']:>9.2f}"
            for n in names) + f" {between[label]['mean']:>9.2f}")
    print(f"{'all':<8}" + "".join(f" {results[n]['median_of_templates']['mean']:>9.2f}"
                                  for n in names) + f" {between['overall']['mean']:>9.2f}")

    print("\nper case: mean error as a target (median of templates) | as a template (single) "
          "| located, mm")
    print(f"{'case':<14}" + "".join(f" {name:>22}" for name in names))
    for case in cases:
        print(f"{case:<14}" + "".join(
            f" {results[n]['per_case'][case]['as_target_median_of_templates_mean']:>6.2f} | "
            f"{results[n]['per_case'][case]['as_template_single_mean']:>6.2f} | "
            f"{results[n]['per_case'][case]['located_mean']:>4.2f}" for n in names))

    guided = {name: guide_labels(b) for name, b in zip(names, builds)}
    unguided = [name for name in names if not guided[name]]
    if any(guided.values()):
        print("\nlandmarks as guides: median-of-templates mean error (mm) on the labels a guided "
              "build held out, and on its guides; the unguided builds on the same labels")
        print(f"{'guided build':<14} {'guides':>6} {'held out':>8} {'on guides':>9}"
              + "".join(f" {name + ' (held)':>16}" for name in unguided))
        for name in names:
            if not guided[name]:
                continue
            per_label = results[name]["per_label"]
            held = [label for label in labels if label not in guided[name]]
            held_error = float(np.mean([per_label[k]["median_of_templates_mean"] for k in held]))
            guide_error = float(np.mean([per_label[k]["median_of_templates_mean"]
                                         for k in guided[name] if k in per_label]))
            others = [float(np.mean([results[u]["per_label"][k]["median_of_templates_mean"]
                                     for k in held])) for u in unguided]
            results[name]["guided"] = {"guides": guided[name], "held_out": held,
                                       "held_out_error": held_error, "guides_error": guide_error,
                                       "unguided_held_out_error": dict(zip(unguided, others))}
            print(f"{name:<14} {len(guided[name]):>6} {held_error:>8.2f} {guide_error:>9.2f}"
                  + "".join(f" {value:>16.2f}" for value in others))

    output.mkdir(parents=True, exist_ok=True)
    report = {"data": str(data), "cases": cases, "labels": labels,
              "builds": {name: str(b) for name, b in zip(names, builds)},
              "missing": missing, "rejected": rejected, "results": results, "raters_spread": spread}
    (output / "landmarks.json").write_text(json.dumps(report, indent=1))
    print(f"\n-> {output / 'landmarks.json'}")
    return 0


def run(args) -> int:
    """Build (existing builds kept), then evaluate."""
    code = build(args)
    if code:
        return code
    output = Path(args.output)
    return evaluate(argparse.Namespace(data=args.data, output=str(output),
                                       builds=[str(output / name) for name in BUILDS]))


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = []
    if "--" in argv:                      # options after -- go to every build
        extra = argv[argv.index("--") + 1:]
        argv = argv[:argv.index("--")]
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    for command, text in (("build", "the mdl, initial and cpd builds (the CLI, one at a time)"),
                          ("run", "build, then evaluate")):
        sub = commands.add_parser(command, help=text,
                                  epilog="options after -- are passed to every build")
        sub.add_argument("data", help="folder with meshes/ and landmarks/ (landmark_data.py)")
        sub.add_argument("--output", required=True)
        sub.add_argument("--points", type=int, default=2562, help="sample points per case")
    evaluator = commands.add_parser("evaluate", help="landmark transfer through build outputs")
    evaluator.add_argument("data", help="folder with meshes/, landmarks/ and raters.json")
    evaluator.add_argument("builds", nargs="+", help="build output folders")
    evaluator.add_argument("--output", help="where landmarks.json goes (default: the first "
                                            "build's parent folder)")
    args = parser.parse_args(argv)
    if extra and args.command == "evaluate":
        parser.error("evaluate takes no build options")
    args.extra = extra
    return {"build": build, "evaluate": evaluate, "run": run}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
