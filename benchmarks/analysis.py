"""The analysis measured: calibration under the null, power and localisation where an effect is
planted, and speed.

``null BUILD``: the build's cases split at random into two halves, many times; for each split
the per-point test with ``--permutations`` permutations. Prints the share of splits with any
point significant after family-wise correction and after FDR correction, with its standard
error (both should be alpha), for the normal and the vector displacement.

``plant LABELS --output DIR``: writes label maps in which a smooth inward push (Gaussian of
``--width`` mm, ``--amplitude`` mm deep) is planted in ``--planted`` of ``--cases`` cases
drawn at random (``--seed``; the files' order follows the source's cohorts, which differ in
shape), ``--width`` being the Gaussian's sigma, at one anatomical place: the tip of the hippocampal head (the label-1 voxel farthest from
the centroid of label 2). Every case, pushed or not, goes through the same steps: the signed
distance of its union of labels, resampled to ``--spacing`` mm (linear), pushed (or not) and
thresholded a little less than half an original voxel out (where the Maurer distance puts the
boundary).
``DIR/planted.json`` records each case's push centre (LPS mm) and group. ``--rescans``: two
scans per case instead (``<case>_pre``, ``<case>_post``), each resampled on a grid moved by a
random offset of up to half an original voxel (a rescan's voxelisation), the push in the post
scan of the planted cases only; ``groups.csv`` then has ``case,id,visit,arm`` (arm ``changed``
or ``stable``) for ``analyze --subject id --time visit``.

``power DIR BUILD [BUILD ...]``: builds of the planted label maps (for example the default MDL
build, ``--strategy none`` and ``--correspondence cpd``), each analysed with the planted and the
unpushed cases as groups, subsets of ``--group-sizes`` cases per group. Where the push is on the
model: each point's mean distance from the planted cases' push centres; a significant point is
"at the push" within 2 widths plus the amplitude of it, "far" from 20 mm on. Prints, per build,
displacement and group size: significant points at the push and far from it, the power (the
share of subsets with any significant point at the push), the share with any far point, and the
median distance of the significant points from the push.

``paired DIR BUILD``: a build of ``plant --rescans`` label maps analysed as repeated measures
(the mean change, and the change compared between the changed and the stable arm, two-sided
and inward) and, ignoring the pairing, the post scans by arm (cross-sectional) and the post
against the pre scans (unpaired): family-wise significant points at the push and far from it.

``superimpose BUILD``: least-squares against resistant superimposition (``analyze
--superimposition``) with the change planted on the build's corresponded shapes, so that the
correspondence is the same and only the alignment differs: a ``--amplitude`` mm Gaussian
(sigma ``--width`` mm) at the tip of the hippocampal head (the end of the mean's long axis
where it is wider), pushed inward along each case's normals (a dent) or back along the case's
long axis (a retraction: the tip retracts, its sides slide), in a random half of the cases.
Per change, group size and superimposition: family-wise significant points at the change and
far from it (as ``power``), the normal difference at the change and the group difference that
the change made far from it by moving the poses; then the null (random half splits of the
unchanged cases). The alignment is done once per analysis on all its cases, before and
without the labels, so the permutations stay valid. ``--tfce``: each analysis also with
threshold-free cluster enhancement (``analyze --tfce``; the same resamples), a row per way of
correcting: the share of the change's points significant beside the counts, and in the null the
share of splits with any point significant by TFCE.

``speed BUILD``: the wall time of 10,000 permutations on the build's points.

Examples::

    mdlshapemodel build ../shared/data/hippocampus/labels -o /tmp/hip --label 1,2
    python benchmarks/analysis.py null /tmp/hip --splits 200
    python benchmarks/analysis.py plant ../shared/data/hippocampus/labels --output /tmp/plant2 \\
        --amplitude 2
    mdlshapemodel build /tmp/plant2/labels -o /tmp/plant2/mdl
    mdlshapemodel build /tmp/plant2/labels -o /tmp/plant2/none --strategy none
    mdlshapemodel build /tmp/plant2/labels -o /tmp/plant2/cpd --correspondence cpd
    python benchmarks/analysis.py power /tmp/plant2 /tmp/plant2/mdl /tmp/plant2/none \\
        /tmp/plant2/cpd
    python benchmarks/analysis.py superimpose /tmp/hip --group-sizes 10 20 41
    python benchmarks/analysis.py superimpose /tmp/hip --group-sizes 10 20 40 --tfce
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def _split_tests(shapes, weights, cells, labels, permutations, seed, displacement,
                 superimposition=None, variance_groups=None, tfce=False):
    from mdlshapemodel.analysis import align, permutation_test, vertex_normals
    from mdlshapemodel.analysis.tfce import surface_of
    from mdlshapemodel.config import AnalysisConfig

    aligned = align(shapes, weights,
                    superimposition=superimposition or AnalysisConfig.superimposition)
    mean = aligned.mean(axis=0)
    normals = vertex_normals(mean, cells)
    offsets = aligned - mean
    data = np.einsum("npd,pd->np", offsets, normals) if displacement == "normal" else offsets
    return permutation_test(data, labels[:, None].astype(float), permutations=permutations,
                            seed=seed, variance_groups=variance_groups,
                            surface=surface_of(mean, cells) if tfce else None)


def null(args):
    from mdlshapemodel.analysis import read_build

    built = read_build(args.build)
    rng = np.random.default_rng(args.seed)
    n = len(built.shapes)
    counts = {d: {"fwer": 0, "fdr": 0} for d in ("normal", "vector")}
    started = time.perf_counter()
    for split in range(args.splits):
        labels = rng.permutation(n) < n // 2
        for displacement in counts:
            result = _split_tests(built.shapes, built.model.weights, built.model.triangles,
                                  labels, args.permutations, int(rng.integers(1 << 30)),
                                  displacement)
            counts[displacement]["fwer"] += bool(np.any(result.p_fwer <= args.alpha))
            counts[displacement]["fdr"] += bool(np.any(result.q_fdr <= args.alpha))
    seconds = time.perf_counter() - started
    se = np.sqrt(args.alpha * (1 - args.alpha) / args.splits)
    print(f"{args.build}: {n} cases, {args.splits} random half splits, {args.permutations} "
          f"permutations each, alpha {args.alpha} (SE of a rate {se:.4f}); {seconds:.0f} s")
    print("displacement  any FWER-significant  any FDR-significant")
    for displacement, count in counts.items():
        print(f"{displacement:<12}  {count['fwer'] / args.splits:.3f}"
              f" ({(count['fwer'] / args.splits - args.alpha) / se:+.1f} SE)"
              f"       {count['fdr'] / args.splits:.3f}"
              f" ({(count['fdr'] / args.splits - args.alpha) / se:+.1f} SE)")


# where plant thresholds the resampled signed distance, in original voxels (see plant)
THRESHOLD = 0.45


def _push_centre(labels: np.ndarray, image) -> np.ndarray:
    """The tip of the head: the label-1 voxel farthest from the centroid of label 2 (LPS mm)."""
    head = np.argwhere(labels == 1)[:, ::-1].astype(float)      # (x, y, z) indices
    body = np.argwhere(labels == 2)[:, ::-1].astype(float)
    tip = head[np.argmax(np.linalg.norm(head - body.mean(axis=0), axis=1))]
    return np.array(image.TransformContinuousIndexToPhysicalPoint(tuple(tip)))


def _scan(image, distance, centre: np.ndarray, args, pushed: bool, offset=(0.0, 0.0, 0.0)):
    """One scan of a case: its signed distance resampled to ``args.spacing`` mm (moved by
    ``offset`` mm, so that a rescan falls on other voxels), pushed inward at ``centre`` or not,
    and thresholded."""
    import SimpleITK as sitk

    size = [int(np.ceil(s * sp / args.spacing)) for s, sp in zip(image.GetSize(),
                                                                   image.GetSpacing())]
    fine = sitk.Resample(distance, size, sitk.TranslationTransform(3, tuple(offset)),
                         sitk.sitkLinear, image.GetOrigin(), [args.spacing] * 3,
                         image.GetDirection(), 10.0, sitk.sitkFloat32)
    values = sitk.GetArrayFromImage(fine)
    if pushed:
        index = np.stack(np.meshgrid(*(np.arange(s) for s in size), indexing="ij"), -1)
        physical = (np.asarray(fine.GetOrigin()) + (index * args.spacing)
                    @ np.asarray(fine.GetDirection()).reshape(3, 3).T)
        # the resampled object is moved by -offset: so is the push centre
        push = args.amplitude * np.exp(-0.5 * np.sum((physical - centre + offset) ** 2,
                                                     axis=-1) / args.width ** 2)
        values = values + np.transpose(push, (2, 1, 0))   # inward: the object shrinks
    # the Maurer distance is 0 on the object's boundary voxels and 1 voxel outside them, so
    # the surface lies about half a voxel out; the threshold stays a little below that,
    # because linear interpolation puts many samples at exactly half (half-way between a
    # 0 and a 1), where a push of any size, however far away, would flip them all
    result = sitk.GetImageFromArray((values < THRESHOLD * min(image.GetSpacing()))
                                    .astype(np.uint8))
    result.CopyInformation(fine)
    return result


def plant(args):
    import SimpleITK as sitk

    files = sorted(Path(args.labels).glob("*.nii.gz"))[:args.cases]
    output = Path(args.output)
    (output / "labels").mkdir(parents=True, exist_ok=True)
    record = {"amplitude": args.amplitude, "width": args.width, "spacing": args.spacing,
              "seed": args.seed, "rescans": args.rescans, "cases": {}}
    # a random half: the files' order follows the source's cohorts, which differ in shape
    rng = np.random.default_rng(args.seed)
    chosen = set(rng.permutation(len(files))[:args.planted])
    rows = ["case,id,visit,arm"] if args.rescans else ["case,group"]
    for k, path in enumerate(files):
        image = sitk.ReadImage(str(path))
        labels = sitk.GetArrayFromImage(image)
        centre = _push_centre(labels, image)
        mask = sitk.Cast(image > 0, sitk.sitkUInt8)
        distance = sitk.SignedMaurerDistanceMap(mask, insideIsPositive=False,
                                                squaredDistance=False, useImageSpacing=True)
        planted = k in chosen
        name = path.name.split(".")[0]
        if not args.rescans:
            sitk.WriteImage(_scan(image, distance, centre, args, planted),
                            str(output / "labels" / f"{name}.nii.gz"))
            record["cases"][name] = {"planted": planted, "centre": centre.tolist()}
            rows.append(f"{name},{'pushed' if planted else 'plain'}")
            print(f"{name}: {'pushed' if planted else 'resampled'} at {np.round(centre, 1)}")
            continue
        # two scans of the subject, each moved by up to half an original voxel; the later one
        # pushed in the planted subjects
        for visit in ("pre", "post"):
            offset = rng.uniform(-0.5, 0.5, 3) * np.asarray(image.GetSpacing())
            pushed = planted and visit == "post"
            sitk.WriteImage(_scan(image, distance, centre, args, pushed, offset),
                            str(output / "labels" / f"{name}_{visit}.nii.gz"))
            record["cases"][f"{name}_{visit}"] = {"planted": pushed,
                                                  "centre": (centre - offset).tolist()}
            rows.append(f"{name}_{visit},{name},{visit},{'changed' if planted else 'stable'}")
        print(f"{name}: two scans{', the later pushed' if planted else ''}")
    (output / "planted.json").write_text(json.dumps(record, indent=2))
    (output / "groups.csv").write_text("\n".join(rows) + "\n")


def _distances(built, record) -> np.ndarray:
    """Per model point, its mean distance (mm) over the planted cases from their push centres:
    where on the model the push was."""
    from mdlshapemodel.prepare import io

    distances = []
    for name, case in record["cases"].items():
        if not case["planted"] or name not in built.model.names:
            continue
        points = io.read_mesh(io.case_file(built.folder / "correspondence", name))[0]
        distances.append(np.linalg.norm(points - np.asarray(case["centre"]), axis=1))
    return np.mean(distances, axis=0)


# a model point is "at the push" when its mean distance from the planted cases' push centres is
# at most NEAR widths plus the amplitude (the pushed surface lies that much deeper), "far" from
# FAR mm on
NEAR, FAR = 2.0, 20.0


def power(args):
    from mdlshapemodel.analysis import read_build

    record = json.loads((Path(args.planted) / "planted.json").read_text())
    print(f"planted: {record['amplitude']} mm inward, {record['width']} mm wide; "
          f"{args.permutations} permutations, alpha {args.alpha}, {args.subsets} subsets per "
          "group size")
    print("build        displacement  per group  at push  far   power  any far  median mm")
    for build in args.builds:
        built = read_build(build)
        distance = _distances(built, record)
        near = distance <= NEAR * record["width"] + record["amplitude"]
        far = distance >= FAR
        pushed = np.array([record["cases"][n]["planted"] for n in built.model.names])
        rng = np.random.default_rng(args.seed)
        for displacement in ("normal", "vector"):
            for size in args.group_sizes:
                at, beyond, spread, hits, false = [], [], [], 0, 0
                subsets = 1 if size >= min(pushed.sum(), (~pushed).sum()) else args.subsets
                for _ in range(subsets):
                    chosen = np.concatenate([
                        rng.choice(np.flatnonzero(pushed), size, replace=False),
                        rng.choice(np.flatnonzero(~pushed), size, replace=False)])
                    result = _split_tests(built.shapes[chosen], built.model.weights,
                                          built.model.triangles, pushed[chosen],
                                          args.permutations, int(rng.integers(1 << 30)),
                                          displacement)
                    significant = result.p_fwer <= args.alpha
                    at.append(int(np.sum(significant & near)))
                    beyond.append(int(np.sum(significant & far)))
                    spread.append(np.median(distance[significant]) if significant.any()
                                  else np.nan)
                    hits += bool(np.any(significant & near))
                    false += bool(np.any(significant & far))
                print(f"{Path(build).name:<12} {displacement:<12}  {size:>9}  "
                      f"{np.mean(at):7.1f}  {np.mean(beyond):5.1f}  {hits / subsets:5.2f}  "
                      f"{false / subsets:7.2f}  {np.nanmedian(spread):8.1f}")
        print(f"{Path(build).name:<12} ({int(near.sum())} points at the push, "
              f"{int(far.sum())} far from it)")


def paired(args):
    """The analyses of a ``plant --rescans`` build: paired designs against cross-sectional and
    unpaired ones, with the family-wise significant points at the push and far from it."""
    import csv
    import tempfile

    from mdlshapemodel.analysis import analyze_shapes, read_build, subjects
    from mdlshapemodel.config import AnalysisConfig

    folder = Path(args.planted)
    record = json.loads((folder / "planted.json").read_text())
    built = read_build(args.build)
    names = list(built.model.names)
    distance = _distances(built, record)
    near = distance <= NEAR * record["width"] + record["amplitude"]
    far = distance >= FAR
    table = folder / "groups.csv"
    with open(table, newline="") as handle:
        rows = list(csv.reader(handle))
    later = Path(tempfile.mkdtemp()) / "post.csv"
    later.write_text("\n".join(",".join(row) for row in rows
                                if row[0] == "case" or row[2] == "post") + "\n")
    repeated = {"subject": "id", "time": "visit", "baseline": "pre"}
    arm = {"group": "arm", "reference": "stable"}
    designs = [
        ("mean change (paired)", table, repeated),
        ("mean change (paired), inward", table, {**repeated, "tail": "less"}),
        ("post against pre (unpaired)", table, {"group": "visit", "reference": "pre"}),
        ("post against pre (unpaired), inward", table,
         {"group": "visit", "reference": "pre", "tail": "less"}),
    ]
    if len({row[3] for row in rows[1:]}) == 2:            # a changed and a stable arm
        designs += [
            ("change by arm (paired)", table, {**repeated, **arm}),
            ("change by arm (paired), inward", table, {**repeated, **arm, "tail": "less"}),
            ("change by arm (paired), pooled", table, {**repeated, **arm, "variance": "pooled"}),
            ("post scans by arm (cross-sectional)", later, arm),
            ("post scans by arm (cross-sectional), pooled", later,
             {**arm, "variance": "pooled"}),
        ]
    print(f"{record['amplitude']} mm inward push, {record['width']} mm wide, in the post scans of "
          f"{sum(c['planted'] for c in record['cases'].values())} subjects; {len(names)} scans; "
          f"{int(near.sum())} points at the push, {int(far.sum())} far; {args.permutations} "
          f"resamples, alpha {args.alpha}")
    print("| design | statistic, resampling | at push | far | smallest p_fwer at push |")
    print("|---|---|---|---|---|")
    for label, path, settings in designs:
        keys = ("group", "reference", "subject", "time", "baseline")
        design = subjects(path, names, **{k: v for k, v in settings.items() if k in keys})
        config = AnalysisConfig(**settings, permutations=args.permutations, seed=args.seed,
                                superimposition=args.superimposition)
        found = analyze_shapes(built.model, built.shapes, design, config).points
        significant = found.p_fwer <= args.alpha
        print(f"| {label} | {found.name}, {found.resampling} | {int(np.sum(significant & near))}"
              f" | {int(np.sum(significant & far))} | {found.p_fwer[near].min():.4f} |",
              flush=True)


def _long_axis_tip(mean: np.ndarray) -> tuple[int, np.ndarray]:
    """The mean shape's point at the end of its long axis (first principal axis) where it is
    wider (the hippocampal head), and the axis pointing towards it."""
    centred = mean - mean.mean(axis=0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    along = centred @ axis
    radial = np.linalg.norm(centred - np.outer(along, axis), axis=1)
    ends = [along >= along.max() - 10, along <= along.min() + 10]
    if radial[ends[1]].mean() > radial[ends[0]].mean():
        axis, along = -axis, -along
    return int(np.argmax(along)), axis


def _planted(shapes, cells, tip, axis_of_mean, kind, amplitude, width):
    """Copies of shapes (n, p, 3) changed at point ``tip``: ``dent``, a Gaussian push inward
    along each case's own normals; ``retraction``, the same Gaussian moving the points back
    along the case's long axis (the tip retracts, its sides slide)."""
    from mdlshapemodel.analysis import vertex_normals

    changed = shapes.copy()
    for i, shape in enumerate(shapes):
        gauss = amplitude * np.exp(-0.5 * np.sum((shape - shape[tip]) ** 2, axis=1) / width ** 2)
        if kind == "dent":
            direction = vertex_normals(shape, cells)
        else:
            centred = shape - shape.mean(axis=0)
            axis = np.linalg.svd(centred, full_matrices=False)[2][0]
            direction = np.broadcast_to(axis if axis @ (shape[tip] - shape.mean(axis=0)) > 0
                                        else -axis, shape.shape)
        changed[i] = shape - gauss[:, None] * direction
    return changed


