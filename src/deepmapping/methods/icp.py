"""2D ICP (point-to-point and point-to-plane) and incremental ICP over a scan sequence.

Scale-aware: with ``max_correspondence_distance=None`` the inlier threshold adapts to the
data (``trim`` x median correspondence distance, floored at twice the median point spacing
of the target), so the same defaults work for px/512 units and for metres.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from deepmapping.geometry import se2
from deepmapping.geometry.alignment import rigid_align
from deepmapping.geometry.normals import pca_normals

__all__ = ["icp_2d", "incremental_icp", "overlap"]


def _clean(points, name: str) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"{name} must be (N, 2), got {pts.shape}")
    return pts[np.isfinite(pts).all(axis=1)]


def icp_2d(
    source,
    target,
    init=(0.0, 0.0, 0.0),
    method: str = "point",
    max_iterations: int = 50,
    max_correspondence_distance: float | None = None,
    tolerance: float = 1e-7,
    trim: float | None = 3.0,
    normal_k: int = 6,
    prior_sigma: tuple[float, float] | None = None,
    point_sigma: float = 0.03,
    target_origins=None,
) -> tuple[np.ndarray, dict]:
    """Register ``source`` (N, 2) onto ``target`` (M, 2); returns (pose (3,), info).

    The pose T satisfies target ≈ T(source) (i.e. it is the pose of the source frame in
    the target frame). ``method``: "point" (point-to-point, closed-form SVD) or "plane"
    (point-to-line with target normals from ``normal_k`` nearest neighbours, Gauss-Newton).
    Correspondences: nearest target point, kept if within ``max_correspondence_distance``
    (None = adaptive) and within ``trim`` x the median correspondence distance (None = off).
    Stops when the pose update is below ``tolerance`` (translation measured relative to the
    target's RMS radius, angle in radians). Non-finite points are ignored.
    ``prior_sigma`` = (sigma_t, sigma_theta) ("plane" only): ``init`` is also a measurement
    (e.g. odometry) with these standard deviations, against point-to-line residuals of
    ``point_sigma``: where the scans leave a direction unconstrained (a straight corridor),
    the pose stays near ``init`` instead of sliding.
    ``target_origins`` (M, 2): the sensor position each target point was seen from; then a pair is
    kept only where both sensors see the surface from the same side (the target point's normal
    against each one's line of sight; the source's sensor at its frame's origin): the two faces of a
    wall seen from two rooms are not matched to each other.
    info: fitness (fraction of source points with an inlier correspondence), rmse (RMS
    inlier point-to-point distance), iterations, converged.
    """
    if method not in ("point", "plane"):
        raise ValueError(f"method must be 'point' or 'plane', got {method!r}")
    if prior_sigma is not None and method != "plane":
        raise ValueError("prior_sigma needs method='plane'")
    src = _clean(source, "source")
    if target_origins is not None:
        finite = np.isfinite(np.asarray(target, dtype=np.float64)).all(axis=1)
        target_origins = np.asarray(target_origins, dtype=np.float64)[finite]
    tgt = _clean(target, "target")
    pose = np.asarray(init, dtype=np.float64).reshape(3).copy()
    prior0 = pose.copy()
    info = {"fitness": 0.0, "rmse": float("inf"), "iterations": 0, "converged": False}
    if src.shape[0] < 3 or tgt.shape[0] < 3:
        return pose, info

    tree = cKDTree(tgt)
    spacing_d, _ = tree.query(tgt, k=2)
    spacing = float(np.median(spacing_d[:, 1]))
    scale = float(np.sqrt(np.mean(np.sum((tgt - tgt.mean(0)) ** 2, axis=1)))) or 1.0
    floor = 2.0 * spacing
    normals = pca_normals(tgt, normal_k, tree) if method == "plane" or target_origins is not None else None
    facing = None if target_origins is None else np.sign(np.sum(normals * (tgt - target_origins), axis=1))

    def correspond(p):
        moved = se2.transform_points(p, src)
        d, j = tree.query(moved)
        keep = np.isfinite(d)
        if max_correspondence_distance is not None:
            keep &= d <= max_correspondence_distance
        if trim is not None and keep.any():
            thr = trim * float(np.median(d[keep]))
            if max_correspondence_distance is None:
                thr = max(thr, floor)
            keep &= d <= thr
        if facing is not None:
            keep &= np.sign(np.sum(normals[j] * (moved - p[:2]), axis=1)) == facing[j]
        return moved, d, j, keep

    for it in range(1, max_iterations + 1):
        moved, d, j, keep = correspond(pose)
        if keep.sum() < 3:
            break
        if method == "point":
            rot, t = rigid_align(moved[keep], tgt[j[keep]])
            delta = np.array([t[0], t[1], np.arctan2(rot[1, 0], rot[0, 0])])
        else:
            p = moved[keep]
            q = tgt[j[keep]]
            n = normals[j[keep]]
            jac = np.column_stack([n[:, 0], n[:, 1], p[:, 0] * n[:, 1] - p[:, 1] * n[:, 0]])
            res = np.sum(n * (p - q), axis=1)
            # Gauss-Newton about the origin of the target frame; tiny damping for degeneracy
            # (e.g. a straight corridor) keeps the unobservable direction at zero.
            jac_s = jac.copy()
            jac_s[:, 2] /= scale  # unknown u = dtheta * scale, in length units like dx, dy
            h = jac_s.T @ jac_s
            g = jac_s.T @ res
            if prior_sigma is not None:
                h_p, g_p = _prior_terms(pose, prior0, prior_sigma, point_sigma, scale)
                h, g = h + h_p, g + g_p
            h += np.eye(3) * (1e-9 * np.trace(h) + 1e-300)
            x = np.linalg.solve(h, -g)
            delta = np.array([x[0], x[1], x[2] / scale])
        pose = se2.compose(delta, pose)
        info["iterations"] = it
        step = np.hypot(delta[0], delta[1]) / scale + abs(delta[2])
        if step < tolerance:
            info["converged"] = True
            break

    moved, d, j, keep = correspond(pose)
    info["fitness"] = float(keep.mean())
    info["rmse"] = float(np.sqrt(np.mean(d[keep] ** 2))) if keep.any() else float("inf")
    return pose, info


def _prior_terms(pose, prior, sigma, point_sigma, scale):
    """Normal-equation terms of the prior (pose - prior) / sigma, in point_sigma units, for the
    update delta = (dx, dy, dtheta * scale) applied on the left of ``pose``."""
    err = pose - prior
    err[2] = (err[2] + np.pi) % (2 * np.pi) - np.pi
    a = np.array([[1.0, 0.0, -pose[1] / scale], [0.0, 1.0, pose[0] / scale], [0.0, 0.0, 1.0 / scale]])
    w = np.diag([(point_sigma / sigma[0]) ** 2] * 2 + [(point_sigma / sigma[1]) ** 2])
    return a.T @ w @ a, a.T @ w @ err


def overlap(pose, source, target, radius_factor: float = 3.0) -> float:
    """Fraction of ``source`` points within ``radius_factor`` x the target's median point spacing
    of a ``target`` point once moved by ``pose``: a fit score that, unlike ICP's adaptive
    inlier threshold, does not grow with the misfit."""
    return _overlap_scorer(source, target, radius_factor)(pose)


def _overlap_scorer(source, target, radius_factor: float = 3.0) -> Callable[[np.ndarray], float]:
    """:func:`overlap` of many poses of one pair: the target's tree and spacing built once."""
    src, tgt = _clean(source, "source"), _clean(target, "target")
    if src.shape[0] == 0 or tgt.shape[0] < 2:
        return lambda pose: 0.0
    tree = cKDTree(tgt)
    radius = radius_factor * float(np.median(tree.query(tgt, k=2)[0][:, 1]))
    return lambda pose: float(np.mean(tree.query(se2.transform_points(np.asarray(pose, np.float64), src))[0]
                                      <= radius))


def _recover(rel, prev, src, tgt, method, margin, icp_kwargs) -> np.ndarray:
    """ICP from the constant-velocity guess can land in a wrong basin (e.g. slide along a
    corridor) and, fed forward as the next guess, run away. Also try the identity and a
    bounded, untrimmed ICP; keep one only if its :func:`overlap` beats ``rel``'s by ``margin``."""
    src, tgt = _clean(src, "source"), _clean(tgt, "target")
    if src.shape[0] < 3 or tgt.shape[0] < 3:
        return rel
    scale = float(np.sqrt(np.mean(np.sum((tgt - tgt.mean(0)) ** 2, axis=1)))) or 1.0
    bound = min(0.25 * scale, icp_kwargs.get("max_correspondence_distance") or np.inf)
    bounded = icp_kwargs | {"trim": None, "max_correspondence_distance": bound}
    cands = [rel, icp_2d(src, tgt, init=np.zeros(3), method=method, **icp_kwargs)[0],
             icp_2d(src, tgt, init=prev, method=method, **bounded)[0]]
    score = _overlap_scorer(src, tgt)
    scores = [score(c) for c in cands]
    best = int(np.argmax(scores))
    return cands[best] if scores[best] > scores[0] + margin else rel


def incremental_icp(
    points,
    valid,
    method: str = "point",
    init: str = "velocity",
    progress: Callable[[int, int], None] | None = None,
    initial_poses: np.ndarray | None = None,
    recover_margin: float | None = 0.05,
    **icp_kwargs,
) -> np.ndarray:
    """Incremental (frame-to-frame) ICP over an ordered scan sequence.

    points (K, N, 2), valid (K, N). Scan i is registered to scan i-1 and the relative
    motions are chained with :func:`se2.chain`; pose 0 is the identity. ``init``:
    "velocity" (previous relative motion, constant-velocity guess), "identity", or "best"
    (run both, keep the higher fitness, then lower rmse). With "velocity", each pair is also
    registered from the identity and with a bounded untrimmed ICP, and one of those replaces
    the velocity result when its :func:`overlap` is higher by ``recover_margin`` (None: off),
    which stops a pair in a wrong basin from running the chain away. ``progress(i, K)`` is
    called after each registered scan. ``initial_poses`` (K, 3), e.g. odometry: each pair
    starts from its relative motion there (``init`` is then ignored) and pose 0 is
    ``initial_poses[0]``. Extra keyword arguments go to :func:`icp_2d`. Returns (K, 3).
    """
    if init not in ("velocity", "identity", "best"):
        raise ValueError(f"init must be 'velocity', 'identity' or 'best', got {init!r}")
    pts = np.asarray(points, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    if pts.ndim != 3 or pts.shape[2] != 2:
        raise ValueError(f"points must be (K, N, 2), got {pts.shape}")
    if valid.shape != pts.shape[:2]:
        raise ValueError(f"valid mask shape {valid.shape} != {pts.shape[:2]}")
    k = pts.shape[0]
    rels = np.zeros((max(k - 1, 0), 3))
    prev = np.zeros(3)
    for i in range(1, k):
        src = pts[i][valid[i]]
        tgt = pts[i - 1][valid[i - 1]]
        if initial_poses is not None:
            guess = se2.relative(initial_poses[i - 1], initial_poses[i])
            rel, _ = icp_2d(src, tgt, init=guess, method=method, **icp_kwargs)
        elif init == "identity":
            rel, _ = icp_2d(src, tgt, init=np.zeros(3), method=method, **icp_kwargs)
        elif init == "velocity":
            rel, _ = icp_2d(src, tgt, init=prev, method=method, **icp_kwargs)
            if recover_margin is not None:
                rel = _recover(rel, prev, src, tgt, method, recover_margin, icp_kwargs)
        else:
            cands = [icp_2d(src, tgt, init=g, method=method, **icp_kwargs) for g in (prev, np.zeros(3))]
            rel, _ = max(cands, key=lambda c: (round(c[1]["fitness"], 6), -c[1]["rmse"]))
        rels[i - 1] = rel
        prev = rel
        if progress is not None:
            progress(i, k)
    first = None if initial_poses is None else np.asarray(initial_poses, np.float64)[0]
    return se2.chain(rels, first)
