"""Correspondence measured against a ground truth: populations with known correspondence.

``make`` deforms one shared femur surface (or any closed mesh) by smooth random fields of low rank
(a few fixed modes, each case a random combination of them), adds a small per-case field and a
random rigid pose, and voxelises every case at ``--spacing`` mm, so that the tool sees only label
maps. Vertex k of every deformed mesh is the same anatomical point: the ground truth.

``template`` is a reference correspondence: the template's points rigidly aligned to each case's
surface (ICP, VTK) and projected to the closest surface point.

``floor`` is the true correspondence seen through the preprocessing: the same template points on
every true mesh, projected onto the case's prepared surface; its error is the noise floor that
voxelisation and surface extraction set for any method.

``from-truth`` separates the objective from the optimiser: the default optimisation started at the
truth (on the true meshes, one shared triangulation and sphere map), and from the sphere maps as a
build aligns them; where each ends, in error and in F.

``evaluate`` measures the correspondence of build outputs (and of ``template`` outputs): each
corresponded point is located on its case's true mesh (closest point, barycentric coordinates),
carried to the undeformed template through the known correspondence, and the spread of each
point's carried copies about their mean is reported (mean and 95th percentile, mm).

All of it in one command (builds that exist are kept):

    python benchmarks/ground_truth.py run --cases 30 --spacing 0.5 --output /tmp/gt-femur

or step by step:

    python benchmarks/ground_truth.py make --cases 30 --spacing 0.5 --output /tmp/gt-femur
    mdlshapemodel build /tmp/gt-femur/labels -o /tmp/gt-femur/mdl
    mdlshapemodel build /tmp/gt-femur/labels -o /tmp/gt-femur/initial --strategy none
    mdlshapemodel build /tmp/gt-femur/labels -o /tmp/gt-femur/cpd --correspondence cpd
    python benchmarks/ground_truth.py template /tmp/gt-femur --output /tmp/gt-femur/template
    python benchmarks/ground_truth.py floor /tmp/gt-femur --output /tmp/gt-femur/floor
    python benchmarks/ground_truth.py evaluate /tmp/gt-femur /tmp/gt-femur/floor \\
        /tmp/gt-femur/initial /tmp/gt-femur/cpd /tmp/gt-femur/template /tmp/gt-femur/mdl

``landmarks`` gives every case 22 landmarks at known places (template vertices) and splits them
into halves, for guided builds (``--landmarks /tmp/gt-femur/landmarks-even``):

    python benchmarks/ground_truth.py landmarks /tmp/gt-femur
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

FEMURS = Path(__file__).resolve().parents[2] / "shared" / "data" / "femurs"


def read_vtp_points(path) -> np.ndarray:
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    reader = vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    return vtk_to_numpy(reader.GetOutput().GetPoints().GetData()).astype(np.float64)


def gaussian_field(points: np.ndarray, centres: np.ndarray, weights: np.ndarray, width: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """u(x) = sum_j w_j exp(-|x - c_j|^2 / (2 s^2)) at ``points`` (n, 3) and its gradient
    du/dx (n, 3, 3)."""
    difference = points[:, None, :] - centres[None, :, :]
    g = np.exp(-np.sum(difference ** 2, axis=2) / (2.0 * width ** 2))       # (n, K)
    field = g @ weights
    gradient = -np.einsum("nk,kd,nke->nde", g, weights, difference) / width ** 2
    return field, gradient


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit normals at the vertices: the area-weighted sum of the adjacent faces' normals."""
    face_normals = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                            vertices[faces[:, 2]] - vertices[faces[:, 0]])
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_normals)
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def make(args):
    import SimpleITK as sitk

    from mdlshapemodel.geometry import rotation_from_vector
    from mdlshapemodel.prepare import io, surface

    output = Path(args.output)
    (output / "labels").mkdir(parents=True, exist_ok=True)
    (output / "meshes").mkdir(parents=True, exist_ok=True)
    vertices, faces = io.read_mesh(args.mesh)
    vertices, faces = surface.merge_close_vertices(vertices, faces)
    vertices, faces = surface.drop_degenerate_faces(vertices, faces)
    surface.require_sphere_like(vertices, faces)
    faces = surface.orient_outwards(vertices, faces)
    if len(vertices) > args.max_vertices:
        vertices, faces = surface.decimate(vertices, faces, args.max_vertices)
    vertices = vertices - vertices.mean(axis=0)
    size = float(np.sqrt(np.mean(np.sum(vertices ** 2, axis=1))))     # RMS radius, mm
    rng = np.random.default_rng(args.seed)
    width = args.width * size
    modes = []
    for m in range(args.modes):   # fixed smooth modes, each moving its largest point by amplitude
        centres = vertices[rng.choice(len(vertices), args.centres, replace=False)]
        weights = rng.normal(size=(args.centres, 3))
        field, _ = gaussian_field(vertices, centres, weights, width)
        scale = args.amplitude / (m + 1) / np.max(np.linalg.norm(field, axis=1))
        modes.append((centres, weights * scale))
    normals = vertex_normals(vertices, faces)
    io.write_polydata(output / "template.vtp", vertices, faces)
    truth = {"template": str(args.mesh), "rms_radius_mm": size, "spacing_mm": args.spacing,
             "offset_mm": list(args.offset), "normal_only": args.normal_only,
             "modes": args.modes, "amplitude_mm": args.amplitude, "cases": {}}
    started = time.perf_counter()
    for i in range(args.cases):
        name = f"case_{i:03d}"
        for attempt in range(20):   # redraw until the deformation is clearly invertible
            coefficients = np.clip(rng.normal(size=args.modes), -2.5, 2.5)
            field = np.zeros_like(vertices)
            gradient = np.zeros((len(vertices), 3, 3))
            for b, (centres, weights) in zip(coefficients, modes):
                f, g = gaussian_field(vertices, centres, b * weights, width)
                field += f
                gradient += g
            centres = vertices[rng.choice(len(vertices), args.centres, replace=False)]
            noise, noise_gradient = gaussian_field(
                vertices, centres, rng.normal(size=(args.centres, 3)), width / 2)
            factor = args.noise / max(np.max(np.linalg.norm(noise, axis=1)), 1e-12)
            noise, noise_gradient = noise * factor, noise_gradient * factor
            jacobian = np.linalg.det(np.eye(3) + gradient + noise_gradient)
            if jacobian.min() > 0.5:
                break
        displacement = field + noise
        along_normal = np.einsum("ij,ij->i", displacement, normals)
        tangential = displacement - along_normal[:, None] * normals
        if args.normal_only:      # only what changes the surface: no sliding along it
            displacement, tangential = along_normal[:, None] * normals, 0.0 * tangential
        pose = rotation_from_vector(rng.normal(size=3) * np.radians(args.rotation) / np.sqrt(3))
        shift = rng.normal(size=3) * args.translation
        deformed = (vertices + displacement) @ pose.T + shift + np.asarray(args.offset)
        io.write_polydata(output / "meshes" / f"{name}.vtp", deformed, faces)
        mask, origin = surface.mesh_to_mask(deformed, faces, args.spacing)
        image = sitk.GetImageFromArray(mask)
        image.SetSpacing((args.spacing,) * 3)
        image.SetOrigin(tuple(float(o) for o in origin))
        sitk.WriteImage(image, str(output / "labels" / f"{name}.nii.gz"), useCompression=True)
        truth["cases"][name] = {"coefficients": coefficients.tolist(),
                                "min_jacobian": float(jacobian.min()),
                                "rms_normal_mm": float(np.sqrt(np.mean(along_normal ** 2))),
                                "rms_tangential_mm": float(np.sqrt(np.mean(
                                    np.sum(tangential ** 2, axis=1)))),
                                "voxels": list(mask.shape[::-1])}
        print(f"{name}: {mask.shape[::-1]} voxels, min Jacobian {jacobian.min():.2f}, "
              f"displacement RMS {truth['cases'][name]['rms_normal_mm']:.2f} mm along the "
              f"normals, {truth['cases'][name]['rms_tangential_mm']:.2f} mm along the surface")
    (output / "truth.json").write_text(json.dumps(truth, indent=2))
    print(f"{args.cases} cases in {time.perf_counter() - started:.0f} s, {len(vertices)} vertices, "
          f"RMS radius {size:.1f} mm -> {output}")


