"""Triangles on the unit sphere: orientation and solid angle, and a row-wise cross product.

Shared by the sphere map (:mod:`.sphere`) and the multilevel initial map (:mod:`.multilevel`).
"""

from __future__ import annotations

import numpy as np


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis; np.cross costs more than the arithmetic on short arrays."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def orientation(sphere: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """det[a, b, c] per face: positive when the triangle is counter-clockwise seen from outside."""
    a, b, c = (sphere[faces[:, k]] for k in range(3))
    return np.einsum("ij,ij->i", a, cross_rows(b, c))


def solid_angles(sphere: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Signed solid angle of each spherical triangle (Van Oosterom & Strackee)."""
    a, b, c = (sphere[faces[:, k]] for k in range(3))
    numerator = np.einsum("ij,ij->i", a, cross_rows(b, c))
    denominator = 1.0 + np.einsum("ij,ij->i", a, b) + np.einsum("ij,ij->i", b, c) \
        + np.einsum("ij,ij->i", c, a)
    return 2.0 * np.arctan2(numerator, denominator)
