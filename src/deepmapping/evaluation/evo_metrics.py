"""Trajectory metrics through evo's Python API (Grupp, github.com/MichaelGrupp/evo; GPL-3.0, a
dependency, nothing copied): APE with SE(3) or Sim(3) alignment, and RPE.

evo is the tool SLAM papers report with, so these numbers can be compared to theirs directly.
APE (translation part, SE(3) alignment) is the same quantity as our ATE: the RMSE of positions
after a closed-form rigid alignment (tests/test_evo.py checks they agree). 2D poses (K, 3) are
lifted to the z = 0 plane.
"""

from __future__ import annotations

import numpy as np

from deepmapping.geometry import se2

__all__ = ["to_trajectory", "ape", "rpe", "evo_metrics"]


def _matrices(poses) -> np.ndarray:
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim == 2 and p.shape[1] == 3:
        return se2.to_se3(p)
    if p.ndim == 3 and p.shape[1:] == (4, 4):
        return p
    raise ValueError(f"poses must be (K, 3) [x, y, theta] or (K, 4, 4), got {p.shape}")


def to_trajectory(poses, timestamps=None):
    """An evo PoseTrajectory3D (timestamps default to the index)."""
    from evo.core.trajectory import PoseTrajectory3D

    m = _matrices(poses)
    ts = np.arange(len(m), dtype=np.float64) if timestamps is None else np.asarray(timestamps, dtype=np.float64)
    return PoseTrajectory3D(poses_se3=list(m), timestamps=ts)


def _stats(result) -> dict:
    return {k: float(v) for k, v in result.stats.items()}


def ape(est, gt, align: str = "se3", relation: str = "translation") -> dict:
    """evo APE stats (rmse, mean, median, std, min, max, sse); ``align``: se3 | sim3 | none;
    ``relation``: translation (units of the poses) | rotation (deg)."""
    from evo.core.metrics import PoseRelation
    from evo.main_ape import ape as evo_ape

    if align not in ("se3", "sim3", "none"):
        raise ValueError(f"align must be se3, sim3 or none, got {align!r}")
    rel = {"translation": PoseRelation.translation_part, "rotation": PoseRelation.rotation_angle_deg}[relation]
    result = evo_ape(to_trajectory(gt), to_trajectory(est), rel, align=align != "none", correct_scale=align == "sim3")
    return _stats(result)


def rpe(est, gt, delta: int = 1, relation: str = "translation") -> dict:
    """evo RPE stats between poses ``delta`` frames apart (translation in the poses' units, or deg)."""
    from evo.core.metrics import PoseRelation, Unit
    from evo.main_rpe import rpe as evo_rpe

    rel = {"translation": PoseRelation.translation_part, "rotation": PoseRelation.rotation_angle_deg}[relation]
    result = evo_rpe(to_trajectory(gt), to_trajectory(est), rel, delta=delta, delta_unit=Unit.frames, all_pairs=False)
    return _stats(result)


def evo_metrics(est, gt, unit_scale: float = 1.0) -> dict:
    """The usual evo summary (RMSE, lengths times ``unit_scale``): APE SE(3) and Sim(3), RPE over 1 frame.

    An entry evo cannot compute is None (its Umeyama alignment refuses degenerate positions,
    e.g. every pose at one place, or a turn in place; our own ATE handles those).
    """
    from evo import EvoException

    def rmse(fn, *args, scale=1.0, **kwargs):
        try:
            return fn(*args, **kwargs)["rmse"] * scale
        except EvoException:
            return None

    s = float(unit_scale)
    return {
        "ape_se3_rmse": rmse(ape, est, gt, "se3", scale=s),
        "ape_sim3_rmse": rmse(ape, est, gt, "sim3", scale=s),
        "ape_rot_se3_rmse_deg": rmse(ape, est, gt, "se3", "rotation"),
        "rpe_trans_rmse": rmse(rpe, est, gt, scale=s),
        "rpe_rot_rmse_deg": rmse(rpe, est, gt, relation="rotation"),
    }