def located_on_template(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                        template: np.ndarray) -> np.ndarray:
    """Each point's closest point on the mesh (vertices, faces), carried to the same barycentric
    coordinates of the same triangle of ``template`` (the mesh's undeformed vertices; or any
    mesh with the same triangles, e.g. carrying template points to a case)."""
    from mdlshapemodel.prepare.surface import SurfaceDistance

    closest, _, face = SurfaceDistance(vertices, faces).closest(points)
    a, b, c = (vertices[faces[face, k]] for k in range(3))
    v0, v1, v2 = b - a, c - a, closest - a
    d00, d01, d11 = (np.einsum("ij,ij->i", x, y) for x, y in ((v0, v0), (v0, v1), (v1, v1)))
    d20, d21 = np.einsum("ij,ij->i", v2, v0), np.einsum("ij,ij->i", v2, v1)
    denominator = d00 * d11 - d01 ** 2
    beta = (d11 * d20 - d01 * d21) / denominator
    gamma = (d00 * d21 - d01 * d20) / denominator
    alpha = 1.0 - beta - gamma
    t = template[faces[face]]
    return alpha[:, None] * t[:, 0] + beta[:, None] * t[:, 1] + gamma[:, None] * t[:, 2]


def correspondence_error(truth_folder: Path, build: Path, cases: list) -> dict:
    """Mean and 95th percentile (mm) of the distance of each point's copies, carried to the
    template, from their mean, over ``cases``."""
    from mdlshapemodel.prepare import io

    from mdlshapemodel.prepare.surface import point_surface_distances

    template, faces = io.read_mesh(truth_folder / "template.vtp")
    carried, distances = [], []
    for name in cases:
        path = build / "correspondence" / f"{name}.vtp"
        vertices, _ = io.read_mesh(truth_folder / "meshes" / path.name)
        carried.append(located_on_template(read_vtp_points(path), vertices, faces, template))
        distances.append(point_surface_distances(read_vtp_points(path), vertices, faces))
    carried = np.stack(carried)                           # (n_s, n_p, 3)
    spread = np.linalg.norm(carried - carried.mean(axis=0), axis=2)
    return {"cases": len(carried), "points": carried.shape[1], "mean_mm": float(spread.mean()),
            "p95_mm": float(np.percentile(spread, 95)),
            "fidelity_mm": float(np.mean(np.concatenate(distances)))}


