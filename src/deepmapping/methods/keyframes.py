"""Every scan of a keyframed sequence placed: by odometry from its nearest keyframe
(``deepmapping.sequence``), then matched by ICP to the keyframes around it."""

from __future__ import annotations

import numpy as np

from deepmapping.data import FullSequence
from deepmapping.geometry import se2
from deepmapping.methods.icp import icp_2d
from deepmapping.methods.loop_closure import keyframe_submap
from deepmapping.sequence import nearest_keyframe, poses_for_all_scans

__all__ = ["place_all_scans", "refine_by_scan_matching"]


def place_all_scans(seq: FullSequence, keyframe_poses: np.ndarray) -> np.ndarray:
    """(S, 3): keyframes at ``keyframe_poses``, the others placed by odometry from their nearest
    keyframe, then (``seq.placement`` "icp") matched to that keyframe's scan. The last answer is
    cached on ``seq`` (the run folder and the relations score ask for the same poses)."""
    kp = np.asarray(keyframe_poses, dtype=np.float64)
    key = kp.tobytes()
    if seq.placed_cache[0] == key:
        return seq.placed_cache[1].copy()
    out = poses_for_all_scans(seq.keyframes, kp, seq.odometry, seq.timestamps)
    if seq.placement == "icp" and seq.points is not None:
        out = refine_by_scan_matching(out, seq.keyframes, seq.timestamps, seq.points, seq.valid)
    seq.placed_cache = (key, out)
    return out.copy()


def refine_by_scan_matching(poses: np.ndarray, keyframes: np.ndarray, timestamps: np.ndarray, points: np.ndarray,
                            valid: np.ndarray, max_shift: float = 0.3, max_turn_deg: float = 45.0,
                            submap: int = 1) -> np.ndarray:
    """Non-keyframes placed by point-to-line ICP against a submap of their nearest keyframe and
    its ``submap`` neighbours on each side (in the keyframes' poses), started from ``poses`` (the
    odometry placement). A match that moves a scan more than ``max_shift`` metres or
    ``max_turn_deg`` from its odometry placement is not trusted (the odometry pose is kept).
    Odometry turns are often off by 10-20 degrees within two seconds (wheel slip on the
    Freiburg logs), so the turn allowed is wide; its translation is good to a few cm."""
    out = np.array(poses, dtype=np.float64, copy=True)
    near = nearest_keyframe(keyframes, timestamps)
    is_key = np.zeros(len(out), bool)
    is_key[keyframes] = True
    key_points, key_valid, key_poses = points[keyframes], valid[keyframes], out[keyframes]
    targets: dict[int, np.ndarray] = {}
    for j in np.flatnonzero(~is_key):
        p = int(near[j])
        k = keyframes[p]
        if p not in targets:
            targets[p] = keyframe_submap(key_points, key_valid, key_poses, p, submap)
        guess = se2.relative(out[k], out[j])
        rel, info = icp_2d(points[j][valid[j]], targets[p], init=guess, method="plane")
        change = se2.relative(guess, rel)
        if info["fitness"] > 0.5 and np.hypot(change[0], change[1]) <= max_shift \
                and abs(np.degrees(change[2])) <= max_turn_deg:
            out[j] = se2.compose(out[k], rel)
    return out
