"""Classic 3D baselines (Open3D): incremental ICP and multiway registration [12] on a synthetic room corner."""

import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deepmapping.errors import ConfigError, InputError
from deepmapping.evaluation.metrics3d import ate_3d
from deepmapping.geometry import se3
from deepmapping.methods.icp3d import incremental_icp_3d
from deepmapping.methods.multiway import build_pose_graph, edge_pairs, multiway_registration
from deepmapping.methods.open3d_utils import require_open3d, to_pcd

K = 5


def _rect(rng, origin, u, v, n):
    a, b = rng.random((2, n, 1))
    return np.asarray(origin, float) + a * np.asarray(u, float) + b * np.asarray(v, float)


def _box(rng, lo, hi, n):
    lo, d = np.asarray(lo, float), np.asarray(hi, float) - np.asarray(lo, float)
    ex, ey, ez = np.diag(d)
    faces = [(lo + ez, ex, ey), (lo, ex, ez), (lo + ey, ex, ez), (lo, ey, ez), (lo + ex, ey, ez)]
    return np.concatenate([_rect(rng, o, u, v, n) for o, u, v in faces])


def _room(rng, density=1500):
    """World points: floor and two walls of a 4 x 3 m corner, plus two boxes (no symmetry)."""
    return np.concatenate([
        _rect(rng, [0, 0, 0], [4, 0, 0], [0, 3, 0], 12 * density),
        _rect(rng, [0, 0, 0], [4, 0, 0], [0, 0, 2.5], 10 * density),
        _rect(rng, [0, 0, 0], [0, 3, 0], [0, 0, 2.5], int(7.5 * density)),
        _box(rng, [1.2, 0.8, 0.0], [1.8, 1.2, 0.5], density // 2),
        _box(rng, [0.5, 1.8, 0.0], [0.8, 2.6, 1.0], density // 2),
    ])


@pytest.fixture(scope="module")
def scans():
    """K scans in their sensor frames (100 deg view cone, 2 mm noise, fresh samples each) + gt poses.

    Between scans the sensor moves ~6 cm and turns ~3 deg (yaw) and ~1 deg (pitch).
    """
    rng = np.random.default_rng(0)
    gt = np.stack([
        se3.from_rt(Rotation.from_euler("zyx", [np.radians(225 + 3 * i), 0.02 * i, 0.01]).as_matrix(),
                    [3.0 - 0.05 * i, 2.3 - 0.03 * i, 1.2 + 0.01 * i])
        for i in range(K)
    ])
    clouds = []
    for pose in gt:
        local = se3.transform_points(se3.inverse(pose), _room(rng))
        local = local[local[:, 0] / np.linalg.norm(local, axis=1) > np.cos(np.radians(50))]
        local = local[rng.permutation(len(local))[:3000]]
        clouds.append(local + rng.normal(0.0, 0.002, local.shape))
    return clouds, gt


def _assert_close_relative(est, gt, max_t=0.01, max_deg=0.5):
    assert est.shape == gt.shape
    err = se3.relative(se3.relative(gt[:-1], gt[1:]), se3.relative(est[:-1], est[1:]))
    assert np.linalg.norm(err[:, :3, 3], axis=1).max() < max_t
    assert se3.rotation_angle_deg(err[:, :3, :3]).max() < max_deg
    assert ate_3d(est, gt) < max_t


def test_scans_overlap_only_partly(scans):
    clouds, gt = scans
    assert all(c.shape == (3000, 3) for c in clouds)
    # the last scan's view cone no longer contains every point the first one saw
    local = se3.transform_points(se3.relative(gt[-1], gt[0]), clouds[0])
    seen = local[:, 0] / np.linalg.norm(local, axis=1) > np.cos(np.radians(50))
    assert 0.5 < seen.mean() < 0.99


@pytest.mark.parametrize("method", ["plane", "point"])
def test_incremental_icp_recovers_ground_truth(scans, method):
    clouds, gt = scans
    est = incremental_icp_3d(clouds, method=method)
    np.testing.assert_allclose(est[0], np.eye(4))
    _assert_close_relative(est, gt)


@pytest.mark.parametrize("edges", ["all", "window:2"])
def test_multiway_recovers_ground_truth(scans, edges):
    clouds, gt = scans
    est = multiway_registration(clouds, edges=edges)
    np.testing.assert_allclose(est[0], np.eye(4), atol=1e-9)
    _assert_close_relative(est, gt)


def test_good_init_stays_right_and_anchors_pose_0(scans):
    clouds, gt = scans
    for est in (incremental_icp_3d(clouds, init=gt), multiway_registration(clouds, init=gt)):
        np.testing.assert_allclose(est[0], gt[0], atol=1e-9)
        assert np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1).max() < 0.01
        _assert_close_relative(est, gt)


def test_edge_pairs():
    assert edge_pairs(4, "all") == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    assert edge_pairs(4, "window:1") == [(0, 1), (1, 2), (2, 3)]
    assert edge_pairs(4, "window:2") == [(0, 1), (0, 2), (1, 2), (1, 3), (2, 3)]
    for bad in ("window:0", "window:", "chain", "ALL"):
        with pytest.raises(ConfigError, match="edges"):
            edge_pairs(4, bad)


def test_pose_graph_has_loop_closures_only_beyond_the_chain(scans):
    clouds, gt = scans
    calls = []
    graph, scales = build_pose_graph(clouds, edges="all", progress=lambda d, t: calls.append((d, t)))
    pairs = sorted((e.source_node_id, e.target_node_id) for e in graph.edges)
    assert pairs == edge_pairs(K, "all") and len(graph.nodes) == K
    assert sorted(e.uncertain for e in graph.edges) == [False] * (K - 1) + [True] * (K * (K - 1) // 2 - K + 1)
    assert calls == [(i, K * (K - 1) // 2) for i in range(1, K * (K - 1) // 2 + 1)]
    for e in graph.edges:  # T_ij = pose of scan i in scan j's frame
        truth = se3.relative(gt[e.target_node_id], gt[e.source_node_id])
        assert np.abs(np.asarray(e.transformation) - truth)[:3, 3].max() < 0.01
        assert np.linalg.eigvalsh(np.asarray(e.information)).min() > 0
    chain, _ = build_pose_graph(clouds, edges="window:1")
    assert len(chain.edges) == K - 1 and not any(e.uncertain for e in chain.edges)
    assert scales.voxel > 0 and scales.fine == pytest.approx(1.5 * scales.voxel)


def test_default_scales_follow_the_cloud_extent(scans):
    clouds, _ = scans
    _, metres = build_pose_graph(clouds[:2], edges="window:1")
    _, millimetres = build_pose_graph([1000 * c for c in clouds[:2]], edges="window:1")
    assert millimetres.voxel == pytest.approx(1000 * metres.voxel)
    assert 0.02 < metres.voxel < 0.1  # scans span a few metres
    _, given = build_pose_graph(clouds[:2], voxel_size=0.05, max_correspondence_distance=0.2, edges="window:1")
    assert (given.voxel, given.fine, given.coarse) == (0.05, 0.2, pytest.approx(2.0))


def test_incremental_icp_progress(scans):
    clouds, _ = scans
    calls = []
    incremental_icp_3d(clouds[:3], progress=lambda d, t: calls.append((d, t)))
    assert calls == [(1, 2), (2, 2)]


@pytest.mark.parametrize("bad", [np.zeros((0, 3)), np.full((50, 3), np.nan), np.ones((5, 3)), np.ones((20, 2))])
@pytest.mark.parametrize("fn", [incremental_icp_3d, multiway_registration])
def test_bad_scan_names_its_index(scans, bad, fn):
    clouds = list(scans[0][:3])
    clouds[2] = bad
    with pytest.raises(InputError, match="scan 2"):
        fn(clouds)


def test_bad_options(scans):
    clouds, gt = scans
    with pytest.raises(ConfigError, match="method"):
        incremental_icp_3d(clouds[:2], method="plain")
    with pytest.raises(InputError, match="init"):
        multiway_registration(clouds[:2], init=gt)
    with pytest.raises(InputError, match="no scans"):
        multiway_registration([])


def test_single_scan_returns_its_init(scans):
    clouds, gt = scans
    np.testing.assert_allclose(incremental_icp_3d(clouds[:1]), np.eye(4)[None])
    np.testing.assert_allclose(multiway_registration(clouds[:1], init=gt[:1]), gt[:1], atol=1e-12)


def test_to_pcd_downsamples_and_orients_normals_to_the_sensor(scans):
    cloud = scans[0][0]
    pcd = to_pcd(cloud, voxel_size=0.1, normals_radius=0.2)
    pts, normals = np.asarray(pcd.points), np.asarray(pcd.normals)
    assert 0 < len(pts) < len(cloud) and normals.shape == pts.shape
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    assert (np.sum(normals * -pts, axis=1) >= 0).all()  # facing the origin of the scan's frame
    assert len(to_pcd(cloud).points) == len(cloud) and not to_pcd(cloud).has_normals()


def test_missing_open3d_is_a_one_line_config_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)  # makes `import open3d` raise ImportError
    with pytest.raises(ConfigError, match="pip install open3d-cpu") as info:
        require_open3d("multiway registration")
    assert "\n" not in str(info.value) and "multiway registration" in str(info.value)
    with pytest.raises(ConfigError):
        incremental_icp_3d([np.random.default_rng(0).random((20, 3))] * 2)


def test_multiway_starts_odometry_pairs_where_the_previous_scan_is(scans, monkeypatch):
    """Without init, the odometry pair (i, i+1) starts from the identity, as incremental ICP: scan i+1
    is not placed yet. (It started from scan i's whole pose, and a long sequence drifted off: 7-Scenes
    multiway 226 mm, no registration 60 mm.) Loop-closure pairs start from the chained poses."""
    import deepmapping.methods.multiway as mw

    clouds, gt = scans
    guesses = {}
    real = mw.register_pair

    def spy(source, target, guess, scales):
        res = real(source, target, guess, scales)
        guesses[len(guesses)] = np.asarray(guess).copy()
        return res

    monkeypatch.setattr(mw, "register_pair", spy)
    graph, _ = build_pose_graph(clouds, edges="all")
    odometry = [guesses[k] for k in range(K - 1)]  # odometry pairs are registered first
    assert all(np.array_equal(g, np.eye(4)) for g in odometry)
    nodes = np.stack([np.asarray(n.pose) for n in graph.nodes])
    loops = [p for p in edge_pairs(K) if p[1] - p[0] > 1]
    for (i, j), g in zip(loops, [guesses[k] for k in range(K - 1, len(guesses))]):
        np.testing.assert_allclose(g, se3.relative(nodes[j], nodes[i]), atol=1e-9)
    _assert_close_relative(multiway_registration(clouds, edges="window:1"), gt)


def test_default_scales_do_not_go_below_the_point_spacing(scans):
    """Sparse scans (few points, e.g. a room at 40 x 30 pixels): the voxel is at least the median
    nearest-neighbour distance, else the normals' radius holds no neighbour; dense ones keep d / 100."""
    from deepmapping.methods.icp3d import default_scales, point_spacing

    clouds, _ = scans
    dense = default_scales(clouds)
    diag = np.median([np.linalg.norm(c.max(0) - c.min(0)) for c in clouds])
    assert point_spacing(clouds) < diag / 100 and dense.voxel == pytest.approx(diag / 100)
    sparse = [c[:: 40] for c in clouds]  # 75 points a scan
    gap = point_spacing(sparse)
    assert gap > diag / 100 and default_scales(sparse).voxel == pytest.approx(gap)
    assert default_scales(sparse, voxel_size=0).normals_radius == pytest.approx(2 * gap)
    assert default_scales(sparse, voxel_size=0.01).voxel == 0.01  # explicit values win


def test_kiss_icp_odometry_recovers_ground_truth_and_anchors_pose_0(scans):
    from deepmapping.methods.kiss_odometry import kiss_config, kiss_icp_poses

    clouds, gt = scans
    cfg = kiss_config(clouds)
    assert cfg.data.deskew is False and cfg.mapping.voxel_size == pytest.approx(cfg.data.max_range / 100)
    steps = []
    est = kiss_icp_poses(clouds, progress=lambda i, n: steps.append((i, n)))
    np.testing.assert_allclose(est[0], np.eye(4), atol=1e-9)
    assert steps[-1] == (K - 1, K - 1)
    _assert_close_relative(est, gt, max_t=0.02, max_deg=1.0)
    anchored = kiss_icp_poses(clouds, init=gt)
    np.testing.assert_allclose(anchored[0], gt[0], atol=1e-9)
    assert ate_3d(anchored, gt) < 0.02


def test_kiss_icp_bad_scan_names_its_index(scans):
    from deepmapping.methods.kiss_odometry import kiss_icp_poses

    clouds = [c.copy() for c in scans[0]]
    clouds[2] = clouds[2][:3]  # too few points to register
    with pytest.raises(InputError, match="scan 2"):
        kiss_icp_poses(clouds)