def evaluate(args):
    """The error of every build on the cases that all of them hold (a build rejects some)."""
    truth = Path(args.truth)
    held = [{p.stem for p in (Path(b) / "correspondence").glob("*.vtp")} for b in args.builds]
    cases = sorted(set.intersection(*held))
    print(f"{len(cases)} cases held by every build (of {len(set.union(*held))})")
    spacing = json.loads((truth / "truth.json").read_text())["spacing_mm"]
    print("error: spread of each point's copies carried to the template (mm); fidelity: mean "
          f"distance of the corresponded points from the true surface (mm; voxel {spacing} mm)")
    print(f"{'correspondence':<28} {'cases':>5} {'points':>6} {'mean mm':>8} {'p95 mm':>8} "
          f"{'fidelity':>8}")
    for build in args.builds:
        result = correspondence_error(truth, Path(build), cases)
        print(f"{Path(build).name:<28} {result['cases']:>5} {result['points']:>6} "
              f"{result['mean_mm']:>8.3f} {result['p95_mm']:>8.3f} {result['fidelity_mm']:>8.3f}")


def prepared_surfaces(truth: Path):
    """Each case's name and surface as the tool makes it from the label map (no sphere map);
    rejected cases are printed and skipped."""
    from mdlshapemodel import BuildConfig, MDLShapeModelError
    from mdlshapemodel.prepare import io
    from mdlshapemodel.prepare.case import surface_of_mask

    config = BuildConfig()
    for path in sorted((truth / "labels").glob("*.nii.gz")):
        try:
            label_map = io.read_label_map(path, config.labels)
            vertices, faces, _, _ = surface_of_mask(
                label_map.mask, label_map.spacing, label_map.origin, label_map.direction, config)
        except MDLShapeModelError as error:
            print(f"{path.name}: rejected ({error})")
            continue
        yield io.case_name(path), vertices, faces


