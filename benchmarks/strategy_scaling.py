"""Tables II-III of Davies et al. (TMI 2010) on the shared hippocampi: how the strategies scale with n_s.

For every training-set size n_s (``--sizes``, the paper's 3-D sizes 15, 25, 35 by default) and trial
k (``--trials``), draw n_s label maps (labels 1+2) at random from the pool of usable shared
hippocampi with a seed of its own, and run every strategy (``--strategies``) on that training set
with an optimiser seed of its own, for a fixed budget (``--budget`` CPU seconds). The convergence trace
of every run is written to ``OUTPUT/traces/``. Then, with :func:`mdlshapemodel.model.convergence.scaling_study`,
compute alpha of eq. (19) of each strategy at each n_s relative to the reference (III-D4,
one-at-a-time with pose, at the smallest n_s, as the paper), with 100 bootstrap resamples of trial
pairs for the standard errors, and the gradient d alpha / d n_s (weighted least squares, +- SE),
once with "time" = CPU seconds of the optimising process and once with "time" = number of
objective evaluations. ``--analyse-only`` redoes the analysis from the stored traces.

    PYTHONPATH=MDLShapeModel python benchmarks/strategy_scaling.py --budget 20 --points 642 \\
        --jobs 2 --max-wall 240 --output /tmp/strategy-scaling
    PYTHONPATH=MDLShapeModel python benchmarks/strategy_scaling.py --analyse-only \\
        --output /tmp/strategy-scaling

Choices (and why)
-----------------
Objective and phase
    Every run optimises eq. (14) only (the full objective, Delta averaged over [1e-4, 0.5] voxel;
    ``OptimisationSettings.fixed_fraction = 0``) and the curves are the trace rows of phase
    "integrated". The library's default schedule (eq. 13 at Delta = 0.1 voxel, then eq. 14) gives
    curves made of two pieces of *different functions*, with a jump where the phase changes at a
    time that depends on the budget, not on the strategy; eq. (19) cannot relate such curves, and
    comparing only the first piece (eq. 13) would measure convergence on a function that is not
    the final objective. A single phase makes every curve one function of time, from the same
    starting point (the Procrustes-aligned initial parameterisation) for every strategy of a trial.
    ``--objective fixed`` runs eq. (13) alone instead (cheaper per evaluation).

Normalising the objective across n_s
    Not needed for alpha: F grows roughly in proportion to n_s (every mode costs about
    -n_s ln Delta + ...), but eq. (19) fits f_ref(t) = a + b f(alpha t) with a free offset a and
    scale b, which absorb any affine change of F; only the *shape in time* of the curves is
    compared. Trials of one (strategy, n_s) are averaged on raw F; their offsets differ with the
    training set, which changes the mean curve by a constant (absorbed by a) and weighs the trials
    by their total decrease. The raw F values are stored, so any normalisation can be tried with
    ``--analyse-only`` after editing :func:`curves`.

Time
    ``cpu_seconds`` of the trace (process CPU time since the start of the optimisation; BLAS runs
    single-threaded inside ``strategies.optimise``), and ``evaluations`` (one evaluation of F, for
    one trial shape of one example or for a whole trial population alike). Times count from the
    first row of the run. The budget is in CPU seconds (checked by the progress callback after
    every example or every 100 simplex evaluations), so a busy machine makes runs longer, not
    shorter; ``--max-wall`` caps the wall time. The convergence test is switched off
    (``tolerance = 0`` and no limit on the sweeps without gain), so the simplex and
    one-at-a-time runs use their whole budget, as in the paper's fixed-length trials. With
    ``tolerance = 0`` alone, one-at-a-time (III-D3) had three sweeps in a row without any gain
    (the library's convergence test) after 15-70 CPU s at n_s = 15 and 25: with the paper's
    kernel widths (half-normal, sigma_G = 1/32) most random kernels are narrower than the
    spacing of 642 samples, and it is close to stalling there (run on to 150 s, those runs
    gained 0-1.6 nats more). Only fast ends early, after its finest level: it has
    converged, and its curve is held at its final value up to the end of the longest run
    (``hold_last`` of :func:`~mdlshapemodel.model.convergence.compare_strategies`); the table counts
    such runs, and the runs cut by the wall-clock cap, which are held too. Rows are recorded at
    every improvement inside a step (``OptimisationSettings.trace_improvements``) and the mean
    curves are averaged on a log-spaced grid (``--spacing log``), so that alpha can be measured
    even when one strategy is hundreds of times slower than the reference.

Trials
    Trial k at n_s uses the same training set and optimiser seed for every strategy (strategies
    are compared on equal terms), and a different set and seed from every other trial. The
    bootstrap draws the trials of the two strategies compared independently (the paper's
    "sampling ... a pair of trials (one from each strategy)"). hippocampus_011 is left out of the
    pool (a duplicate of hippocampus_010), as are cases that preprocessing rejects.

Multiresolution (III-D1)
    Can be run (``--strategies ... multiresolution``) and its traces are stored, but it is left
    out of the alpha table, as in the paper (V-A): its curve has another shape (it stalls once
    the number of simplex parameters doubles), so eq. (19) does not describe it.

Fast (ours)
    ``--strategies fast`` runs the default strategy too, on the same training sets; its alpha
    against the same reference is added to the table (no paper value). Its curve has a row per
    round (coarse-to-fine L-BFGS-B rounds), not per kernel.

Output folder
    ``plan.json`` (arguments, pool, every job's cases and seed); ``traces/<strategy>_ns<n>_t<k>.csv``
    (``convergence.csv`` format) with ``.json`` next to it (cases, seed, budget, final F, CPU
    seconds, evaluations, n_p). A later run into the same folder with the same budget, points,
    objective and seed adds its jobs (other strategies, sizes or trials) to ``plan.json`` and runs
    only those, so the analysis covers both. ``alphas.csv`` (time, strategy, n_s, alpha, SE, a,
    b) and ``results.json`` (everything, including the bootstrap alphas and the gradients);
    ``table.txt`` (what is printed).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import csv
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "hippocampus" / "labels"
STRATEGIES = ("multiscale", "one-at-a-time", "one-at-a-time-pose")
REFERENCE = "one-at-a-time-pose"
BOUNDS = (1e-3, 1e5)                # search range of alpha
DUPLICATES = ("hippocampus_011",)   # identical to hippocampus_010 (data README)
TIMES = (("cpu_seconds", "CPU time"), ("evaluations", "evaluations"))
EXTRA = ("multiresolution", "fast")   # can be run; multiresolution is left out of the table
PAPER_TABLE_III = {"multiscale": (47.5163, 2.4037), "one-at-a-time": (0.3276, 0.2722),
                   "one-at-a-time-pose": (0.3106, 0.2758)}
PAPER_TABLE_II = {"multiscale": (5.4613, 1.0384), "one-at-a-time": (0.9082, 0.4624),
                  "one-at-a-time-pose": (0.8282, 0.4576)}    # 2-D: 100 hands
LABELS = {"multiscale": "Multiscale (III-D2)", "one-at-a-time": "One-at-a-time (III-D3)",
          "one-at-a-time-pose": "Including pose (III-D4)", "multiresolution":
          "Multiresolution (III-D1)", "fast": "Fast (ours, default)"}
ANALYSED = STRATEGIES + ("fast",)


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--output", default="strategy-scaling", help="output folder")
    parser.add_argument("--data", default=str(DATA), help="folder of the label maps (or curves)")
    parser.add_argument("--pattern", default="*.nii.gz",
                        help="the pool's files in --data, e.g. '*.csv' for 2-D curves (Table II)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[15, 25, 35], help="n_s values")
    parser.add_argument("--trials", type=int, default=3, help="trials per n_s")
    parser.add_argument("--strategies", nargs="+", default=list(STRATEGIES),
                        choices=list(STRATEGIES) + list(EXTRA))
    parser.add_argument("--budget", type=float, default=60.0,
                        help="CPU seconds of optimisation per run")
    parser.add_argument("--max-wall", type=float, default=0.0,
                        help="wall-clock cap per run, seconds (default 10 x --budget)")
    parser.add_argument("--objective", choices=("integrated", "fixed"), default="integrated",
                        help="the single objective optimised: eq. 14 (default) or eq. 13")
    parser.add_argument("--points", type=int, default=None,
                        help="n_p, sample points per shape (default: the build's, 2562 on the "
                             "sphere, 128 on the circle)")
    parser.add_argument("--seed", type=int, default=2010, help="seed of subsets and optimisers")
    parser.add_argument("--jobs", type=int, default=2, help="runs in parallel (processes)")
    parser.add_argument("--bootstrap", type=int, default=100, help="bootstrap resamples")
    parser.add_argument("--grid", type=int, default=300,
                        help="points of the time grid of the mean curves")
    parser.add_argument("--spacing", choices=("log", "linear"), default="log",
                        help="time grid of the mean curves: regular in log t or in t")
    parser.add_argument("--analyse-only", action="store_true",
                        help="skip the runs; analyse the traces in --output")
    parser.add_argument("--rerun", action="store_true",
                        help="run again the jobs whose trace already exists")
    return parser.parse_args(argv)


# ---------------------------------------------------------------------------------------------
# planning


def usable_pool(data: Path, workers: int, pattern: str = "*.nii.gz") -> list:
    """Sorted paths of the pool: the files that preprocessing accepts, minus duplicates."""
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.prepare.io import case_name
    from mdlshapemodel.prepare import preprocess

    paths = [p for p in sorted(data.glob(pattern)) if case_name(p) not in DUPLICATES]
    prepared, rejected = preprocess(paths, BuildConfig(labels=[1, 2], workers=workers))
    for rejection in rejected:
        print(f"left out of the pool: {rejection.name}: {rejection.reason}", file=sys.stderr)
    accepted = {case.name for case in prepared}
    return [str(p) for p in paths if case_name(p) in accepted]


def plan_jobs(pool: list, sizes, trials: int, strategies, seed: int) -> list:
    """One job per (n_s, trial, strategy); a trial's cases and seed are shared by its strategies."""
    jobs = []
    for n_s in sorted(sizes):
        if n_s > len(pool):
            raise SystemExit(f"n_s = {n_s} exceeds the pool of {len(pool)} usable cases")
        for trial in range(trials):
            trial_seed = int(np.random.SeedSequence([seed, n_s, trial]).generate_state(1)[0])
            rng = np.random.default_rng(trial_seed)
            cases = sorted(str(pool[k]) for k in rng.choice(len(pool), n_s, replace=False))
            for strategy in strategies:
                jobs.append({"strategy": strategy, "n_s": n_s, "trial": trial,
                             "seed": trial_seed, "cases": cases})
    return jobs


