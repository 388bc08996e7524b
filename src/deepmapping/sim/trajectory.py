"""Random robot trajectories through the free space of a binary map (section 4.1 of the paper).

Each step turns by a rotation drawn uniformly in ±max_rotation and then moves along the new
heading by a distance drawn uniformly in [0.5, 1.5]·mean_step (mean ≈ mean_step; the paper
uses ±10° and 8.16 px). Every pose and every straight segment between poses keeps
``clearance_px`` of distance to the nearest obstacle pixel. When no random candidate fits,
the robot turns in place by at most max_rotation, always the same way, until a move fits.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["sample_trajectory", "clearance_map", "wrap_angle"]


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Wrap angles (radians) to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(a, dtype=np.float64), 2.0 * np.pi)


def clearance_map(occ: np.ndarray) -> np.ndarray:
    """Per pixel: Euclidean distance (px, centre to centre) to the nearest obstacle pixel; 0 on obstacles.

    Pixels outside the image count as obstacles (the image is padded by one obstacle ring).
    """
    free = np.asarray(occ) >= 128 if np.asarray(occ).dtype != bool else np.asarray(occ)
    padded = np.pad(free, 1, constant_values=False)
    return ndimage.distance_transform_edt(padded)[1:-1, 1:-1]


def _clear_at(dist: np.ndarray, xy: np.ndarray, clearance: float) -> np.ndarray:
    """True where the points ``xy`` (..., 2) lie in the image on a pixel with enough clearance."""
    h, w = dist.shape
    x, y = xy[..., 0], xy[..., 1]
    inside = (x >= 0) & (y >= 0) & (x < w) & (y < h)
    c = np.clip(np.floor(x).astype(np.int64), 0, w - 1)
    r = np.clip(np.floor(y).astype(np.int64), 0, h - 1)
    return inside & (dist[r, c] >= clearance)


def _segments_clear(
    dist: np.ndarray, start: np.ndarray, ends: np.ndarray, clearance: float, spacing: float = 0.5
) -> np.ndarray:
    """For each end point (M, 2): True when the whole segment start→end keeps the clearance."""
    length = np.linalg.norm(ends - start[None, :], axis=1)
    n = max(2, int(np.ceil(length.max() / spacing)) + 1) if len(ends) else 2
    s = np.linspace(0.0, 1.0, n)
    pts = start[None, None, :] + s[None, :, None] * (ends - start[None, :])[:, None, :]
    return _clear_at(dist, pts, clearance).all(axis=1)


def _escape_ok(
    dist: np.ndarray,
    ends: np.ndarray,
    headings: np.ndarray,
    clearance: float,
    turn: float,
    step: float,
    n_steps: int,
    sub: int = 4,
) -> np.ndarray:
    """(M,) bool: from each pose (end, heading) a left arc, right arc or straight run of
    ``n_steps`` steps (``step`` px, turning ``turn`` rad per step) keeps the clearance."""
    m = ends.shape[0]
    out = np.zeros(m, dtype=bool)
    if m == 0:
        return out
    i = np.arange(1, n_steps + 1, dtype=np.float64)
    frac = np.arange(1, sub + 1, dtype=np.float64) / sub
    for sign in (1.0, -1.0, 0.0):
        todo = ~out
        if not todo.any():
            break
        th = headings[todo, None] + sign * turn * i[None, :]
        seg = step * np.stack([np.cos(th), np.sin(th)], axis=-1)  # (M', n, 2)
        verts = ends[todo, None, :] + np.cumsum(seg, axis=1)
        prev = np.concatenate([ends[todo, None, :], verts[:, :-1]], axis=1)
        samples = prev[:, :, None, :] + frac[None, None, :, None] * seg[:, :, None, :]
        out[todo] = _clear_at(dist, samples, clearance).all(axis=(1, 2))
    return out


def _free_run(
    dist: np.ndarray, start: np.ndarray, direction: np.ndarray, horizon: float, clearance: float
) -> np.ndarray:
    """Distance (capped at ``horizon``) one can go from ``start`` along each ``direction`` (M, 2)."""
    s = np.arange(0.0, horizon + 0.25, 0.5)
    pts = start[None, None, :] + s[None, :, None] * direction[:, None, :]
    ok = _clear_at(dist, pts, clearance)
    blocked = ~ok
    first = np.where(blocked.any(axis=1), blocked.argmax(axis=1), s.size)
    return np.where(first < s.size, s[np.minimum(first, s.size - 1)], horizon)


def sample_trajectory(
    occ: np.ndarray,
    num_poses: int = 256,
    seed: int = 0,
    max_rotation_deg: float = 10.0,
    mean_step_px: float = 8.16,
    clearance_px: float = 8.0,
    num_candidates: int = 32,
    lookahead_steps: float = 8.0,
) -> np.ndarray:
    """Sample ``num_poses`` poses [x_px, y_px, theta] (K, 3) float64 in the free space of ``occ``.

    Start: a random pixel whose clearance is at least ``clearance_px + 1`` (uniform position
    within that pixel) and a random heading. Step: up to ``num_candidates`` random
    (rotation, translation) pairs are drawn; the first collision-free one from which an
    escape manoeuvre (a tightest-turn U-turn arc left or right, or a straight run) is also
    free is taken (a wide U-turn is tried first, so the robot starts turning early);
    failing that, the tightest turn (±max_rotation, 0.5·mean step) that keeps an escape;
    failing that, the collision-free candidate with the longest free run ahead (capped at
    ``lookahead_steps`` mean steps); if nothing is collision-free, the robot rotates in
    place by a random angle in [0.5, 1]·max_rotation in a persistent direction, so it never
    gets stuck. Every pose and segment keeps ``clearance_px`` (measured from the pose's pixel centre to obstacle pixel centres).
    Deterministic from ``seed``. Raises ValueError when no pixel has enough clearance.
    """
    if num_poses < 1:
        raise ValueError(f"num_poses must be >= 1, got {num_poses}")
    rng = np.random.default_rng(seed)
    dist = clearance_map(occ)
    start_cells = np.flatnonzero(dist.ravel() >= clearance_px + 1.0)
    if start_cells.size == 0:
        raise ValueError(f"no free pixel with clearance {clearance_px} px in the map")
    h, w = dist.shape
    cell = int(rng.choice(start_cells))
    x = cell % w + rng.uniform(0.0, 1.0)
    y = cell // w + rng.uniform(0.0, 1.0)
    theta = float(wrap_angle(rng.uniform(-np.pi, np.pi)))

    max_rot = np.deg2rad(max_rotation_deg)
    poses = np.empty((num_poses, 3), dtype=np.float64)
    poses[0] = (x, y, theta)
    horizon = max(lookahead_steps, 1.5) * mean_step_px
    # Escape manoeuvre: the tightest turn the step model allows.
    esc_turn = max_rot
    esc_step = 0.5 * mean_step_px
    esc_steps = int(np.ceil(np.pi / max(esc_turn, 1e-3))) + 1 if esc_turn > 0 else 1
    esc_steps = min(esc_steps, 64)
    wide_turn = 0.75 * max_rot
    wide_step = mean_step_px
    wide_steps = min(int(np.ceil(np.pi / max(wide_turn, 1e-3))) + 1 if wide_turn > 0 else 1, 64)
    turn_sign = 0.0  # persistent in-place turning direction while blocked
    for k in range(1, num_poses):
        pos = poses[k - 1, :2]
        th = poses[k - 1, 2]
        rot = rng.uniform(-max_rot, max_rot, size=num_candidates)
        step = rng.uniform(0.5, 1.5, size=num_candidates) * mean_step_px
        heading = th + rot
        direction = np.stack([np.cos(heading), np.sin(heading)], axis=1)
        ends = pos[None, :] + step[:, None] * direction
        ok = _segments_clear(dist, pos, ends, clearance_px)
        # 1. The first (random) collision-free candidate from which the robot can still
        #    escape (U-turn left/right or go straight on) without stopping: first with a
        #    wide, comfortable U-turn (so it starts turning early), then with the tightest.
        chosen = -1
        for turn, step_len, n_arc in ((wide_turn, wide_step, wide_steps), (esc_turn, esc_step, esc_steps)):
            safe = ok.copy()
            safe[ok] = _escape_ok(dist, ends[ok], heading[ok], clearance_px, turn, step_len, n_arc)
            if safe.any():
                chosen = int(np.flatnonzero(safe)[0])
                break
        if chosen >= 0:
            poses[k] = (ends[chosen, 0], ends[chosen, 1], float(wrap_angle(heading[chosen])))
            turn_sign = 0.0
            continue
        # 2. The tightest allowed turns (rotation ±max, shortest step), in random order:
        #    the first step of an escape arc that was checked at an earlier pose.
        esc_heading = th + (esc_turn if rng.random() < 0.5 else -esc_turn) * np.array([1.0, -1.0])
        esc_dir = np.stack([np.cos(esc_heading), np.sin(esc_heading)], axis=1)
        esc_ends = pos[None, :] + esc_step * esc_dir
        esc_ok = _segments_clear(dist, pos, esc_ends, clearance_px)
        esc_ok[esc_ok] = _escape_ok(
            dist, esc_ends[esc_ok], esc_heading[esc_ok], clearance_px, esc_turn, esc_step, esc_steps
        )
        if esc_ok.any():
            j = int(np.flatnonzero(esc_ok)[0])
            poses[k] = (esc_ends[j, 0], esc_ends[j, 1], float(wrap_angle(esc_heading[j])))
            turn_sign = 0.0
            continue
        # 3. Any collision-free candidate: the one with the longest free run ahead.
        if ok.any():
            free_run = _free_run(dist, pos, direction, horizon, clearance_px)
            score = np.where(ok, free_run, -1.0)
            j = int(np.flatnonzero(score >= score.max())[0])
            poses[k] = (ends[j, 0], ends[j, 1], float(wrap_angle(heading[j])))
            turn_sign = 0.0
            continue
        # 4. Blocked: turn in place, always the same way until a move fits.
        if turn_sign == 0.0:
            turn_sign = 1.0 if rng.random() < 0.5 else -1.0
        dth = turn_sign * rng.uniform(0.5, 1.0) * max_rot
        poses[k] = (pos[0], pos[1], float(wrap_angle(th + dth)))
    return poses
