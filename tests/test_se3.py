"""SE(3) helpers and 3D metrics (groundwork of the 3D issue)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deepmapping.evaluation.metrics3d import align_poses_3d, ate_3d, rotation_errors_deg
from deepmapping.geometry import se3


def random_poses(k, seed=0):
    rng = np.random.default_rng(seed)
    return se3.from_rt(Rotation.random(k, random_state=seed).as_matrix(), rng.normal(size=(k, 3)))


def test_compose_inverse_relative_and_transform_agree():
    a, b = random_poses(5, 0), random_poses(5, 1)
    np.testing.assert_allclose(se3.compose(a, se3.inverse(a)), se3.identity((5,)), atol=1e-12)
    np.testing.assert_allclose(se3.compose(a, se3.relative(a, b)), b, atol=1e-12)
    pts = np.random.default_rng(2).normal(size=(5, 7, 3))
    homog = np.concatenate([pts, np.ones((5, 7, 1))], -1) @ np.swapaxes(a, 1, 2)
    np.testing.assert_allclose(se3.transform_points(a, pts), homog[..., :3], atol=1e-12)
    with pytest.raises(ValueError, match=r"\(\.\.\., 4, 4\)"):
        se3.compose(np.eye(3), a)


def test_quaternion_round_trip_is_scalar_last_and_normalizes():
    T = random_poses(6, 3)
    q = se3.to_xyz_quat(T)
    assert q.shape == (6, 7) and (q[:, 6] >= 0).all()
    np.testing.assert_allclose(se3.from_xyz_quat(q), T, atol=1e-12)
    np.testing.assert_allclose(se3.from_xyz_quat([1, 2, 3, 0, 0, 0, 2.0]), se3.from_rt(np.eye(3), [1, 2, 3]))
    quarter_z = se3.from_xyz_quat([0, 0, 0, 0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    np.testing.assert_allclose(se3.transform_points(quarter_z, [[1.0, 0, 0]]), [[0, 1, 0]], atol=1e-12)


def test_planar_xz_poses_rotate_about_the_vertical_axis():
    T = se3.from_planar_xz([2.0, 3.0, np.pi / 2])
    np.testing.assert_allclose(T[:3, 3], [2, 0, 3])
    np.testing.assert_allclose(se3.transform_points(T, [[0, 0, 1.0]]), [[3, 0, 3]], atol=1e-12)
    np.testing.assert_allclose(T[1, :3], [0, 1, 0])  # y (up) is kept


def test_rotation_from_6d_is_a_rotation_and_recovers_its_columns():
    rot = Rotation.random(4, random_state=5).as_matrix()
    six = np.concatenate([rot[..., 0] * 3.0, rot[..., 1] + 0.5 * rot[..., 0]], -1)  # scaled, skewed
    got = se3.rotation_from_6d(six)
    np.testing.assert_allclose(got, rot, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(se3.rotation_from_6d(np.random.default_rng(0).normal(size=(9, 6)))), 1.0)


def test_ate_and_rotation_errors_are_invariant_to_a_global_rigid_motion():
    gt = random_poses(20, 6)
    motion = random_poses(1, 7)[0]
    est = se3.compose(motion, gt)
    assert ate_3d(est, gt) == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(rotation_errors_deg(est, gt), 0.0, atol=1e-6)
    np.testing.assert_allclose(align_poses_3d(est, gt), gt, atol=1e-9)
    noisy = est.copy()
    noisy[3, :3, :3] = noisy[3, :3, :3] @ Rotation.from_euler("z", 10, degrees=True).as_matrix()
    err = rotation_errors_deg(noisy, gt, tip=0)  # positions only: the rotated pose does not move the alignment
    assert err[3] == pytest.approx(10.0, abs=1e-6) and np.delete(err, 3).max() < 1e-6
    shifted = est.copy()
    shifted[:, :3, 3] += np.random.default_rng(8).normal(0, 0.1, (20, 3))
    assert 0.1 < ate_3d(shifted, gt) < 0.25  # 0.1 per axis: about 0.17 in 3D, less what alignment absorbs


def test_rotation_errors_are_defined_when_positions_coincide():
    """AVD turns in place: positions alone do not fix the alignment's rotation, axis tips do."""
    gt = se3.from_rt(Rotation.from_euler("y", np.arange(6)[:, None] * 30.0, degrees=True).as_matrix(), np.zeros((6, 3)))
    est = se3.compose(random_poses(1, 3)[0], gt)
    np.testing.assert_allclose(rotation_errors_deg(est, gt), 0.0, atol=1e-6)
    assert rotation_errors_deg(est, gt, tip=0).max() > 1.0  # what position-only alignment gives
