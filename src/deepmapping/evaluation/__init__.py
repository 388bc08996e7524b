"""Scoring a registration: ATE, point distance, rotation error (2D and 3D), evo, relation scores."""

from __future__ import annotations

import numpy as np

from deepmapping.evaluation.metrics import ate as ate_2d
from deepmapping.evaluation.metrics import evaluate as evaluate_2d
from deepmapping.evaluation.metrics3d import ate_3d, evaluate_3d

__all__ = ["ate", "evaluate"]


def ate(est, gt) -> float:
    """ATE (RMSE of positions after the closed-form rigid alignment) of 2D poses (K, 3) or 3D
    poses (K, 4, 4), in the poses' units."""
    return ate_3d(est, gt) if np.asarray(gt).ndim == 3 else ate_2d(est, gt)


def evaluate(est, gt, points, valid, unit_scale: float = 1.0, success_threshold: float | None = None,
             avd_protocol: bool = False) -> dict:
    """The paper's metrics of 2D (``points`` (K, N, 2), poses (K, 3)) or 3D (``points`` (K, N, 3),
    poses (K, 4, 4)) registrations, with the same keys: ate, point_distance (both times
    ``unit_scale``), success, success_threshold (None: 20 px in 2D; 3D: 450 mm for the AVD protocol,
    else 2 % of the typical range), rotation_rmse_deg, rotation_max_deg, num_scans."""
    if np.asarray(points).shape[-1] == 3:
        return evaluate_3d(est, gt, points, valid, unit_scale=unit_scale, success_threshold=success_threshold,
                           avd_protocol=avd_protocol)
    return evaluate_2d(est, gt, points, valid, unit_scale=unit_scale, success_threshold=success_threshold)
