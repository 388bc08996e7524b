"""3D trajectory metrics on (K, 4, 4) poses: ATE after rigid alignment, per-pose rotation error."""

from __future__ import annotations

import numpy as np

from deepmapping.core import se3
from deepmapping.core.alignment import rigid_align


def _check(est, gt) -> tuple[np.ndarray, np.ndarray]:
    est, gt = np.asarray(est, dtype=np.float64), np.asarray(gt, dtype=np.float64)
    if est.ndim != 3 or est.shape[1:] != (4, 4) or est.shape != gt.shape:
        raise ValueError(f"est and gt must both be (K, 4, 4), got {est.shape} and {gt.shape}")
    return est, gt


def align_poses_3d(est, gt) -> np.ndarray:
    """The estimate moved by the rigid transform (no scale) that best maps its positions onto gt's."""
    est, gt = _check(est, gt)
    rot, t = rigid_align(est[:, :3, 3], gt[:, :3, 3])
    return se3.compose(se3.from_rt(rot, t), est)


def ate_3d(est, gt) -> float:
    """RMSE of positions after alignment, in the units of gt."""
    aligned, gt = align_poses_3d(est, gt), np.asarray(gt, dtype=np.float64)
    return float(np.sqrt(np.mean(np.sum((aligned[:, :3, 3] - gt[:, :3, 3]) ** 2, axis=1))))


def rotation_errors_deg(est, gt) -> np.ndarray:
    """(K,) angle of R_gt^T R_est per pose after the same alignment as ATE (degrees)."""
    aligned, gt = align_poses_3d(est, gt), np.asarray(gt, dtype=np.float64)
    return se3.rotation_angle_deg(np.swapaxes(gt[:, :3, :3], 1, 2) @ aligned[:, :3, :3])
