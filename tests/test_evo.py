"""evo's APE/RPE (through its Python API) next to our ATE: the same quantity, the same number."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deepmapping.api import evaluate_poses
from deepmapping.data import ScanSet
from deepmapping.evaluation.evo_metrics import ape, evo_metrics, rpe
from deepmapping.evaluation.metrics import ate
from deepmapping.evaluation.metrics3d import ate_3d
from deepmapping.geometry import se2, se3


def _traj2d(seed=0, k=40):
    rng = np.random.default_rng(seed)
    gt = se2.chain(rng.normal([0.3, 0.0, 0.1], 0.1, (k - 1, 3)))
    est = se2.compose(np.array([2.0, 1.0, 0.5]), gt) + rng.normal(0, 0.05, gt.shape)
    return est, gt


def test_ape_equals_our_ate_2d_and_3d():
    est, gt = _traj2d()
    assert ape(est, gt)["rmse"] == pytest.approx(ate(est, gt), rel=1e-9)
    rng = np.random.default_rng(1)
    g3 = np.stack([se3.from_rt(Rotation.from_rotvec(rng.normal(0, 0.5, 3)).as_matrix(), rng.normal(0, 2, 3))
                   for _ in range(30)])
    e3 = g3.copy()
    e3[:, :3, 3] += rng.normal(0, 0.1, (30, 3))
    e3 = se3.compose(se3.from_rt(Rotation.from_rotvec([0.3, 0.2, 1.0]).as_matrix(), [1, 2, 3]), e3)
    assert ape(e3, g3)["rmse"] == pytest.approx(ate_3d(e3, g3), rel=1e-9)
    assert ape(e3, g3, align="none")["rmse"] > 1.0  # no alignment: the rigid offset counts


def test_sim3_and_rpe():
    _, gt = _traj2d(2)
    scaled = gt.copy()
    scaled[:, :2] *= 1.7
    assert ape(scaled, gt, "se3")["rmse"] > 0.5 and ape(scaled, gt, "sim3")["rmse"] < 1e-9
    moved = se2.compose(np.array([-3.0, 4.0, 2.0]), gt)  # a rigid move: no relative error
    assert rpe(moved, gt)["rmse"] < 1e-9 and rpe(moved, gt, relation="rotation")["rmse"] < 1e-6
    bent = gt.copy()
    bent[20:] = se2.compose(se2.compose(gt[20], np.array([0.0, 0.0, 0.1])), se2.relative(gt[20], gt[20:]))
    assert rpe(bent, gt, relation="rotation")["max"] == pytest.approx(np.degrees(0.1), rel=1e-6)
    with pytest.raises(ValueError, match="align must be"):
        ape(gt, gt, align="affine")


def test_evaluate_poses_reports_evo():
    est, gt = _traj2d(3, k=10)
    scans = ScanSet(points=np.ones((10, 4, 2), np.float32), valid=np.ones((10, 4), bool), gt_poses=gt,
                    unit_scale=512.0, unit="px")
    m = evaluate_poses(scans, est)
    assert m["evo"]["ape_se3_rmse"] == pytest.approx(m["ate"], rel=1e-9)
    same_place = np.zeros_like(gt)  # evo's Umeyama refuses it; our ATE does not
    degenerate = evo_metrics(same_place, gt)
    assert degenerate["ape_se3_rmse"] is None and degenerate["rpe_trans_rmse"] is not None
    assert set(evo_metrics(est, gt)) == {"ape_se3_rmse", "ape_sim3_rmse", "ape_rot_se3_rmse_deg",
                                         "rpe_trans_rmse", "rpe_rot_rmse_deg"}