def merged_plan(old: dict, new: dict) -> dict:
    """The plan of an output folder extended by the jobs of a new run with the same settings."""
    same = ("budget", "max_wall", "objective", "points", "seed")
    differ = [k for k in same if old["args"][k] != new["args"][k]]
    if differ:
        raise SystemExit(f"the output folder holds a study with other settings ({', '.join(differ)}"
                         f"): use another --output")
    key = lambda job: (job["strategy"], job["n_s"], job["trial"])  # noqa: E731
    known = {key(job) for job in old["jobs"]}
    args = dict(old["args"])
    for name in ("strategies", "sizes"):
        args[name] = sorted(set(old["args"][name]) | set(new["args"][name]))
    args["trials"] = max(old["args"]["trials"], new["args"]["trials"])
    return {"args": args, "pool": old["pool"],
            "jobs": old["jobs"] + [job for job in new["jobs"] if key(job) not in known]}


def trace_path(output: Path, job: dict) -> Path:
    return output / "traces" / f"{job['strategy']}_ns{job['n_s']}_t{job['trial']}.csv"


# ---------------------------------------------------------------------------------------------
# one run (in a worker process)


def initial_state(paths, points: int):
    """Correspondence state of the cases as ``mdlshapemodel build`` sets it up (from the cache)
    and the two objectives (eq. 13, eq. 14) with the default Delta settings (Table I)."""
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.correspondence.initial import initial_state as pipeline_state
    from mdlshapemodel.prepare import preprocess

    config = BuildConfig(labels=[1, 2], workers=1, points=points)
    prepared, rejected = preprocess(paths, config)
    if rejected:
        raise RuntimeError(f"rejected: {[r.name for r in rejected]}")
    state, (fixed, integrated), _, _ = pipeline_state(prepared, config)
    return state, fixed, integrated


