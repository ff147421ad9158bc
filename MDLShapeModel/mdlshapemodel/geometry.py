"""Rigid and similarity alignment: poses, the orthogonal Procrustes rotation, weighted generalized
Procrustes alignment (eq. 18).

The one place of these tools for every stage: preparation aligns sphere maps with
:func:`best_rotation`, the correspondence and the fitting of a new case pose shapes with
:func:`align` and :func:`generalized_procrustes`, the analysis superimposes a build's shapes with
them. Shapes are arrays (n_p, 3); weights w (n_p,) sum to one (the area measure of eq. 15-17), so
weighted sums of squares are mean squared distances in the shapes' units.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Pose:
    """x -> scale * R x + translation."""

    scale: float = 1.0
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * points @ self.rotation.T + self.translation

    def compose(self, other: "Pose") -> "Pose":
        """self after other: x -> self(other(x))."""
        return Pose(self.scale * other.scale, self.rotation @ other.rotation,
                    self.scale * self.rotation @ other.translation + self.translation)

    def inverse(self) -> "Pose":
        rotation = self.rotation.T
        return Pose(1.0 / self.scale, rotation, -(rotation @ self.translation) / self.scale)

    def copy(self) -> "Pose":
        return Pose(float(self.scale), self.rotation.copy(), self.translation.copy())


def rotation_from_vector(vector: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis * angle), Rodrigues' formula."""
    vector = np.asarray(vector, dtype=np.float64)
    angle = float(np.linalg.norm(vector))
    if angle < 1e-15:
        return np.eye(3)
    k = vector / angle
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def pose_from_parameters(parameters: np.ndarray) -> Pose:
    """Pose from 7 numbers: rotation vector (3), translation (3), log scale (1)."""
    return Pose(float(np.exp(parameters[6])), rotation_from_vector(parameters[:3]),
                np.asarray(parameters[3:6], dtype=np.float64))


def weighted_centroid(points: np.ndarray, weights: np.ndarray) -> np.ndarray:
    return weights @ points


def centroid_size(points: np.ndarray, weights: np.ndarray) -> float:
    """Root weighted mean squared distance to the weighted centroid."""
    centred = points - weighted_centroid(points, weights)
    return float(np.sqrt(weights @ np.einsum("ij,ij->i", centred, centred)))


def align(source: np.ndarray, target: np.ndarray, weights: np.ndarray,
          scaling: bool = True, planar: bool = False) -> Pose:
    """Similarity (or rigid) transform minimising sum_k w_k |T(source_k) - target_k|^2.

    Weighted orthogonal Procrustes (Umeyama), proper rotations only. ``planar``: for shapes in
    the plane z = 0 (closed curves), a rotation about z (a proper 2-D rotation, never a
    reflection) and a translation in x and y.
    """
    mu_s = weighted_centroid(source, weights)
    mu_t = weighted_centroid(target, weights)
    s = source - mu_s
    t = target - mu_t
    covariance = (t * weights[:, None]).T @ s
    if planar:
        rotation, gain = planar_rotation(covariance)
    else:
        rotation, gain = best_rotation(covariance)
    if scaling:
        variance = float(weights @ np.einsum("ij,ij->i", s, s))
        scale = float(gain / variance) if variance > 0 else 1.0
    else:
        scale = 1.0
    return Pose(scale, rotation, mu_t - scale * rotation @ mu_s)


def best_rotation(cross: np.ndarray) -> tuple[np.ndarray, float]:
    """The proper rotation P maximising <cross, P> (orthogonal Procrustes, a reflection never
    allowed) and that maximum (3 x 3 ``cross``)."""
    u, singular, vt = np.linalg.svd(cross)
    d = np.ones(3)
    d[2] = np.sign(np.linalg.det(u @ vt)) or 1.0
    return (u * d) @ vt, float(np.sum(singular * d))


def planar_rotation(covariance: np.ndarray) -> tuple[np.ndarray, float]:
    """The rotation about z maximising sum_k w_k t_k . R s_k, and that maximum, from the
    covariance C = sum_k w_k t_k s_k^T (3 x 3; only its x-y block is used): eq. 18 in the plane.

    With R the rotation by angle a, the sum is cos a (C_xx + C_yy) + sin a (C_yx - C_xy): largest
    at a = atan2(C_yx - C_xy, C_xx + C_yy), where it is the length of that vector.
    """
    along = covariance[0, 0] + covariance[1, 1]
    across = covariance[1, 0] - covariance[0, 1]
    angle = np.arctan2(across, along)
    rotation = np.eye(3)
    rotation[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    return rotation, float(np.hypot(along, across))


def apply_poses(poses: list, shapes: np.ndarray) -> np.ndarray:
    """Each shape (n_s, n_p, 3) moved by its :class:`Pose`."""
    return np.stack([p.apply(x) for p, x in zip(poses, shapes)])


def generalized_procrustes(shapes: np.ndarray, weights: np.ndarray, scaling: bool = True,
                           target_size: float | None = None, iterations: int = 50,
                           tolerance: float = 1e-10, planar: bool = False
                           ) -> tuple[np.ndarray, list[Pose]]:
    """Align shapes (n_s, n_p, 3) to their common mean (Goodall 1991, weighted; eq. 18).

    The mean is kept centred at the origin with centroid size ``target_size`` (default: the mean
    centroid size of the inputs), so aligned shapes stay in the inputs' units (mm) and a coding
    accuracy Delta given in those units keeps its meaning. ``planar``: shapes in the plane
    z = 0, rotated about z only (:func:`align`).

    Returns the aligned shapes and one :class:`Pose` per shape (input -> aligned).
    """
    shapes = np.asarray(shapes, dtype=np.float64)
    if target_size is None:
        target_size = float(np.mean([centroid_size(x, weights) for x in shapes]))
    poses = [align(x, shapes[0], weights, scaling=False, planar=planar) for x in shapes]
    previous = np.inf
    for _ in range(iterations):
        aligned = apply_poses(poses, shapes)
        mean = aligned.mean(axis=0)
        mean = mean - weighted_centroid(mean, weights)
        mean *= target_size / centroid_size(mean, weights)
        poses = [align(x, mean, weights, scaling=scaling, planar=planar) for x in shapes]
        aligned = apply_poses(poses, shapes)
        residual = float(np.sum((aligned - mean) ** 2 * weights[None, :, None]))
        if previous - residual <= tolerance * max(residual, 1e-300):
            break
        previous = residual
    return aligned, poses