def template_points(truth: Path, count: int) -> tuple[np.ndarray, np.ndarray]:
    """A fixed random subset of the template's vertices: their indices and positions."""
    from mdlshapemodel.prepare import io

    template, _ = io.read_mesh(truth / "template.vtp")
    chosen = np.random.default_rng(0).choice(len(template), min(count, len(template)),
                                             replace=False)
    return chosen, template[chosen]


def write_landmarks(args):
    """Landmarks with a known place: ``--count`` template vertices spread by farthest-point
    sampling (from the top of the template), each case's landmark its true mesh's same vertex,
    as CSV files ``label,x,y,z`` in ``landmarks-all``, and every other label in
    ``landmarks-even`` and ``landmarks-odd`` (half the labels as guides, the other half held
    out)."""
    truth = Path(args.truth)
    template = read_vtp_points(truth / "template.vtp")
    chosen = [int(np.argmax(template[:, 2]))]
    distance = np.linalg.norm(template - template[chosen[0]], axis=1)
    while len(chosen) < args.count:
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(template - template[chosen[-1]], axis=1))
    labels = [f"L{k:02d}" for k in range(args.count)]
    halves = {"all": range(args.count), "even": range(0, args.count, 2),
              "odd": range(1, args.count, 2)}
    for name, picked in halves.items():
        folder = truth / f"landmarks-{name}"
        folder.mkdir(exist_ok=True)
        for mesh in sorted((truth / "meshes").glob("*.vtp")):
            points = read_vtp_points(mesh)
            rows = [f"{labels[k]},{points[chosen[k]][0]:.4f},{points[chosen[k]][1]:.4f},"
                    f"{points[chosen[k]][2]:.4f}" for k in picked]
            (folder / f"{mesh.stem}.csv").write_text("label,x,y,z\n" + "\n".join(rows) + "\n")
    print(f"{args.count} landmarks per case -> {truth}/landmarks-all, -even, -odd")


def template_reference(args):
    """The template's points rigidly aligned (ICP) to each case's prepared surface and projected
    to its closest points."""
    import vtk

    from mdlshapemodel.prepare import io
    from mdlshapemodel.prepare.surface import SurfaceDistance, arrays_to_polydata

    truth, output = Path(args.truth), Path(args.output)
    (output / "correspondence").mkdir(parents=True, exist_ok=True)
    _, points = template_points(truth, args.points)
    for name, target, target_faces in prepared_surfaces(truth):
        source = points - points.mean(axis=0) + target.mean(axis=0)
        icp = vtk.vtkIterativeClosestPointTransform()
        icp.SetSource(arrays_to_polydata(source))
        icp.SetTarget(arrays_to_polydata(target, target_faces))
        icp.GetLandmarkTransform().SetModeToRigidBody()
        icp.SetMaximumNumberOfIterations(200)
        icp.SetMaximumNumberOfLandmarks(len(source))
        icp.StartByMatchingCentroidsOn()
        icp.Update()
        matrix = np.array([[icp.GetMatrix().GetElement(r, c) for c in range(4)] for r in range(4)])
        aligned = source @ matrix[:3, :3].T + matrix[:3, 3]
        projected = SurfaceDistance(target, target_faces).closest(aligned)[0]
        io.write_polydata(output / "correspondence" / f"{name}.vtp", projected)
        print(f"{name}: aligned, mean projection {np.mean(np.linalg.norm(projected - aligned, axis=1)):.2f} mm")