def run_job(job: dict, budget: float, max_wall: float, objective: str, points: int,
            path: str) -> dict:
    """Optimise one training set with one strategy for ``budget`` CPU seconds; write its trace."""
    from mdlshapemodel.prepare import io
    from mdlshapemodel.config import OptimisationSettings
    from mdlshapemodel.correspondence.strategies import optimise
    from mdlshapemodel.correspondence.trace import Trace
    from mdlshapemodel.errors import Cancelled

    state, fixed, integrated = initial_state(job["cases"], points)
    chosen = integrated if objective == "integrated" else fixed
    # A single phase on the chosen objective (optimise's second phase), no convergence test, a row
    # for every improvement; the CPU budget is enforced through the progress callback (called
    # after every example, or every 100 simplex evaluations), the wall-clock cap by the library.
    settings = OptimisationSettings(strategy=job["strategy"], max_time=max_wall,
                                    fixed_fraction=0.0, tolerance=0.0, patience=10 ** 9,
                                    max_sweeps=10 ** 9, trace_improvements=True)
    trace = Trace()

    def out_of_cpu(fraction, message):
        if time.process_time() - trace.start_cpu > budget:
            raise Cancelled

    try:
        optimise(state, (fixed, chosen), settings, np.random.default_rng(job["seed"]), trace,
                 progress=out_of_cpu)
        # back before the budget: the wall-clock cap, or fast's own end (after its finest level)
        capped = trace.last.wall_seconds >= max_wall
        stopped = "wall-clock cap" if capped else "converged"
    except Cancelled:
        stopped = "CPU budget"
    io.write_csv(path, Trace.HEADER, trace.rows)
    info = {**job, "budget": budget, "objective": objective, "points": state.n_points,
            "stopped": stopped, "initial": trace.rows[0].objective, "final": trace.last.objective,
            "cpu_seconds": trace.last.cpu_seconds, "wall_seconds": trace.last.wall_seconds,
            "evaluations": trace.last.evaluations, "rows": len(trace.rows)}
    Path(path).with_suffix(".json").write_text(json.dumps(info, indent=1))
    return info


