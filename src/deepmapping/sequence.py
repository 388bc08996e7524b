"""Keyframes of a long 2D sequence, and a pose for every scan from the keyframes' poses by odometry.

A keyframe spec is a string:

- ``"all"``: every scan;
- ``"every:K"``: scans 0, K, 2K, ...;
- ``"motion:D,A"``: a new keyframe once the odometry has moved D metres or turned A degrees
  since the last keyframe (the usual choice for logs where the robot often stands still);
- ``"time:S"``: a new keyframe once S seconds have passed since the last one.

The first scan is always a keyframe. Non-keyframes are placed by odometry relative to their
nearest keyframe (in time): T_j = T_k · inv(O_k) · O_j, so every scan of the input gets a pose
(``methods.keyframes`` then matches them to the keyframes around it).
"""

from __future__ import annotations

import numpy as np

from deepmapping.errors import ConfigError
from deepmapping.geometry import se2

__all__ = ["parse_keyframes", "select_keyframes", "nearest_keyframe", "poses_for_all_scans"]


def parse_keyframes(spec: str) -> tuple[str, tuple[float, ...]]:
    kind, _, args = str(spec).partition(":")
    try:
        values = tuple(float(a) for a in args.split(",")) if args else ()
    except ValueError:
        values = None
    arity = {"all": 0, "every": 1, "motion": 2, "time": 1}
    if kind not in arity or values is None or len(values) != arity[kind] or any(v < 0 for v in values) \
            or (kind == "every" and (values[0] < 1 or values[0] != int(values[0]))):
        raise ConfigError(f"keyframes must be 'all', 'every:K' (K >= 1), 'motion:METRES,DEGREES' or "
                          f"'time:SECONDS', got {spec!r}")
    return kind, values


def select_keyframes(spec: str, odometry: np.ndarray, timestamps: np.ndarray) -> np.ndarray:
    """Indices (increasing, starting at 0) of the keyframes among S scans with odometry (S, 3)."""
    kind, values = parse_keyframes(spec)
    s = len(odometry)
    if kind == "all":
        return np.arange(s)
    if kind == "every":
        return np.arange(0, s, int(values[0]))
    keep, last = [0], 0
    for k in range(1, s):
        if kind == "time":
            new = timestamps[k] - timestamps[last] >= values[0]
        else:
            rel = se2.relative(odometry[last], odometry[k])
            new = np.hypot(rel[0], rel[1]) >= values[0] or abs(np.degrees(rel[2])) >= values[1]
        if new:
            keep.append(k)
            last = k
    return np.array(keep)


def nearest_keyframe(keyframes: np.ndarray, timestamps: np.ndarray) -> np.ndarray:
    """For each of the S scans, the position (in ``keyframes``) of the keyframe nearest in time."""
    kf_t = timestamps[keyframes]
    after = np.clip(np.searchsorted(kf_t, timestamps), 1, max(len(keyframes) - 1, 1))
    before = after - 1
    if len(keyframes) == 1:
        return np.zeros(len(timestamps), dtype=int)
    return np.where(np.abs(timestamps - kf_t[before]) <= np.abs(kf_t[after] - timestamps), before, after)


def poses_for_all_scans(keyframes: np.ndarray, keyframe_poses: np.ndarray, odometry: np.ndarray,
                        timestamps: np.ndarray) -> np.ndarray:
    """(S, 3) poses: keyframes get ``keyframe_poses``, every other scan its nearest keyframe's pose
    composed with the odometry motion from that keyframe to the scan."""
    near = nearest_keyframe(keyframes, timestamps)
    anchor = keyframes[near]
    motion = se2.relative(odometry[anchor], odometry)
    out = se2.compose(np.asarray(keyframe_poses, np.float64)[near], motion)
    out[keyframes] = keyframe_poses
    return out