def noise_floor(args):
    """The true correspondence seen through the preprocessing: the same template points on every
    true mesh, projected to the closest points of the case's prepared surface. Its error is what
    voxelisation and surface extraction alone cost; no correspondence method can do better."""
    from mdlshapemodel.prepare import io
    from mdlshapemodel.prepare.surface import SurfaceDistance

    truth, output = Path(args.truth), Path(args.output)
    (output / "correspondence").mkdir(parents=True, exist_ok=True)
    chosen, _ = template_points(truth, args.points)
    for name, target, target_faces in prepared_surfaces(truth):
        true_points = io.read_mesh(truth / "meshes" / f"{name}.vtp")[0][chosen]
        projected = SurfaceDistance(target, target_faces).closest(true_points)[0]
        io.write_polydata(output / "correspondence" / f"{name}.vtp", projected)
        print(f"{name}: true points moved {np.mean(np.linalg.norm(projected - true_points, axis=1)):.3f} mm")


def description_lengths(shapes: np.ndarray, triangles: np.ndarray, config, voxel: float,
                        data_range: float) -> tuple[float, float]:
    """F of eq. 13 (at the build's fixed Delta) and eq. 14 of corresponded shapes (n_s, n_p, 3)
    with the library's alignment and weights: weighted Procrustes with area weights of the mean
    (three rounds), rescaled to the mean's centroid size."""
    from mdlshapemodel.correspondence.objective import objectives
    from mdlshapemodel.geometry import generalized_procrustes
    from mdlshapemodel.prepare.surface import triangle_vertex_areas

    weights = np.full(shapes.shape[1], 1.0 / shapes.shape[1])
    for _ in range(3):
        aligned, _ = generalized_procrustes(shapes, weights)
        weights = triangle_vertex_areas(aligned.mean(axis=0), triangles)
        weights = weights / weights.sum()
    centred = (aligned - aligned.mean(axis=0)) * np.sqrt(weights)[None, :, None]
    flat = centred.reshape(len(shapes), -1)
    fixed, integrated = objectives(config, voxel, data_range)
    return fixed(flat @ flat.T), integrated(flat @ flat.T)


def objective_check(args):
    """Does the objective prefer the truth? F of a build's correspondence, and of the same points
    moved to their true places: each point's copies, carried to the template, are replaced by
    their mean's closest template point, carried back to every case's true mesh and projected
    onto the case's prepared surface (the surface the build saw)."""
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.prepare import io
    from mdlshapemodel.prepare.surface import SurfaceDistance

    truth, build = Path(args.truth), Path(args.build)
    config = BuildConfig.from_dict(json.loads((build / "config.json").read_text()))
    metrics = json.loads((build / "metrics.json").read_text())
    template, faces = io.read_mesh(truth / "template.vtp")
    surfaces = {name: (v, f) for name, v, f in prepared_surfaces(truth)}
    names = sorted(p.stem for p in (build / "correspondence").glob("*.vtp") if p.stem in surfaces)
    points, triangles = {}, None
    for name in names:
        points[name], triangles = io.read_mesh(build / "correspondence" / f"{name}.vtp")
    true_meshes = {n: io.read_mesh(truth / "meshes" / f"{n}.vtp")[0] for n in names}
    carried = np.stack([located_on_template(points[n], true_meshes[n], faces, template)
                        for n in names])
    # each point's true place: its carried copies' mean, located on the template and carried to
    # every case's true mesh, then onto the prepared surface
    mean = carried.mean(axis=0)
    truths = [SurfaceDistance(*surfaces[n]).closest(
        located_on_template(mean, template, faces, true_meshes[n]))[0] for n in names]
    voxel, data_range = metrics["voxel_size_mm"], metrics["data_range_mm"]
    built = description_lengths(np.stack([points[n] for n in names]), triangles, config, voxel,
                                data_range)
    true = description_lengths(np.stack(truths), triangles, config, voxel, data_range)
    reported = metrics["objective"].get("parts", {}).get("final", {}).get(
        "description_length", metrics["objective"]["final"])
    print(f"{len(names)} cases; the build reported eq. 14 = {reported:.2f}")
    print(f"{'correspondence':<34} {'eq. 13 (fixed Delta)':>20} {'eq. 14':>10}")
    print(f"{'the build':<34} {built[0]:>20.2f} {built[1]:>10.2f}")
    print(f"{'the same points at their true places':<34} {true[0]:>20.2f} {true[1]:>10.2f}")