def run_all(jobs: list, args, output: Path):
    todo = [j for j in jobs if args.rerun or not trace_path(output, j).exists()]
    print(f"{len(jobs) - len(todo)} of {len(jobs)} runs already done; running {len(todo)} "
          f"x {args.budget:g} s on {args.jobs} process(es)", flush=True)
    (output / "traces").mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    with concurrent.futures.ProcessPoolExecutor(max_workers=args.jobs,
                                                max_tasks_per_child=1) as executor:
        futures = {executor.submit(run_job, job, args.budget, args.max_wall or 10 * args.budget,
                                   args.objective, args.points, str(trace_path(output, job))): job
                   for job in todo}
        for future in concurrent.futures.as_completed(futures):
            job = futures[future]
            try:
                info = future.result()
            except Exception as error:  # keep the other runs going; report at the end
                print(f"FAILED {job['strategy']} n_s={job['n_s']} trial {job['trial']}: "
                      f"{error!r}", flush=True)
                continue
            print(f"{time.perf_counter() - started:7.0f} s  {job['strategy']:>19} "
                  f"n_s={job['n_s']:<3} trial {job['trial']}: F {info['initial']:.1f} -> "
                  f"{info['final']:.1f} in {info['cpu_seconds']:.0f} CPU s, "
                  f"{info['evaluations']} evaluations, {info['rows']} trace rows", flush=True)


# ---------------------------------------------------------------------------------------------
# analysis


