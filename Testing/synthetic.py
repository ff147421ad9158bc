"""Small synthetic populations shared by the integration-style tests (cached per session)."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from mdlshapemodel.config import BuildConfig
from mdlshapemodel.prepare import surface
from mdlshapemodel.correspondence.objective import objectives
from mdlshapemodel.correspondence.state import CorrespondenceState, Example, PartState
from mdlshapemodel.demo import bump_ellipsoid_mask
from mdlshapemodel.correspondence.sampling import sphere_grid
from mdlshapemodel.prepare.sphere import align_parameterizations, sphere_map

SMALL_SHAPE = (18, 20, 28)


def torus(major: float = 10.0, minor: float = 3.0, n: int = 24, m: int = 12
          ) -> tuple[np.ndarray, np.ndarray]:
    """A consistently oriented triangulated torus (Euler characteristic 0), n x m vertices."""
    u, v = np.meshgrid(np.arange(n) * 2 * np.pi / n, np.arange(m) * 2 * np.pi / m, indexing="ij")
    points = np.stack([(major + minor * np.cos(v)) * np.cos(u),
                       (major + minor * np.cos(v)) * np.sin(u), minor * np.sin(v)], -1).reshape(-1, 3)
    index = np.arange(n * m).reshape(n, m)
    a, b = index, np.roll(index, -1, axis=0)
    c, d = np.roll(b, -1, axis=1), np.roll(index, -1, axis=1)
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                            np.stack([a, c, d], -1).reshape(-1, 3)])
    return points, faces


def small_mask(position: float, scale: float = 1.0) -> np.ndarray:
    """A small ellipsoid with a bump at ``position`` in [-1, 1] along its long axis."""
    return bump_ellipsoid_mask(shape=SMALL_SHAPE, semi_axes=(10.0, 6.0, 5.0),
                               bump_position=position, bump_radius=3.5, scale=scale)


def thin_and_full_build(folder: Path, count: int) -> Path:
    """A real build (``folder``/build, no optimisation, 162 points) of ``count`` small bumpy
    ellipsoids ``folder``/labels/case_KK.nii.gz, their bumps spread along the long axis, the odd
    ones 8% smaller (two groups that differ in size)."""
    import SimpleITK as sitk

    from mdlshapemodel import build_model

    paths = []
    for k, position in enumerate(np.linspace(-0.5, 0.5, count)):
        mask = small_mask(float(position), 0.92 if k % 2 else 1.0).astype(np.uint8)
        paths.append(folder / "labels" / f"case_{k:02d}.nii.gz")
        paths[-1].parent.mkdir(exist_ok=True)
        sitk.WriteImage(sitk.GetImageFromArray(mask), str(paths[-1]))
    config = BuildConfig(points=162, strategy="none", baselines=[], workers=1,
                         evaluation_modes=2, specificity_samples=100, surface_samples=0,
                         cache_dir="")
    build_model(paths, folder / "build", config)
    return folder / "build"


def small_bump_top(position: float) -> np.ndarray:
    """The top of :func:`small_mask`'s bump in voxel coordinates (x, y, z)."""
    cz, cy, cx = [(n - 1) / 2.0 for n in SMALL_SHAPE]
    ax, ay = 10.0, 6.0
    by = cy + ay * np.sqrt(1.0 - (0.6 * position) ** 2)
    return np.array([cx + 0.6 * ax * position, by + 3.5, cz])


@lru_cache(maxsize=None)
def small_maps(n: int = 5) -> tuple:
    """Aligned sphere maps of ``n`` small bumpy ellipsoids (about 300 vertices each)."""
    maps = []
    for k, position in enumerate(np.linspace(-0.6, 0.6, n)):
        mask = small_mask(float(position), 1.0 + 0.03 * ((k % 3) - 1))
        vertices, faces, _ = surface.mask_to_surface(mask, edge_length=1.5)
        maps.append(sphere_map(vertices, faces))
    return tuple(align_parameterizations(maps))


def small_state(n: int = 5, points: int = 162) -> CorrespondenceState:
    """A fresh correspondence state of the small population (no objective set)."""
    grid, triangles = sphere_grid(points)
    examples = [Example(f"case_{k}", [PartState(m.vertices, m.faces, m.sphere, grid, triangles)])
                for k, m in enumerate(small_maps(n))]
    return CorrespondenceState(examples, [(grid, triangles)])


def build_objectives(state: CorrespondenceState, config: BuildConfig | None = None,
                     voxel: float = 1.0) -> tuple:
    """(fixed, integrated): the two objectives a build gives ``state``, made by the build's own
    :func:`~mdlshapemodel.correspondence.objective.objectives` from ``config`` (default: the
    defaults, ``--fixed-delta 0.1`` and ``--delta-range 1e-4 0.5``, in voxels) at the mean voxel
    size ``voxel``, with the data range of the aligned shapes as ``initial_state`` measures it."""
    data_range = float(np.max(np.ptp(state.aligned_shapes().reshape(-1, 3), axis=0)))
    return objectives(BuildConfig() if config is None else config, voxel, data_range)