def sliding(args):
    """How much of the truth slides along the surface: every true mesh rigidly aligned to the
    template (the vertices correspond), its displacements split along the template's normals, and
    each point's spread about the population mean printed for both parts (mm)."""
    from mdlshapemodel.geometry import generalized_procrustes
    from mdlshapemodel.prepare import io

    truth = Path(args.truth)
    template, faces = io.read_mesh(truth / "template.vtp")
    normals = vertex_normals(template, faces)
    names = sorted(json.loads((truth / "truth.json").read_text())["cases"])
    meshes = [io.read_mesh(truth / "meshes" / f"{name}.vtp")[0] for name in names]
    shapes = np.stack([template, *meshes])
    aligned, _ = generalized_procrustes(shapes, np.full(len(template), 1.0 / len(template)),
                                        scaling=False)
    displacement = aligned[1:] - aligned[0]
    along = np.einsum("ikd,kd->ik", displacement, normals)
    tangential = displacement - along[..., None] * normals[None]
    spread = np.linalg.norm(tangential - tangential.mean(axis=0), axis=2)
    print(f"{len(names)} cases; spread of each point's true displacement about the population "
          f"mean: along the surface {spread.mean():.3f} mm (95th percentile "
          f"{np.percentile(spread, 95):.3f}), along the normals "
          f"{np.abs(along - along.mean(axis=0)).mean():.3f} mm")


