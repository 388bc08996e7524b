"""Evaluation metrics of the paper (§4): ATE and point distance after rigid alignment."""

from __future__ import annotations

import numpy as np

from deepmapping.geometry import se2
from deepmapping.geometry.alignment import align_poses_2d

__all__ = ["ate", "point_distance", "rotation_rmse_deg", "evaluate"]


def _check(est, gt) -> tuple[np.ndarray, np.ndarray]:
    est = np.asarray(est, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if est.ndim != 2 or est.shape[1] != 3 or est.shape != gt.shape:
        raise ValueError(f"est and gt must both be (K, 3), got {est.shape} and {gt.shape}")
    return est, gt


def ate(est, gt) -> float:
    """Absolute trajectory error: RMSE of positions after aligning est onto gt."""
    est, gt = _check(est, gt)
    aligned = align_poses_2d(est, gt)
    return float(np.sqrt(np.mean(np.sum((aligned[:, :2] - gt[:, :2]) ** 2, axis=1))))


def heading_errors_deg(est, gt) -> np.ndarray:
    """(K,) absolute heading errors (degrees) after the same alignment as ATE."""
    est, gt = _check(est, gt)
    aligned = align_poses_2d(est, gt)
    return np.abs(np.degrees(se2.wrap_angle(aligned[:, 2] - gt[:, 2])))


def rotation_rmse_deg(est, gt) -> float:
    """RMSE of heading errors (degrees) after the same alignment as ATE."""
    return float(np.sqrt(np.mean(heading_errors_deg(est, gt) ** 2)))


def point_distance(points, valid, est, gt) -> float:
    """Mean distance between each valid point registered with gt poses and with est poses.

    points (K, N, 2) in sensor frames, valid (K, N) bool. The estimate is first aligned onto
    gt exactly as for ATE (positions), then used to register the points.
    """
    est, gt = _check(est, gt)
    pts = np.asarray(points, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    if pts.ndim != 3 or pts.shape[2] != 2 or pts.shape[0] != est.shape[0]:
        raise ValueError(f"points must be (K, N, 2) with K = {est.shape[0]}, got {pts.shape}")
    if valid.shape != pts.shape[:2]:
        raise ValueError(f"valid mask shape {valid.shape} != {pts.shape[:2]}")
    if not valid.any():
        raise ValueError("no valid point")
    aligned = align_poses_2d(est, gt)
    g_gt = se2.transform_points(gt, pts)
    g_est = se2.transform_points(aligned, pts)
    d = np.linalg.norm(g_est - g_gt, axis=-1)
    return float(d[valid].mean())


SUCCESS_PX = 20.0  # the paper's success criterion for 2D data (ATE in px, §4.1 / supplementary B)


def evaluate(est, gt, points, valid, unit_scale: float = 1.0, success_threshold: float | None = SUCCESS_PX) -> dict:
    """All metrics; lengths multiplied by ``unit_scale`` (ground-truth units such as px).

    Returns {"ate", "point_distance", "success" (ate < success_threshold, both in scaled
    units), "success_threshold", "rotation_rmse_deg", "rotation_max_deg", "num_scans"}: the keys
    of ``metrics3d.evaluate_3d``.
    """
    est, gt = _check(est, gt)
    a = ate(est, gt) * unit_scale
    success_threshold = SUCCESS_PX if success_threshold is None else success_threshold
    heading = heading_errors_deg(est, gt)
    return {
        "ate": a,
        "point_distance": point_distance(points, valid, est, gt) * unit_scale,
        "success": bool(a < success_threshold),
        "success_threshold": float(success_threshold),
        "rotation_rmse_deg": float(np.sqrt(np.mean(heading**2))),
        "rotation_max_deg": float(heading.max()),
        "num_scans": int(est.shape[0]),
    }