def split_into_part_files(paths, parts: dict, folder, manifest: str = "cases.csv"):
    """Write each label map's parts (``{name: label}``) as binary label maps of their own in
    ``folder``, and a manifest (case,part,file; paths relative to ``folder``) listing them.
    Returns the manifest's path."""
    import SimpleITK as sitk

    rows = ["case,part,file"]
    for path in map(Path, paths):
        image = sitk.ReadImage(str(path))
        case = path.name.split(".")[0]
        for name, label in parts.items():
            part = sitk.Cast(image == label, sitk.sitkUInt8)
            part.CopyInformation(image)
            sitk.WriteImage(part, str(Path(folder) / f"{case}_{name}.nii.gz"))
            rows.append(f"{case},{name},{case}_{name}.nii.gz")
    table = Path(folder) / manifest
    table.write_text("\n".join(rows) + "\n")
    return table


def write_population(folder, n: int = 5) -> list:
    """``n`` small bumpy ellipsoids (:func:`small_mask`, sizes varying by 3 %) written as label
    maps ``case_K.nii.gz`` (label 1) into ``folder`` (made); returns their paths."""
    from files import write_label_map

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    return [write_label_map(folder / f"case_{k}.nii.gz",
                            small_mask(float(position), 1.0 + 0.03 * ((k % 3) - 1)))
            for k, position in enumerate(np.linspace(-0.6, 0.6, n))]


def vertex_areas(vertices, faces):
    """One third of the area of the triangles around each vertex (written out, as a reference)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    result = np.zeros(len(vertices))
    for k in range(3):
        np.add.at(result, faces[:, k], area / 3.0)
    return result


def radial_population(rng, n_s, n_functions, coarse=162, fine=642, semi_axes=(12.0, 9.0, 7.0),
                      amplitude=0.08):
    """Ellipsoids with random radial bumps: (shapes (n_s, coarse, 3), triangles, weights, true
    surfaces [(vertices, faces)] on the fine icosphere)."""
    directions, triangles = sphere_grid(coarse)
    fine_directions, fine_faces = sphere_grid(fine)
    assert np.allclose(fine_directions[:coarse], directions)          # the coarse vertices reappear
    frequencies = rng.normal(size=(n_functions, 3)) * 1.5
    phases = rng.uniform(0, 2 * np.pi, n_functions)
    coefficients = rng.normal(size=(n_s, n_functions)) * amplitude

    def sample(u, c):
        return u * (1 + np.sin(u @ frequencies.T + phases) @ c)[:, None] * np.array(semi_axes)

    shapes = np.stack([sample(directions, c) for c in coefficients])
    surfaces = [(sample(fine_directions, c), fine_faces) for c in coefficients]
    weights = vertex_areas(shapes.mean(axis=0), triangles)
    return shapes, triangles, weights / weights.sum(), surfaces


def two_sized_ellipsoids(folder: Path, n: int = 12) -> tuple:
    """n noisy ellipsoids on the triangles of an icosphere, each turned and moved, the odd ones
    10 % smaller; (the model of their least-squares alignment, the unaligned shapes, a subjects
    table: case, group full/thin, age; case_05 without a group).

    For the analysis's quick tests: a model with triangles and shapes in millimetres without a
    build."""
    from scipy.spatial.transform import Rotation

    from mdlshapemodel.analysis import align
    from mdlshapemodel.correspondence.sampling import icosphere
    from mdlshapemodel.model.shape_model import ShapeModel

    sphere, triangles = icosphere(2)
    rng = np.random.default_rng(9)
    shapes = []
    for k in range(n):
        noisy = (sphere * [30.0, 12.0, 10.0] * (0.9 if k % 2 else 1.0)
                 + rng.normal(scale=0.4, size=sphere.shape))
        turn = Rotation.from_rotvec(rng.normal(scale=0.3, size=3))
        shapes.append(turn.apply(noisy) + rng.normal(scale=5.0, size=3))
    shapes = np.stack(shapes)
    names = [f"case_{k:02d}" for k in range(n)]
    weights = np.full(len(sphere), 1.0 / len(sphere))
    model = ShapeModel.from_shapes(align(shapes, weights, superimposition="least-squares"),
                                   weights, names=names, triangles=triangles)
    table = Path(folder) / "subjects.csv"
    groups = ["" if k == 5 else "thin" if k % 2 else "full" for k in range(n)]
    rows = [f"{name},{group},{40 + 3 * k}" for k, (name, group) in enumerate(zip(names, groups))]
    table.write_text("\n".join(["case,group,age", *rows]) + "\n")
    return model, shapes, table
