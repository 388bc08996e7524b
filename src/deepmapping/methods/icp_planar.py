"""Planar (3-DoF) point-to-plane ICP with yaw hypotheses, for AVD-like RGB-D sequences.

AVD-style poses move on the floor: ``[x, z, theta]``, theta about the vertical y axis
(:func:`deepmapping.geometry.se3.from_planar_xz`). Estimating only those three parameters keeps
ICP from tilting or lifting a scan to fit a floor or a wall, and a few yaw hypotheses per
pair (0 and +-30 deg by default: AVD turns the camera in 30 deg steps) get it out of the
rotation local minima that make 6-DoF ICP from the identity wrong on most turns. Each
hypothesis is refined coarse to fine (Gauss-Newton, Cauchy-weighted point-to-plane residuals,
target normals by Open3D) and the one with the highest fitness (share of source points within
the fine correspondence distance) wins.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

from deepmapping.geometry import se3
from deepmapping.methods.icp3d import check_clouds, check_init, default_scales, prepare_clouds

__all__ = ["planar_params", "register_pair_planar", "incremental_icp_planar", "DEFAULT_YAW_HYPOTHESES_DEG"]

DEFAULT_YAW_HYPOTHESES_DEG = (0.0, 30.0, -30.0)
ROBUST_SCALE_FACTOR = 0.35  # Cauchy scale = this x the fine correspondence distance


def _gauss_newton(src, tgt, normals, tree, x, distance, robust, iterations):
    for _ in range(iterations):
        T = se3.from_planar_xz(x)
        rotated = src @ T[:3, :3].T
        dist, idx = tree.query(rotated + T[:3, 3], distance_upper_bound=distance)
        m = np.isfinite(dist)
        if m.sum() < 6:
            break
        q, n, r_src = tgt[idx[m]], normals[idx[m]], rotated[m]
        res = np.einsum("ij,ij->i", r_src + T[:3, 3] - q, n)
        jac = np.stack([n[:, 0], n[:, 2], n[:, 0] * r_src[:, 2] - n[:, 2] * r_src[:, 0]], axis=1)
        w = 1.0 / (1.0 + (res / robust) ** 2)
        step = np.linalg.solve((jac * w[:, None]).T @ jac + 1e-9 * np.eye(3), -(jac * w[:, None]).T @ res)
        x = x + step
        if np.abs(step).max() < 1e-6:
            break
    return x


def planar_params(pose: np.ndarray) -> np.ndarray:
    """[x, z, theta] of a planar 4x4 pose (inverse of se3.from_planar_xz)."""
    return np.array([pose[0, 3], pose[2, 3], np.arctan2(pose[0, 2], pose[0, 0])])


def register_pair_planar(source: np.ndarray, target: np.ndarray, target_normals: np.ndarray, fine: float,
                         coarse: float, yaw_hypotheses_deg: Sequence[float] = DEFAULT_YAW_HYPOTHESES_DEG,
                         max_iterations: int = 30, guess: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Pose (4x4) of ``source``'s sensor in ``target``'s frame, and its fitness in [0, 1].

    The hypotheses are yaw offsets from ``guess`` (planar 4x4; None = identity).
    """
    tree = cKDTree(target)
    x0 = np.zeros(3) if guess is None else planar_params(guess)
    best_pose, best_fit = np.eye(4), -1.0
    for yaw in np.radians(np.asarray(yaw_hypotheses_deg, dtype=np.float64)):
        x = x0 + np.array([0.0, 0.0, yaw])
        for distance in (0.5 * coarse, 0.25 * coarse, fine):
            x = _gauss_newton(source, target, target_normals, tree, x, distance,
                              ROBUST_SCALE_FACTOR * fine, max_iterations)
        pose = se3.from_planar_xz(x)
        dist, _ = tree.query(se3.transform_points(pose, source), distance_upper_bound=fine)
        fit = float(np.isfinite(dist).mean())
        if fit > best_fit:
            best_pose, best_fit = pose, fit
    return best_pose, best_fit


def incremental_icp_planar(
    clouds,
    init: np.ndarray | None = None,
    voxel_size: float | None = None,
    max_correspondence_distance: float | None = None,
    yaw_hypotheses_deg: Sequence[float] = DEFAULT_YAW_HYPOTHESES_DEG,
    max_iterations: int = 30,
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """Chain planar ICP over an ordered sequence: scan i+1 registered to scan i.

    ``clouds``: K arrays (N_i, 3) in sensor frames (y = down/up, poses about y). Returns
    sensor-to-world poses (K, 4, 4), pose 0 = identity (or ``init[0]``). With ``init`` (K, 4, 4),
    each pair starts from its relative motion in ``init`` (reduced to x, z, yaw).
    """
    clouds = check_clouds(clouds)
    init = check_init(init, len(clouds))
    scales = default_scales(clouds, voxel_size, max_correspondence_distance)
    pcds = prepare_clouds(clouds, scales, normals=True)
    points = [np.asarray(p.points) for p in pcds]
    poses = se3.identity((len(clouds),))
    if init is not None:
        poses[0] = init[0]
    for i in range(len(clouds) - 1):
        guess = None if init is None else se3.from_planar_xz(planar_params(se3.relative(init[i], init[i + 1])))
        rel, _ = register_pair_planar(points[i + 1], points[i], np.asarray(pcds[i].normals), scales.fine,
                                      scales.coarse, yaw_hypotheses_deg, max_iterations, guess)
        poses[i + 1] = poses[i] @ rel
        if progress is not None:
            progress(i + 1, len(clouds) - 1)
    return poses