def curves(output: Path, jobs: list, time_column: str, phase: str) -> dict:
    """``{strategy: {n_s: [(times, F), ...]}}`` of the stored traces (missing runs skipped).

    Times count from the run's first row (the start of the phase): eq. (19) scales time about 0.
    """
    from mdlshapemodel.model.convergence import read_trace

    runs: dict = {}
    for job in jobs:
        path = trace_path(output, job)
        if path.exists():
            times, values = read_trace(path, time_column, phase)
            runs.setdefault(job["strategy"], {}).setdefault(job["n_s"], []).append(
                (times - times[0], values))
    return runs


def analyse(output: Path, plan: dict, n_bootstrap: int, n_grid: int, spacing: str) -> dict:
    """alpha of every strategy and n_s against the reference, and d alpha / d n_s, per time."""
    from mdlshapemodel.model.convergence import scaling_study

    jobs, args = plan["jobs"], plan["args"]
    results = {}
    for time_column, _ in TIMES:
        runs = curves(output, jobs, time_column, args["objective"])
        if REFERENCE not in runs:
            raise SystemExit(f"no {REFERENCE} traces in {output}: nothing to compare with")
        smallest = min(runs[REFERENCE])
        reference = runs[REFERENCE][smallest]
        compared = {s: runs[s] for s in ANALYSED if s in runs}
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", RuntimeWarning)
            study = scaling_study(reference, compared, n_bootstrap=n_bootstrap, rng=args["seed"],
                                  spacing=spacing, n_grid=n_grid, bounds=BOUNDS, hold_last=True)
        results[time_column] = {
            "reference": {"strategy": REFERENCE, "n_s": smallest, "trials": len(reference)},
            "grid": {"spacing": spacing, "points": n_grid, "bootstrap": n_bootstrap},
            "fits_at_a_bound": sum("end of the search range" in str(w.message) for w in caught),
            "strategies": {s: {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                               for k, v in entry.items()} for s, entry in study.items()},
            "trials": {s: {str(n): len(t) for n, t in sorted(by_size.items())}
                       for s, by_size in runs.items()}}
    return results


def run_summary(output: Path, jobs: list) -> dict:
    """Per strategy and n_s: mean initial and final F, CPU seconds and evaluations of the runs,
    then how many runs converged, how many the wall-clock cap cut, and how many there are."""
    infos: dict = {}
    for job in jobs:
        info_file = trace_path(output, job).with_suffix(".json")
        if info_file.exists():
            infos.setdefault(job["strategy"], {}).setdefault(str(job["n_s"]), []).append(
                json.loads(info_file.read_text()))
    summary: dict = {}
    for strategy, by_size in infos.items():
        for n, runs in by_size.items():
            means = np.mean([[info[k] for k in ("initial", "final", "cpu_seconds", "evaluations")]
                             for info in runs], axis=0).tolist()
            # "stopped": "CPU budget", "converged" or "wall-clock cap" (run_job)
            counts = [sum(info["stopped"] == end for info in runs)
                      for end in ("converged", "wall-clock cap")]
            summary.setdefault(strategy, {})[n] = means + counts + [len(runs)]
    return summary