def superimpose(args):
    """Least-squares against resistant superimposition, effects planted on a build's
    corresponded shapes (so that only the alignment differs): at the change and far from it,
    and under the null."""
    from mdlshapemodel.analysis import align, read_build

    built = read_build(args.build)
    shapes, cells, weights = built.shapes, built.model.triangles, built.model.weights
    n = len(shapes)
    mean = align(shapes, weights, superimposition="least-squares").mean(axis=0)
    tip, _ = _long_axis_tip(mean)
    # per point, its mean distance over the cases from their tip
    distance = np.mean(np.linalg.norm(shapes - shapes[:, tip:tip + 1], axis=2), axis=0)
    near = distance <= NEAR * args.width + args.amplitude
    far = distance >= FAR
    methods = ("least-squares", "resistant")
    rng = np.random.default_rng(args.seed)
    print(f"{args.build}: {n} cases, {len(mean)} points; {args.amplitude} mm, Gaussian sigma "
          f"{args.width} mm at the head's tip (point {tip}); {int(near.sum())} points at the "
          f"change, {int(far.sum())} >= {FAR:.0f} mm from it; {args.permutations} permutations, "
          f"Welch's v (variance groups), alpha {args.alpha}, {args.subsets} subsets per size")
    corrections = ("maximum", "TFCE") if args.tfce else ("maximum",)
    print("| change | per group | superimposition | family-wise | at change | share at change "
          "| far | power | any far | normal difference at change (mm) | difference made far "
          "from it (mm) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for kind in ("dent", "retraction"):
        planted = np.zeros(n, bool)
        planted[rng.permutation(n)[:n // 2]] = True
        changed = np.where(planted[:, None, None],
                           _planted(shapes, cells, tip, None, kind, args.amplitude,
                                    args.width), shapes)
        for size in args.group_sizes:
            subsets = 1 if size >= min(planted.sum(), (~planted).sum()) else args.subsets
            chosen = [np.concatenate([rng.choice(np.flatnonzero(planted), size, replace=False),
                                      rng.choice(np.flatnonzero(~planted), size,
                                                 replace=False)])
                      for _ in range(subsets)]
            seeds = rng.integers(1 << 30, size=subsets)
            for method in methods:
                found = {c: {"at": [], "far": [], "hits": 0, "false": 0} for c in corrections}
                shift_at, shift_far = [], []
                for rows, seed in zip(chosen, seeds):
                    labels = planted[rows]
                    result = _split_tests(changed[rows], weights, cells, labels,
                                          args.permutations, int(seed), "normal", method,
                                          labels.astype(int), args.tfce)
                    for correction, counts in found.items():
                        significant = (result.p_fwer if correction == "maximum" else
                                       result.tfce_p_fwer) <= args.alpha
                        counts["at"].append(int(np.sum(significant & near)))
                        counts["far"].append(int(np.sum(significant & far)))
                        counts["hits"] += bool(np.any(significant & near))
                        counts["false"] += bool(np.any(significant & far))
                    normal, moved = _moved(changed[rows], shapes[rows], weights, cells, labels,
                                           method)
                    shift_at.append(normal[near].mean())
                    shift_far.append(moved[far].mean())
                for correction, counts in found.items():
                    print(f"| {kind} | {size} | {method} | {correction} | "
                          f"{np.mean(counts['at']):.1f} | {np.mean(counts['at']) / near.sum():.2f}"
                          f" | {np.mean(counts['far']):.1f} | {counts['hits'] / subsets:.2f} | "
                          f"{counts['false'] / subsets:.2f} | {np.mean(shift_at):+.2f} | "
                          f"{np.mean(shift_far):.3f} |", flush=True)
    se = np.sqrt(args.alpha * (1 - args.alpha) / args.splits)
    print(f"\nnull: {args.splits} random half splits of the unchanged cases (SE of a rate "
          f"{se:.4f})")
    print("| superimposition | any FWER-significant | any FDR-significant"
          + (" | any TFCE FWER-significant |" if args.tfce else " |"))
    print("|---|---|---|" + ("---|" if args.tfce else ""))
    splits = [rng.permutation(n) < n // 2 for _ in range(args.splits)]
    seeds = rng.integers(1 << 30, size=args.splits)

    def rate(count: int) -> str:
        return f"{count / args.splits:.3f} ({(count / args.splits - args.alpha) / se:+.1f} SE)"

    for method in methods:
        fwer = fdr = enhanced = 0
        for labels, seed in zip(splits, seeds):
            result = _split_tests(shapes, weights, cells, labels, args.permutations, int(seed),
                                  "normal", method, labels.astype(int), args.tfce)
            fwer += bool(np.any(result.p_fwer <= args.alpha))
            fdr += bool(np.any(result.q_fdr <= args.alpha))
            enhanced += args.tfce and bool(np.any(result.tfce_p_fwer <= args.alpha))
        print(f"| {method} | {rate(fwer)} | {rate(fdr)} |"
              + (f" {rate(enhanced)} |" if args.tfce else ""), flush=True)


def _moved(changed, unchanged, weights, cells, labels, method):
    """The planted minus the unchanged cases' mean displacement along the mean's normals, and
    per point the group difference the change made by moving the aligned points (the planted
    minus the unchanged cases' mean movement from the same cases aligned without the change,
    its norm, mm): away from the change, all of it is the superimposition's doing."""
    from mdlshapemodel.analysis import align, vertex_normals

    aligned = align(changed, weights, superimposition=method)
    reference = align(unchanged, weights, superimposition=method)
    mean = aligned.mean(axis=0)
    normal = np.einsum("npd,pd->np", aligned - mean, vertex_normals(mean, cells))
    moved = aligned - reference
    moved = np.linalg.norm(moved[labels].mean(axis=0) - moved[~labels].mean(axis=0), axis=1)
    return normal[labels].mean(axis=0) - normal[~labels].mean(axis=0), moved


def speed(args):
    from mdlshapemodel.analysis import permutation_test, read_build

    built = read_build(args.build)
    labels = (np.arange(len(built.shapes)) < len(built.shapes) // 2).astype(float)[:, None]
    offsets = built.shapes - built.shapes.mean(axis=0)
    for name, data in (("normal", offsets[..., 0]), ("vector", offsets)):
        started = time.perf_counter()
        permutation_test(data, labels, permutations=args.permutations)
        print(f"{name}: {len(built.shapes)} cases x {data.shape[1]} points x "
              f"{args.permutations} permutations: {time.perf_counter() - started:.2f} s")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    p = commands.add_parser("null")
    p.add_argument("build")
    p.add_argument("--splits", type=int, default=200)
    p.add_argument("--permutations", type=int, default=1000)
    p.add_argument("--alpha", type=float, default=0.05)
    p.add_argument("--seed", type=int, default=0)
    p = commands.add_parser("plant")
    p.add_argument("labels")
    p.add_argument("--output", required=True)
    p.add_argument("--cases", type=int, default=80)
    p.add_argument("--planted", type=int, default=40)
    p.add_argument("--amplitude", type=float, default=2.0)
    p.add_argument("--width", type=float, default=4.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--spacing", type=float, default=0.5)
    p.add_argument("--rescans", action="store_true",
                   help="two scans per case (pre, post), each on a grid moved by up to half "
                        "a voxel; the post scan pushed in the planted cases")
    p = commands.add_parser("power")
    p.add_argument("planted")
    p.add_argument("builds", nargs="+")
    p.add_argument("--group-sizes", type=int, nargs="+", default=[10, 20, 40])
    p.add_argument("--subsets", type=int, default=10)
    p.add_argument("--permutations", type=int, default=1000)
    p.add_argument("--alpha", type=float, default=0.05)
    p.add_argument("--seed", type=int, default=0)
    p = commands.add_parser("paired")
    p.add_argument("planted")
    p.add_argument("build")
    p.add_argument("--permutations", type=int, default=9999)
    p.add_argument("--alpha", type=float, default=0.05)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--superimposition", default="resistant")
    p = commands.add_parser("superimpose")
    p.add_argument("build")
    p.add_argument("--amplitude", type=float, default=2.0)
    p.add_argument("--width", type=float, default=4.0)
    p.add_argument("--group-sizes", type=int, nargs="+", default=[10, 20, 40])
    p.add_argument("--subsets", type=int, default=5)
    p.add_argument("--splits", type=int, default=100)
    p.add_argument("--permutations", type=int, default=1000)
    p.add_argument("--alpha", type=float, default=0.05)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--tfce", action="store_true",
                   help="also threshold-free cluster enhancement: a row per correction")
    p = commands.add_parser("speed")
    p.add_argument("build")
    p.add_argument("--permutations", type=int, default=10_000)
    args = parser.parse_args()
    {"null": null, "plant": plant, "power": power, "paired": paired,
     "superimpose": superimpose, "speed": speed}[args.command](args)


if __name__ == "__main__":
    main()