def from_truth(args):
    """Where does the optimiser go from the truth? The true meshes (before voxelisation) on one
    shared triangulation, the decimated template's carried to every case through the known
    correspondence. ``--start truth``: one sphere map, the template's, for every case, so the
    initial samples of all cases are the same anatomical points (error 0); ``--start maps``:
    every case's own sphere map, aligned as a build aligns them (the build's initial
    correspondence, on the same meshes). Then the default optimisation (the build's settings and
    objectives); the error and both objectives are printed before and after. A truth that the
    optimiser leaves says what the objective prefers; a truth whose F is far below what the
    optimiser reaches from the sphere maps says that the optimiser stops in another basin."""
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.correspondence.objective import objectives
    from mdlshapemodel.geometry import generalized_procrustes
    from mdlshapemodel.correspondence.sampling import sphere_grid
    from mdlshapemodel.correspondence.state import CorrespondenceState, Example, PartState
    from mdlshapemodel.correspondence.strategies import optimise
    from mdlshapemodel.correspondence.trace import Trace
    from mdlshapemodel.prepare import io, surface
    from mdlshapemodel.prepare.sphere import align_parameterizations, sphere_map

    truth = Path(args.truth)
    config = BuildConfig(max_time=args.max_time, fixed_fraction=args.fixed_fraction,
                         fixed_delta=args.fixed_delta)
    spacing = json.loads((truth / "truth.json").read_text())["spacing_mm"]
    names = sorted(json.loads((truth / "truth.json").read_text())["cases"])
    template, faces = io.read_mesh(truth / "template.vtp")
    coarse, triangles = surface.decimate(template, faces, config.target_vertices)
    cases = [located_on_template(coarse, template, faces,
                                 io.read_mesh(truth / "meshes" / f"{name}.vtp")[0])
             for name in names]
    started = time.perf_counter()
    if args.start == "truth":
        spheres = [sphere_map(coarse, triangles).sphere] * len(cases)
    else:
        spheres = [m.sphere for m in align_parameterizations(
            [sphere_map(vertices, triangles) for vertices in cases])]
    print(f"{len(cases)} true meshes of {len(coarse)} vertices; sphere maps in "
          f"{time.perf_counter() - started:.0f} s")
    grid, grid_triangles = sphere_grid(config.points_for(curves=False))
    examples = [Example(name, [PartState(vertices, triangles, sphere, grid, grid_triangles)])
                for name, vertices, sphere in zip(names, cases, spheres)]
    state = CorrespondenceState(examples, [(grid, grid_triangles)], scaling=config.scaling)
    # R of the objectives from the true meshes, aligned: the same for both starts, so that their
    # F compare
    aligned, _ = generalized_procrustes(np.stack(cases), np.full(len(coarse), 1.0 / len(coarse)))
    data_range = float(np.max(np.ptp(aligned.reshape(-1, 3), axis=0)))
    fixed, integrated = objectives(config, spacing, data_range)

    def measured(when: str):
        carried = np.stack([located_on_template(example.parts[0].points, vertices, triangles,
                                                coarse)
                            for example, vertices in zip(state.examples, cases)])
        spread = np.linalg.norm(carried - carried.mean(axis=0), axis=2)
        values = []
        for objective in (fixed, integrated):
            state.objective = objective
            values.append(state.value())
        print(f"{when:<6} error {spread.mean():.3f} mm (95th percentile "
              f"{np.percentile(spread, 95):.3f}), eq. 13 {values[0]:.2f}, eq. 14 {values[1]:.2f}",
              flush=True)

    measured("start")
    started = time.perf_counter()
    trace = Trace()
    optimise(state, (fixed, integrated), config.optimisation_settings(),
             np.random.default_rng(config.seed), trace)
    print(f"optimised ({config.strategy}) in {time.perf_counter() - started:.0f} s")
    measured("end")


def run_all(args):
    """Every correspondence on one population: make it (unless it exists), build with every
    strategy and the CPD baseline through the command line, the two references, then evaluate."""
    import subprocess
    import sys

    output = Path(args.output)
    here = Path(__file__).resolve()
    if not (output / "truth.json").exists():
        subprocess.run([sys.executable, str(here), "make", "--cases", str(args.cases),
                        "--spacing", str(args.spacing), "--output", str(output)], check=True)
    builds = {"initial": ["--strategy", "none"], "cpd": ["--correspondence", "cpd"]}
    builds.update({name: ["--strategy", name] for name in args.strategies})
    for name, options in builds.items():
        folder = output / "builds" / name
        if (folder / "model.h5").exists():
            continue
        started = time.perf_counter()
        subprocess.run(["mdlshapemodel", "build", str(output / "labels"), "-o", str(folder),
                        "--baselines", "", "--max-time", str(args.max_time), "-q", *options],
                       check=True)
        print(f"{name}: built in {time.perf_counter() - started:.0f} s", flush=True)
    for name in ("template", "floor"):
        if not (output / "builds" / name / "correspondence").exists():
            subprocess.run([sys.executable, str(here), name, str(output), "--output",
                            str(output / "builds" / name)], check=True, stdout=subprocess.DEVNULL)
    order = ["floor", "initial", "template", "cpd", *args.strategies]
    evaluate(argparse.Namespace(truth=str(output),
                                builds=[str(output / "builds" / name) for name in order]))


