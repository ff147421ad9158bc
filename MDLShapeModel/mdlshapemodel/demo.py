"""Small synthetic populations for ``mdlshapemodel demo``: label maps (3-D, or two parts) and
2-D curves.

Each subject is an ellipsoid of varying thickness with a bump on its upper side whose size varies
from subject to subject. An area-preserving parameterization gives a large bump more of the
sphere than a small one, which shifts the parameterization of everything around it: equal spacing
on the sphere then makes a less compact model than a correspondence that follows the bump.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def bump_ellipsoid_mask(shape=(30, 34, 48), semi_axes=(16.0, 9.0, 7.0), bump_position=0.0,
                        bump_radius=5.0, scale=1.0) -> np.ndarray:
    """Binary mask (z, y, x) of an ellipsoid with a spherical bump.

    ``bump_position`` in [-1, 1] places the bump along the long (x) axis.
    """
    z, y, x = np.indices(shape, dtype=np.float64)
    cz, cy, cx = [(n - 1) / 2.0 for n in shape]
    ax, ay, az = (scale * s for s in semi_axes)
    ellipsoid = ((x - cx) / ax) ** 2 + ((y - cy) / ay) ** 2 + ((z - cz) / az) ** 2 <= 1.0
    bx = cx + 0.6 * ax * bump_position
    by = cy + ay * np.sqrt(max(0.0, 1.0 - (0.6 * bump_position) ** 2))
    bump = (x - bx) ** 2 + (y - by) ** 2 + (z - cz) ** 2 <= (scale * bump_radius) ** 2
    return ellipsoid | bump


def _population(folder, seed: int, sizes: np.ndarray):
    """The folder (made), the generator of a demo population and its subjects' sizes in a
    random order."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    rng.shuffle(sizes)
    return folder, rng, sizes


#: the parts of the two-part demo population (``write_demo_population(..., parts=True)``): the
#: labels of its two halves, as ``--part`` takes them
DEMO_PARTS = ("left=1", "right=2")


def write_demo_population(folder, n_subjects: int = 12, seed: int = 0,
                          parts: bool = False) -> list[Path]:
    """Write ``n_subjects`` label maps (NIfTI, 1 mm voxels) to ``folder``; return their paths.

    With ``parts``, each ellipsoid is cut across its long axis, 4 voxels left of its centre, into
    two touching parts, labels 1 and 2 (:data:`DEMO_PARTS`); the bump is on the right part.
    """
    import SimpleITK as sitk

    folder, rng, radii = _population(folder, seed, np.linspace(2.5, 7.5, n_subjects))
    paths = []
    for k, radius in enumerate(radii):
        thickness = float(7.0 + 1.0 * rng.uniform(-1, 1))
        shape = (30, 34, 48)
        mask = bump_ellipsoid_mask(shape=shape, semi_axes=(16.0, 9.0, thickness),
                                   bump_position=0.3, bump_radius=float(radius))
        labels = mask.astype(np.uint8)
        if parts:
            labels[:, :, (shape[2] - 1) // 2 - 4:] *= 2
        image = sitk.GetImageFromArray(labels)
        image.SetSpacing((1.0, 1.0, 1.0))
        path = folder / f"subject_{k + 1:02d}.nii.gz"
        sitk.WriteImage(image, str(path))
        paths.append(path)
    return paths


def demo_curve(bump: float, width: float, rng: np.random.Generator, n: int = 400) -> np.ndarray:
    """A closed 2-D outline (n, 2), mm: an ellipse (40 x 24 mm) with a bump of height ``bump``
    (mm) on its upper side, slightly wobbled, starting at a random point."""
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    bumped = 1.0 + bump / 12.0 * np.exp(-((t - 1.9) / 0.2) ** 2)
    wobble = 1.0 + 0.02 * np.sin(3.0 * t + rng.uniform(0, 2 * np.pi))
    points = np.stack([20.0 * width * np.cos(t), 12.0 * bumped * wobble * np.sin(t)], axis=1)
    return np.roll(points, int(rng.integers(n)), axis=0)


def write_demo_curves(folder, n_subjects: int = 12, seed: int = 0) -> list[Path]:
    """Write ``n_subjects`` closed outlines as CSV point lists (x, y per row) to ``folder``:
    ellipses of varying width whose bump varies in height (a larger bump takes more of the
    arc length, so equal arc-length spacing shifts the points around it). Returns the paths."""
    folder, rng, bumps = _population(folder, seed, np.linspace(3.0, 18.0, n_subjects))
    paths = []
    for k, bump in enumerate(bumps):
        points = demo_curve(float(bump), float(1.0 + 0.05 * rng.uniform(-1, 1)), rng)
        path = folder / f"outline_{k + 1:02d}.csv"
        np.savetxt(path, points, delimiter=",", header="x,y", comments="", fmt="%.6f")
        paths.append(path)
    return paths
