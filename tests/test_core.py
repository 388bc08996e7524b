"""Tests of SE(2), rigid alignment, metrics and 2D ICP (deepmapping.geometry, .evaluation, .methods)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deepmapping.evaluation.metrics import ate, evaluate, point_distance, rotation_rmse_deg
from deepmapping.geometry import se2
from deepmapping.geometry.alignment import align_poses_2d, rigid_align
from deepmapping.methods.icp import icp_2d, incremental_icp


def random_poses(rng, k, trans=5.0):
    return np.column_stack([rng.uniform(-trans, trans, (k, 2)), rng.uniform(-np.pi, np.pi, k)])


def assert_pose_close(a, b, atol):
    a, b = np.asarray(a), np.asarray(b)
    np.testing.assert_allclose(a[..., :2], b[..., :2], atol=atol)
    np.testing.assert_allclose(se2.wrap_angle(a[..., 2] - b[..., 2]), 0.0, atol=atol)


# ---------------------------------------------------------------- SE(2)


def test_wrap_angle_range():
    a = np.array([-np.pi, np.pi, 3 * np.pi, -3 * np.pi, 0.0, 7.0, -7.0])
    w = se2.wrap_angle(a)
    assert np.all(w > -np.pi) and np.all(w <= np.pi)
    np.testing.assert_allclose(w[:4], np.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-12)


def test_matrix_round_trip_and_compose_matches_matrix_product():
    rng = np.random.default_rng(0)
    a, b = random_poses(rng, 50), random_poses(rng, 50)
    assert se2.to_matrix(a).shape == (50, 3, 3)
    assert_pose_close(se2.from_matrix(se2.to_matrix(a)), a, 1e-12)
    assert_pose_close(se2.compose(a, b), se2.from_matrix(se2.to_matrix(a) @ se2.to_matrix(b)), 1e-12)
    np.testing.assert_allclose(se2.to_matrix(se2.inverse(a)), np.linalg.inv(se2.to_matrix(a)), atol=1e-12)


def test_compose_inverse_associativity():
    rng = np.random.default_rng(1)
    a, b, c = random_poses(rng, 50), random_poses(rng, 50), random_poses(rng, 50)
    ident = np.zeros((50, 3))
    assert_pose_close(se2.compose(a, se2.inverse(a)), ident, 1e-12)
    assert_pose_close(se2.compose(se2.inverse(a), a), ident, 1e-12)
    assert_pose_close(se2.inverse(se2.inverse(a)), a, 1e-12)
    assert_pose_close(se2.compose(se2.compose(a, b), c), se2.compose(a, se2.compose(b, c)), 1e-11)
    assert_pose_close(se2.compose(a, se2.relative(a, b)), b, 1e-11)
    assert_pose_close(se2.inverse(se2.compose(a, b)), se2.compose(se2.inverse(b), se2.inverse(a)), 1e-11)
    # broadcasting a single pose against many
    assert_pose_close(se2.compose(a[0], b), se2.compose(np.repeat(a[:1], 50, 0), b), 1e-12)


def test_transform_points_matches_matrix_product():
    rng = np.random.default_rng(2)
    poses = random_poses(rng, 7)
    pts = rng.normal(size=(7, 11, 2))
    out = se2.transform_points(poses, pts)
    hom = np.concatenate([pts, np.ones((7, 11, 1))], -1)
    ref = np.einsum("kij,knj->kni", se2.to_matrix(poses), hom)[..., :2]
    assert out.shape == (7, 11, 2)
    np.testing.assert_allclose(out, ref, atol=1e-12)
    np.testing.assert_allclose(se2.transform_points(poses[3], pts[3]), ref[3], atol=1e-12)
    # composition acts on points as T_a(T_b(p))
    a, b = poses[0], poses[1]
    np.testing.assert_allclose(
        se2.transform_points(se2.compose(a, b), pts[0]),
        se2.transform_points(a, se2.transform_points(b, pts[0])),
        atol=1e-12,
    )


def test_chain_reproduces_trajectory_and_wrong_order_drifts():
    rng = np.random.default_rng(3)
    k = 100
    rels_true = np.column_stack([rng.uniform(0.2, 1.0, k - 1), rng.uniform(-0.5, 0.5, k - 1),
                                 rng.uniform(-2.5, 2.5, k - 1)])  # large rotations
    gt = np.zeros((k, 3))
    gt[0] = [1.0, -2.0, 0.7]
    m = se2.to_matrix(gt[0])
    for i in range(k - 1):  # ground truth by homogeneous matrix products
        m = m @ se2.to_matrix(rels_true[i])
        gt[i + 1] = se2.from_matrix(m)
    rels = se2.relative(gt[:-1], gt[1:])
    assert_pose_close(rels, rels_true, 1e-9)
    out = se2.chain(rels, first=gt[0])
    assert out.shape == (k, 3)
    assert_pose_close(out, gt, 1e-9)
    assert_pose_close(se2.chain(rels[:0]), np.zeros((1, 3)), 0)

    # The authors' order: update the heading first, then rotate the translation with it.
    wrong = np.zeros((k, 3))
    wrong[0] = gt[0]
    for i in range(k - 1):
        th = wrong[i, 2] + rels[i, 2]
        wrong[i + 1, :2] = wrong[i, :2] + se2.rotation(th) @ rels[i, :2]
        wrong[i + 1, 2] = se2.wrap_angle(th)
    assert np.max(np.linalg.norm(wrong[:, :2] - gt[:, :2], axis=1)) > 1.0


# ---------------------------------------------------------------- alignment


@pytest.mark.parametrize("dim", [2, 3])
def test_rigid_align_recovers_transform(dim):
    rng = np.random.default_rng(4 + dim)
    src = rng.normal(size=(40, dim)) * 3
    rot = Rotation.random(random_state=5).as_matrix() if dim == 3 else se2.rotation(2.7)
    t = rng.normal(size=dim) * 10
    dst = src @ rot.T + t
    r_est, t_est = rigid_align(src, dst)
    np.testing.assert_allclose(r_est, rot, atol=1e-10)
    np.testing.assert_allclose(t_est, t, atol=1e-9)
    # weights: outliers with zero weight are ignored
    dst_bad = dst.copy()
    dst_bad[:5] += 100.0
    w = np.ones(40)
    w[:5] = 0.0
    r_w, t_w = rigid_align(src, dst_bad, weights=w)
    np.testing.assert_allclose(r_w, rot, atol=1e-10)
    np.testing.assert_allclose(t_w, t, atol=1e-9)


def test_rigid_align_coplanar_3d_is_proper_rotation():
    # Coplanar points: the cross-covariance has rank 2, a naive SVD can return a reflection.
    rng = np.random.default_rng(6)
    src = np.column_stack([rng.normal(size=(30, 2)), np.zeros(30)])
    rot = Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix()
    t = np.array([1.0, 2.0, -3.0])
    dst = src @ rot.T + t
    r_est, t_est = rigid_align(src, dst)
    assert np.linalg.det(r_est) == pytest.approx(1.0)
    np.testing.assert_allclose(r_est, rot, atol=1e-10)
    np.testing.assert_allclose(t_est, t, atol=1e-9)


def test_rigid_align_mirrored_2d_returns_best_proper_rotation():
    rng = np.random.default_rng(7)
    src = rng.normal(size=(25, 2)) * np.array([3.0, 1.0])
    dst = src * np.array([1.0, -1.0])  # mirror image: no rotation fits exactly
    r_est, t_est = rigid_align(src, dst)
    assert np.linalg.det(r_est) == pytest.approx(1.0)
    cost = np.sum((src @ r_est.T + t_est - dst) ** 2)
    for th in np.linspace(-np.pi, np.pi, 721):  # brute force over rotations (optimal t = centroid shift)
        r = se2.rotation(th)
        tt = dst.mean(0) - r @ src.mean(0)
        assert cost <= np.sum((src @ r.T + tt - dst) ** 2) + 1e-9


def test_align_poses_2d_undoes_rigid_motion():
    rng = np.random.default_rng(8)
    gt = random_poses(rng, 20)
    est = se2.compose(np.array([3.0, -1.0, 2.0]), gt)
    assert_pose_close(align_poses_2d(est, gt), gt, 1e-10)


# ---------------------------------------------------------------- metrics


def test_ate_zero_and_invariant_to_rigid_motion():
    rng = np.random.default_rng(9)
    gt = random_poses(rng, 30)
    moved = se2.compose(np.array([-4.0, 7.0, -2.2]), gt)
    assert ate(moved, gt) < 1e-10
    assert rotation_rmse_deg(moved, gt) < 1e-8
    noisy = gt + np.column_stack([rng.normal(size=(30, 2)) * 0.1, rng.normal(size=30) * 0.01])
    e = ate(noisy, gt)
    assert e > 0.01
    assert ate(se2.compose(np.array([10.0, 3.0, 1.0]), noisy), gt) == pytest.approx(e, rel=1e-9)


def test_ate_hand_computation():
    # Square corners; pose 0 pushed radially outward by c. By symmetry the best rotation is 0
    # and the best translation is c/4 along the push: residuals 3c/4, c/4, c/4, c/4.
    gt = np.array([[1.0, 1.0, 0.0], [-1.0, 1.0, 0.0], [-1.0, -1.0, 0.0], [1.0, -1.0, 0.0]])
    c = 0.4
    est = gt.copy()
    est[0, :2] += c / np.sqrt(2.0)
    assert ate(est, gt) == pytest.approx(c * np.sqrt(3.0) / 4.0, rel=1e-12)


def test_point_distance_and_evaluate():
    rng = np.random.default_rng(10)
    gt = random_poses(rng, 6)
    pts = rng.normal(size=(6, 40, 2))
    valid = rng.random((6, 40)) > 0.2
    moved = se2.compose(np.array([1.0, 2.0, 0.5]), gt)
    assert point_distance(pts, valid, moved, gt) < 1e-10
    # a pure heading error on one pose: zero ATE, positive point distance
    est = gt.copy()
    est[2, 2] += 0.1
    pd = point_distance(pts, valid, est, gt)
    ref = np.mean(np.linalg.norm(se2.transform_points(est[2], pts[2]) - se2.transform_points(gt[2], pts[2]), axis=1)[valid[2]])
    assert pd == pytest.approx(ref * valid[2].sum() / valid.sum(), rel=1e-9)
    res = evaluate(est, gt, pts, valid, unit_scale=512.0, success_threshold=20.0)
    assert set(res) == {"ate", "point_distance", "success", "success_threshold", "rotation_rmse_deg",
                        "rotation_max_deg", "num_scans"}
    assert res["ate"] < 1e-8 and res["success"] is True and res["num_scans"] == 6 and res["success_threshold"] == 20.0
    assert res["point_distance"] == pytest.approx(512.0 * pd)
    assert res["rotation_rmse_deg"] == pytest.approx(np.degrees(0.1) / np.sqrt(6), rel=1e-6)
    # one heading off by 0.1 rad; the alignment spreads it over the six: the largest error under 0.1 rad
    assert res["rotation_rmse_deg"] < res["rotation_max_deg"] < np.degrees(0.1) + 1e-9
    far = gt.copy()
    far[0, :2] += 1.0
    assert evaluate(far, gt, pts, valid, unit_scale=512.0)["success"] is False


def test_one_evaluate_for_2d_and_3d_with_the_same_keys():
    from deepmapping.evaluation import evaluate as evaluate_any
    from deepmapping.geometry import se3

    rng = np.random.default_rng(3)
    gt2 = random_poses(rng, 5)
    pts2, valid2 = rng.normal(size=(5, 30, 2)), np.ones((5, 30), bool)
    gt3 = np.stack([se3.from_rt(np.eye(3), t) for t in rng.normal(size=(5, 3))])
    pts3, valid3 = rng.normal(size=(5, 30, 3)), np.ones((5, 30), bool)
    two = evaluate_any(gt2, gt2, pts2, valid2)
    three = evaluate_any(gt3, gt3, pts3, valid3)
    assert set(two) == set(three)
    assert two["success_threshold"] == 20.0 and two["ate"] < 1e-9 and three["ate"] < 1e-9
    assert evaluate_any(gt3, gt3, pts3, valid3, avd_protocol=True)["success_threshold"] == 0.45  # AVD's 450 mm, in m
    from deepmapping.evaluation import ate as ate_any

    moved2, moved3 = gt2.copy(), gt3.copy()
    moved2[0, :2] += 1.0
    moved3[0, :3, 3] += 1.0
    assert ate_any(moved2, gt2) == pytest.approx(ate(moved2, gt2)) and ate_any(moved2, gt2) > 0.1
    assert ate_any(moved3, gt3) > 0.1


# ---------------------------------------------------------------- ICP

ROOM = [((0, 0), (10, 0)), ((10, 0), (10, 8)), ((10, 8), (0, 8)), ((0, 8), (0, 0)),
        ((7, 5), (8.5, 5)), ((8.5, 5), (8.5, 6.5)), ((8.5, 6.5), (7, 6.5)), ((7, 6.5), (7, 5))]
ROOM_SIZE = np.hypot(10, 8)


def sample_walls(rng, n):
    seg = np.array(ROOM, dtype=float)
    lengths = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
    which = rng.choice(len(seg), size=n, p=lengths / lengths.sum())
    u = rng.random(n)[:, None]
    return seg[which, 0] + u * (seg[which, 1] - seg[which, 0])


def raycast(pose, beams=256):
    """Organized scan (sensor frame) of ROOM from ``pose``; beam j at angle 2*pi*j/beams."""
    seg = np.array(ROOM, dtype=float)
    ang = 2 * np.pi * np.arange(beams) / beams
    d = np.stack([np.cos(ang + pose[2]), np.sin(ang + pose[2])], -1)  # (B, 2)
    a, e = seg[:, 0], seg[:, 1] - seg[:, 0]  # (S, 2)
    o = pose[:2]
    def cross(u, v):
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    den = cross(d[:, None], e[None])  # (B, S)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = cross((a - o)[None], e[None]) / den
        u = cross((a - o)[None], d[:, None]) / den
    ok = (np.abs(den) > 1e-12) & (t > 1e-9) & (u >= 0) & (u <= 1)
    r = np.where(ok, t, np.inf).min(axis=1)
    valid = np.isfinite(r)
    pts = np.where(valid[:, None], r[:, None] * np.stack([np.cos(ang), np.sin(ang)], -1), 0.0)
    return pts, valid


REL = np.array([0.3, -0.2, np.radians(5.0)])  # ~3% of the room size, 5 degrees


@pytest.mark.parametrize("method", ["point", "plane"])
@pytest.mark.parametrize("unit", [1.0, 1.0 / 512.0])
def test_icp_recovers_known_transform_same_points(method, unit):
    rng = np.random.default_rng(11)
    world = sample_walls(rng, 256) * unit
    pose0 = np.array([3.0 * unit, 4.0 * unit, 0.3])
    rel = REL * np.array([unit, unit, 1.0])
    pose1 = se2.compose(pose0, rel)
    target = se2.transform_points(se2.inverse(pose0), world)
    source = se2.transform_points(se2.inverse(pose1), world)
    est, info = icp_2d(source, target, method=method)
    assert np.hypot(*(est[:2] - rel[:2])) < 1e-3 * ROOM_SIZE * unit
    assert abs(np.degrees(se2.wrap_angle(est[2] - rel[2]))) < 0.1
    assert info["fitness"] > 0.95 and info["iterations"] >= 1
    np.testing.assert_allclose(se2.transform_points(est, source), target, atol=1e-3 * ROOM_SIZE * unit)


@pytest.mark.parametrize("method", ["point", "plane"])
def test_icp_raycast_scans_with_missing_points(method):
    pose0 = np.array([3.0, 4.0, 0.3])
    pose1 = se2.compose(pose0, REL)
    p0, v0 = raycast(pose0)
    p1, v1 = raycast(pose1)
    rng = np.random.default_rng(12)
    v1 &= rng.random(v1.shape) > 0.2  # drop 20% of the returns
    est, info = icp_2d(p1[v1], p0[v0], method=method)
    tol = 1e-3 if method == "plane" else 5e-3
    assert np.hypot(*(est[:2] - REL[:2])) < tol * ROOM_SIZE
    assert abs(np.degrees(se2.wrap_angle(est[2] - REL[2]))) < (0.1 if method == "plane" else 0.3)
    assert info["fitness"] > 0.8


def test_icp_degenerate_inputs():
    pose, info = icp_2d(np.zeros((2, 2)), np.ones((10, 2)), init=[1.0, 2.0, 0.1])
    np.testing.assert_allclose(pose, [1.0, 2.0, 0.1])
    assert info["fitness"] == 0.0
    with pytest.raises(ValueError):
        icp_2d(np.zeros((5, 2)), np.zeros((5, 2)), method="nope")


@pytest.mark.parametrize("method", ["point", "plane"])
def test_incremental_icp_sequence(method):
    k = 10
    step = np.array([0.4, 0.05, np.radians(8.0)])
    gt = se2.chain(np.repeat(step[None], k - 1, 0), first=np.array([2.0, 1.5, 0.1]))
    scans = [raycast(p) for p in gt]
    pts = np.stack([s[0] for s in scans])
    valid = np.stack([s[1] for s in scans])
    calls = []
    est = incremental_icp(pts, valid, method=method, progress=lambda i, n: calls.append((i, n)))
    assert est.shape == (k, 3)
    np.testing.assert_allclose(est[0], 0.0)
    assert calls == [(i, k) for i in range(1, k)]
    motion = np.hypot(step[0], step[1])
    # point-to-point is biased by the different beam samples of consecutive scans
    assert ate(est, gt) < (0.02 if method == "plane" else 0.05) * motion
    assert rotation_rmse_deg(est, gt) < (0.1 if method == "plane" else 1.0)


def test_incremental_icp_does_not_run_away_from_a_wrong_basin():
    """Paper trajectory 25, scans 28-34: from the constant-velocity guess (and from the
    identity) point-to-line ICP of scan 32 onto 31 lands 214 px off, and the wrong motion, fed
    forward as the next guess, runs the chain away (the suite's icp-plane ATE: 16780 px). The
    recovery keeps the bounded untrimmed ICP there, whose overlap is far higher."""
    from deepmapping.sim.dataset import paper_trajectory

    scans = paper_trajectory(25)
    pts, valid, gt = scans.points[28:35].astype(np.float64), scans.valid[28:35], scans.gt_poses[28:35]

    def step_errors_px(est):
        return np.array([np.hypot(*(se2.relative(est[i - 1], est[i])[:2] - se2.relative(gt[i - 1], gt[i])[:2]))
                         for i in range(1, len(gt))]) * scans.unit_scale

    assert step_errors_px(incremental_icp(pts, valid, method="plane", recover_margin=None)).max() > 100.0
    assert step_errors_px(incremental_icp(pts, valid, method="plane")).max() < 5.0

    # the same through register() and the config (icp.recover_margin: null turns it off)
    import dataclasses

    from deepmapping.api import register
    from deepmapping.config import load_config

    part = dataclasses.replace(scans, points=scans.points[28:35], valid=valid, gt_poses=gt, names=[])
    ate_px = {m: register(part, load_config("default", overrides={"method": "icp-plane", "icp.recover_margin": m}))
              .metrics["ate"] for m in (None, 0.05)}
    assert ate_px[None] > 50.0 and ate_px[0.05] < 5.0