def main():
    from mdlshapemodel.config import STRATEGIES, BuildConfig

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    maker = commands.add_parser("make", help="a population with known correspondence")
    maker.add_argument("--mesh", default=str(FEMURS / "m3_lfemur_mm.stl"))
    maker.add_argument("--cases", type=int, default=30)
    maker.add_argument("--spacing", type=float, default=0.5, help="voxel size, mm")
    maker.add_argument("--modes", type=int, default=4)
    maker.add_argument("--amplitude", type=float, default=6.0,
                       help="largest displacement of the first mode at 1 SD, mm (mode m: /m)")
    maker.add_argument("--noise", type=float, default=0.5, help="per-case field, largest mm")
    maker.add_argument("--width", type=float, default=0.5, help="field width / RMS radius")
    maker.add_argument("--centres", type=int, default=8, help="Gaussians per field")
    maker.add_argument("--rotation", type=float, default=10.0, help="SD of the pose angle, deg")
    maker.add_argument("--translation", type=float, default=3.0, help="SD per axis, mm")
    maker.add_argument("--max-vertices", type=int, default=40000)
    maker.add_argument("--seed", type=int, default=0)
    maker.add_argument("--normal-only", action="store_true",
                       help="keep only the displacements' components along the template's "
                            "normals: a truth with no sliding along the surface, which no "
                            "method that sees only the surfaces could recover")
    maker.add_argument("--offset", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar="MM",
                       help="a shift of every case before voxelising: the same shapes voxelised "
                            "anew (a sub-voxel offset measures how stable a build is)")
    maker.add_argument("--output", required=True)
    reference = commands.add_parser("template", help="rigid template + closest point reference")
    reference.add_argument("truth")
    reference.add_argument("--points", type=int, default=2562)
    reference.add_argument("--output", required=True)
    floor = commands.add_parser("floor", help="the true correspondence through the preprocessing")
    floor.add_argument("truth")
    floor.add_argument("--points", type=int, default=2562)
    floor.add_argument("--output", required=True)
    marker = commands.add_parser("landmarks", help="landmarks at known places, in halves")
    marker.add_argument("truth")
    marker.add_argument("--count", type=int, default=22)
    evaluator = commands.add_parser("evaluate", help="correspondence error of build outputs")
    evaluator.add_argument("truth")
    evaluator.add_argument("builds", nargs="+")
    checker = commands.add_parser("objective", help="F of a build and of its points' true places")
    checker.add_argument("truth")
    checker.add_argument("build")
    slider = commands.add_parser("sliding", help="how much of the truth slides along the surface")
    slider.add_argument("truth")
    start = commands.add_parser("from-truth", help="optimise from the truth on the true meshes")
    start.add_argument("truth")
    start.add_argument("--start", choices=("truth", "maps"), default="truth",
                       help="the template's sphere map for every case (the truth), or each "
                            "case's own, aligned as a build aligns them")
    start.add_argument("--max-time", type=float, default=300.0, help="optimisation budget, s")
    start.add_argument("--fixed-fraction", type=float, default=BuildConfig.fixed_fraction,
                       help="as the build's option (0: eq. 14 alone)")
    start.add_argument("--fixed-delta", type=float, default=BuildConfig.fixed_delta,
                       help="as the build's option (voxels)")
    everything = commands.add_parser("run", help="make, build with every strategy, evaluate")
    everything.add_argument("--cases", type=int, default=30)
    everything.add_argument("--spacing", type=float, default=0.5)
    everything.add_argument("--strategies", type=lambda text: text.split(","),
                            default=",".join(name for name in STRATEGIES if name != "none"),
                            help="comma-separated (default %(default)s)")
    everything.add_argument("--max-time", type=float, default=600.0,
                            help="optimisation budget of each build, s")
    everything.add_argument("--output", required=True)
    args = parser.parse_args()
    {"make": make, "template": template_reference, "floor": noise_floor,
     "evaluate": evaluate, "run": run_all, "landmarks": write_landmarks, "objective": objective_check,
     "sliding": sliding, "from-truth": from_truth}[args.command](args)


if __name__ == "__main__":
    main()
