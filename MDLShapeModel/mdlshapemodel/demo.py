"""A small synthetic population for ``mdlshapemodel demo``.

Each subject is an ellipsoid with a bump on its upper side; the bump slides along the long axis
from subject to subject and the ellipsoid's size varies a little. Equal spacing on the sphere puts
the bump at different parameter values in each subject (a poor, non-compact model); a good
correspondence follows the bump.
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


def write_demo_population(folder, n_subjects: int = 12, seed: int = 0) -> list[Path]:
    """Write ``n_subjects`` label maps (NIfTI, 1 mm voxels) to ``folder``; return their paths."""
    import SimpleITK as sitk

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    positions = np.linspace(-0.8, 0.8, n_subjects)
    rng.shuffle(positions)
    paths = []
    for k, position in enumerate(positions):
        mask = bump_ellipsoid_mask(bump_position=float(position),
                                   scale=float(1.0 + 0.05 * rng.standard_normal()))
        image = sitk.GetImageFromArray(mask.astype(np.uint8))
        image.SetSpacing((1.0, 1.0, 1.0))
        path = folder / f"subject_{k + 1:02d}.nii.gz"
        sitk.WriteImage(image, str(path))
        paths.append(path)
    return paths
