"""Closed-form rigid alignment (Horn / Umeyama, no scale)."""

from __future__ import annotations

import numpy as np

from deepmapping.geometry import se2

__all__ = ["rigid_align", "align_poses_2d"]


def rigid_align(src, dst, weights=None) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid transform mapping ``src`` onto ``dst``.

    Minimises sum_i w_i ||R src_i + t - dst_i||^2 over proper rotations R (det +1) and
    translations t. src, dst: (M, D) with D = 2 or 3; weights: (M,) non-negative or None.
    Returns (R (D, D), t (D,)). With a single point (or all weight on one point) R = I.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape != dst.shape or src.shape[1] not in (2, 3):
        raise ValueError(f"src and dst must both be (M, 2|3), got {src.shape} and {dst.shape}")
    m, d = src.shape
    if m == 0:
        raise ValueError("rigid_align needs at least one point pair")
    if weights is None:
        w = np.full(m, 1.0 / m)
    else:
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        if w.shape != (m,) or (w < 0).any() or not np.isfinite(w).all():
            raise ValueError("weights must be (M,) finite and non-negative")
        total = w.sum()
        if total <= 0:
            raise ValueError("weights sum to zero")
        w = w / total
    mu_s = w @ src
    mu_d = w @ dst
    sc = src - mu_s
    dc = dst - mu_d
    cov = (dc * w[:, None]).T @ sc  # (D, D) = sum w (dst - mu_d)(src - mu_s)^T
    u, _, vt = np.linalg.svd(cov)
    fix = np.ones(d)
    fix[-1] = np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0
    rot = (u * fix) @ vt
    t = mu_d - rot @ mu_s
    return rot, t


def align_poses_2d(est, gt, return_transform: bool = False):
    """Rigidly align estimated poses onto ground truth using their positions.

    est, gt: (K, 3). The rigid transform (R, t) that best maps est positions onto gt
    positions is applied to the full estimated poses (positions and headings).
    Returns the aligned (K, 3) poses, or (aligned, (R, t)) when ``return_transform``.
    """
    est = np.asarray(est, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if est.ndim != 2 or est.shape[1] != 3 or est.shape != gt.shape:
        raise ValueError(f"est and gt must both be (K, 3), got {est.shape} and {gt.shape}")
    rot, t = rigid_align(est[:, :2], gt[:, :2])
    align = np.array([t[0], t[1], np.arctan2(rot[1, 0], rot[0, 0])])
    aligned = se2.compose(align, est)
    if return_transform:
        return aligned, (rot, t)
    return aligned