def table(results: dict, summary: dict, plan: dict) -> str:
    args = plan["args"]
    cpu, evaluations = results["cpu_seconds"], results["evaluations"]
    ref = cpu["reference"]
    curves = plan["args"].get("curves", False)
    paper_table, which = (PAPER_TABLE_II, "2-D") if curves else (PAPER_TABLE_III, "3-D")
    lines = [f"Gradient of alpha against n_s (cf. Table {'II' if curves else 'III'}); "
             f"reference: {ref['strategy']} at "
             f"n_s = {ref['n_s']} ({ref['trials']} trials); alpha > 1 = slower than the reference",
             f"budget {args['budget']:g} CPU s per run, "
             f"n_p = {args['points'] or 'the default'}, objective: "
             f"eq. {14 if args['objective'] == 'integrated' else 13} only, "
             f"{args['trials']} trials per n_s, {cpu['grid']['bootstrap']} bootstrap resamples, "
             f"{cpu['grid']['spacing']} time grid of {cpu['grid']['points']} points",
             "",
             f"{'strategy':<26}{'CPU time':>20}{'evaluations':>20}   paper {which} (CPU / eval.)"]
    for s in ANALYSED:
        if s not in cpu["strategies"]:
            continue
        a, b = cpu["strategies"][s], evaluations["strategies"][s]
        paper = "%g / %g" % paper_table[s] if s in paper_table else "-"
        lines.append(f"{LABELS[s]:<26}{a['gradient']:>11.3f} +- {a['gradient_se']:<6.3f}"
                     f"{b['gradient']:>11.3f} +- {b['gradient_se']:<6.3f}   {paper}")
    for time_column, title in TIMES:
        part = results[time_column]
        sizes = sorted({int(n) for s in part["strategies"].values() for n in s["n_shapes"]})
        lines += ["", f"alpha (+- SE), time = {title}" +
                  (f"; {part['fits_at_a_bound']} fits at a bound of {BOUNDS}"
                   if part["fits_at_a_bound"] else ""),
                  f"{'strategy':<26}" + "".join(f"{'n_s = ' + str(n):>20}" for n in sizes)]
        for s, entry in part["strategies"].items():
            cells = {int(n): f"{al:.3g} +- {se:.2g}" for n, al, se in
                     zip(entry["n_shapes"], entry["alpha"], entry["alpha_se"])}
            lines.append(f"{LABELS[s]:<26}" + "".join(f"{cells.get(n, '-'):>20}" for n in sizes))
    lines += ["", "runs (means over trials): F initial -> final, CPU s, evaluations; runs that "
              "converged before the budget (held at their final F)"]
    for s, by_size in summary.items():
        for n, (first, last, seconds, count, converged, capped, runs) in sorted(
                by_size.items(), key=lambda x: int(x[0])):
            lines.append(f"{LABELS.get(s, s):<26} n_s = {n:<3} F {first:9.1f} -> {last:9.1f} "
                         f"({100 * (first - last) / abs(first):4.1f} %), {seconds:5.1f} s, "
                         f"{count:8.0f} evaluations, {converged} of {runs} converged"
                         + (f", {capped} cut by the wall-clock cap" if capped else ""))
    return "\n".join(lines)


def write_results(output: Path, results: dict, summary: dict, text: str):
    (output / "results.json").write_text(json.dumps({"analysis": results, "runs": summary},
                                                    indent=1))
    rows = []
    for time_column, part in results.items():
        for s, entry in part["strategies"].items():
            for n, al, se, a, b in zip(entry["n_shapes"], entry["alpha"], entry["alpha_se"],
                                       entry["a"], entry["b"]):
                rows.append((time_column, s, int(n), al, se, a, b))
    with open(output / "alphas.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(("time", "strategy", "n_s", "alpha", "alpha_se", "a", "b"))
        writer.writerows(rows)
    (output / "table.txt").write_text(text + "\n")


def main(argv=None) -> int:
    args = parse_args(argv)
    output = Path(args.output)
    plan_file = output / "plan.json"
    if args.analyse_only:
        if not plan_file.exists():
            print(f"no {plan_file}: run without --analyse-only first", file=sys.stderr)
            return 2
        plan = json.loads(plan_file.read_text())
    else:
        pool = usable_pool(Path(args.data), args.jobs, args.pattern)
        if not pool:
            print(f"no usable label maps in {args.data}", file=sys.stderr)
            return 2
        from mdlshapemodel.prepare.curve_io import is_curve_file

        jobs = plan_jobs(pool, args.sizes, args.trials, args.strategies, args.seed)
        plan = {"args": {**vars(args), "curves": is_curve_file(pool[0])}, "pool": pool,
                "jobs": jobs}
        if plan_file.exists():  # more strategies, sizes or trials for the same study
            plan = merged_plan(json.loads(plan_file.read_text()), plan)
        output.mkdir(parents=True, exist_ok=True)
        plan_file.write_text(json.dumps(plan, indent=1))
        run_all(jobs, args, output)
    results = analyse(output, plan, args.bootstrap, args.grid, args.spacing)
    summary = run_summary(output, plan["jobs"])
    text = table(results, summary, plan)
    write_results(output, results, summary, text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
