"""Ideal 2D lidar: exact ray casting through a binary occupancy image (Amanatides–Woo DDA).

Image frame (see docs/conventions.md): pixel (row r, col c) covers x in [c, c+1),
y in [r, r+1); value < 128 is an obstacle (0 = black), >= 128 is free (255 = white).
A ray stops where it first enters an obstacle pixel square; the returned hit is the exact
intersection of the ray with that square's boundary (the crossed coordinate is set to the
integer grid line exactly, the other one is interpolated). The outside of the image is
treated as an obstacle, so a ray that leaves the image returns the point where it crosses
the image border (this is the paper's "unlimited range" behaviour). With ``max_range``, a
beam whose first hit lies farther than ``max_range`` pixels is invalid.

Beam j of a scan with B beams points at angle ``2*pi*j/B`` in the sensor frame, i.e. at
global angle ``theta + 2*pi*j/B`` for a sensor pose ``[x, y, theta]``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["cast_rays", "beam_angles", "simulate_scan", "simulate_scans"]


def beam_angles(num_beams: int) -> np.ndarray:
    """Sensor-frame angles ``2*pi*j/num_beams``, j = 0..num_beams-1 (float64)."""
    if num_beams < 1:
        raise ValueError(f"num_beams must be >= 1, got {num_beams}")
    return 2.0 * np.pi * np.arange(num_beams, dtype=np.float64) / num_beams


def _obstacle_mask(occ: np.ndarray) -> np.ndarray:
    occ = np.asarray(occ)
    if occ.ndim != 2 or occ.shape[0] < 1 or occ.shape[1] < 1:
        raise ValueError(f"occupancy image must be a non-empty 2D array, got shape {occ.shape}")
    if occ.dtype == bool:
        return ~occ  # True = free
    return occ < 128


def _check_origins(obst: np.ndarray, origins: np.ndarray) -> None:
    h, w = obst.shape
    x, y = origins[:, 0], origins[:, 1]
    if not (np.isfinite(origins).all()):
        raise ValueError("sensor position contains NaN or inf")
    outside = (x < 0) | (y < 0) | (x >= w) | (y >= h)
    if outside.any():
        k = int(np.flatnonzero(outside)[0])
        raise ValueError(f"sensor position {origins[k].tolist()} lies outside the {w}x{h} image")
    inside = obst[np.floor(y).astype(np.int64), np.floor(x).astype(np.int64)]
    if inside.any():
        k = int(np.flatnonzero(inside)[0])
        raise ValueError(f"sensor position {origins[k].tolist()} lies inside an obstacle")


def cast_rays(
    occ: np.ndarray,
    origins: np.ndarray,
    angles: np.ndarray,
    max_range: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cast rays from ``origins`` (R, 2) px at global ``angles`` (R,) rad; fully vectorised.

    Returns ``(hits, ranges, valid)``: ``hits`` (R, 2) float64 global hit points in px,
    exactly on an obstacle-pixel (or image) boundary (one coordinate is an exact integer);
    ``ranges`` (R,) distance from the origin to the hit; ``valid`` (R,) bool, False when
    the first hit is farther than ``max_range`` (then hit = origin, range = inf).
    Raises ValueError when an origin is outside the image or inside an obstacle.
    """
    obst = _obstacle_mask(occ)
    h, w = obst.shape
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 2)
    angles = np.asarray(angles, dtype=np.float64).reshape(-1)
    if origins.shape[0] != angles.shape[0]:
        raise ValueError(f"{origins.shape[0]} origins for {angles.shape[0]} angles")
    _check_origins(obst, origins)
    n = angles.shape[0]
    limit = np.inf if max_range is None else float(max_range)
    if not limit > 0:
        raise ValueError(f"max_range must be > 0, got {max_range}")

    # Padded flat obstacle grid: one ring of obstacle cells around the image, so that
    # leaving the image is "entering an obstacle" at the border line.
    pad = np.ones((h + 2, w + 2), dtype=bool)
    pad[1:-1, 1:-1] = obst
    flat = pad.ravel()
    stride = w + 2

    ox, oy = origins[:, 0], origins[:, 1]
    dx, dy = np.cos(angles), np.sin(angles)
    ix = np.floor(ox).astype(np.int64)
    iy = np.floor(oy).astype(np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        tdx = np.where(dx != 0, 1.0 / np.abs(dx), np.inf)
        tdy = np.where(dy != 0, 1.0 / np.abs(dy), np.inf)
        tmx = np.where(dx > 0, (ix + 1 - ox) * tdx, np.where(dx < 0, (ox - ix) * tdx, np.inf))
        tmy = np.where(dy > 0, (iy + 1 - oy) * tdy, np.where(dy < 0, (oy - iy) * tdy, np.inf))
    sx = np.where(dx > 0, 1, -1).astype(np.int64)
    sy = np.where(dy > 0, 1, -1).astype(np.int64)
    # Cell index in the padded grid and its increments.
    cell = (iy + 1) * stride + (ix + 1)
    cx_step = sx
    cy_step = sy * stride

    hit_t = np.full(n, np.inf)
    hit_axis = np.zeros(n, dtype=np.int8)  # 0: crossed a vertical line x = const, 1: horizontal
    hit_line = np.zeros(n, dtype=np.float64)  # the integer grid line crossed
    gx = ix.copy()  # current column (image coordinates)
    gy = iy.copy()
    idx = np.arange(n)

    # Every step moves to a neighbouring cell; a ray crosses at most w + h + 2 lines.
    for _ in range(w + h + 4):
        if idx.size == 0:
            break
        stepx = tmx <= tmy
        t = np.where(stepx, tmx, tmy)
        # Line crossed: for x steps, the boundary between old and new column.
        line = np.where(stepx, np.where(sx > 0, gx + 1, gx), np.where(sy > 0, gy + 1, gy))
        gx = gx + np.where(stepx, sx, 0)
        gy = gy + np.where(stepx, 0, sy)
        cell = cell + np.where(stepx, cx_step, cy_step)
        tmx = np.where(stepx, tmx + tdx, tmx)
        tmy = np.where(stepx, tmy, tmy + tdy)
        hit = flat[cell]
        over = t > limit
        done = hit | over
        if done.any():
            d_idx = idx[done]
            got = hit[done] & ~over[done]
            hit_t[d_idx[got]] = t[done][got]
            hit_axis[d_idx[got]] = np.where(stepx[done][got], 0, 1)
            hit_line[d_idx[got]] = line[done][got]
            keep = ~done
            idx = idx[keep]
            tmx, tmy, tdx, tdy = tmx[keep], tmy[keep], tdx[keep], tdy[keep]
            sx, sy, cx_step, cy_step = sx[keep], sy[keep], cx_step[keep], cy_step[keep]
            gx, gy, cell = gx[keep], gy[keep], cell[keep]
    if idx.size:  # cannot happen: the padded ring stops every ray
        raise RuntimeError("ray casting did not terminate")

    valid = np.isfinite(hit_t)
    hits = origins.copy()
    axis = hit_axis[valid]
    ln = hit_line[valid]
    ovx, ovy, dvx, dvy = ox[valid], oy[valid], dx[valid], dy[valid]
    # Recompute t from the crossed grid line (no accumulated rounding from the DDA sums).
    with np.errstate(divide="ignore", invalid="ignore"):
        tv = np.where(axis == 0, (ln - ovx) / dvx, (ln - ovy) / dvy)
    tv = np.maximum(tv, 0.0)
    hits[valid, 0] = np.where(axis == 0, ln, ovx + tv * dvx)
    hits[valid, 1] = np.where(axis == 1, ln, ovy + tv * dvy)
    hit_t[valid] = tv
    return hits, hit_t, valid


def simulate_scans(
    occ: np.ndarray,
    poses_px: np.ndarray,
    num_beams: int = 256,
    max_range: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Scan from every pose ``[x_px, y_px, theta]`` of ``poses_px`` (K, 3) at once.

    Returns ``(points, valid)``: ``points`` (K, num_beams, 2) float64 in each SENSOR frame
    (px), point j = beam j at sensor angle ``2*pi*j/num_beams``; ``valid`` (K, num_beams)
    bool. Invalid beams (nothing within ``max_range``) are (0, 0). ``max_range=None`` is
    the unlimited ideal scanner (rays leaving the image return the border crossing).
    Raises ValueError when a sensor lies outside the image or inside an obstacle.
    """
    poses = np.asarray(poses_px, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3:
        raise ValueError(f"poses must be (K, 3) [x, y, theta], got shape {poses.shape}")
    k = poses.shape[0]
    a = beam_angles(num_beams)
    origins = np.repeat(poses[:, :2], num_beams, axis=0)
    angles = (poses[:, 2:3] + a[None, :]).reshape(-1)
    _, ranges, valid = cast_rays(occ, origins, angles, max_range)
    ranges = np.where(valid, ranges, 0.0).reshape(k, num_beams)
    valid = valid.reshape(k, num_beams)
    points = np.stack([ranges * np.cos(a)[None, :], ranges * np.sin(a)[None, :]], axis=-1)
    return points, valid


def simulate_scan(
    occ: np.ndarray,
    pose_px: np.ndarray,
    num_beams: int = 256,
    max_range: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """One scan from ``pose_px`` = [x_px, y_px, theta]: ``(points (N, 2) float64 sensor frame, valid (N,))``.

    See :func:`simulate_scans` for conventions.
    """
    pose = np.asarray(pose_px, dtype=np.float64).reshape(1, 3)
    points, valid = simulate_scans(occ, pose, num_beams, max_range)
    return points[0], valid[0]
