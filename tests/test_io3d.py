"""Readers of the real 3D data sets: Stanford Bunny (bun.conf + ply) and 3DTK (slam6D)."""

import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from deepmapping.errors import InputError
from deepmapping.geometry import se3
from deepmapping.io.bunny import bunny_pose_errors, is_bunny_folder, load_bunny, scan_centroids
from deepmapping.io.ply import read_ply
from deepmapping.io.threedtk import is_3dtk_folder, load_3dtk, read_3d, read_frames, read_pose, write_frames, write_pose

DATA = Path(__file__).resolve().parent / "data"  # excerpts of ../shared/data (tests/data/make_excerpts.py)
BUNNY, TDTK = DATA / "bunny", DATA / "3dtk"


@pytest.fixture(scope="module")
def bunny():
    return load_bunny(BUNNY, max_points=None)


def world(scans):
    return se3.transform_points(scans.gt_poses, scans.points)


def test_bunny_layout():
    s = load_bunny(BUNNY, max_points=500)
    assert is_bunny_folder(BUNNY) and not is_bunny_folder(TDTK)
    assert s.points.shape == (10, 500, 3) and s.valid.all() and s.names[:2] == ["bun000", "bun045"]
    assert (s.unit, s.unit_scale, s.ordered, s.pose_dof, s.grid_shape) == ("mm", 1000.0, False, 6, None)
    again = load_bunny(BUNNY, max_points=500)
    assert np.array_equal(again.points, s.points)  # seeded
    assert not np.array_equal(load_bunny(BUNNY, max_points=500, seed=1).points, s.points)
    conf = load_bunny(BUNNY, max_points=20, init_path=BUNNY / "bun.conf")  # a .conf as initial poses
    np.testing.assert_array_equal(conf.init_poses, s.gt_poses)


def test_bunny_gt_registers_scans(bunny):
    """README: 99-100 % of a scan's points lie within 1 mm of the other scans."""
    w = world(bunny)
    i = bunny.names.index("bun045")
    others = np.concatenate([w[k][bunny.valid[k]] for k in range(len(w)) if k != i])
    d, _ = cKDTree(others).query(w[i][bunny.valid[i]])
    assert (d < 0.001).mean() > 0.97


def test_bunny_shift_keeps_world_points(bunny):
    """gt (shifted) applied to the shifted points = the conf's R(q)^T p + t on the file's points."""
    line = next(ln.split() for ln in (BUNNY / "bun.conf").read_text().splitlines() if "bun045" in ln)
    v = np.array(line[2:], float)
    raw = read_ply(BUNNY / "bun045.ply").astype(np.float64)
    want = raw @ Rotation.from_quat(v[3:]).as_matrix() + v[:3]  # p @ R == R^T p
    i = bunny.names.index("bun045")
    got = world(bunny)[i][: len(raw)]
    assert bunny.valid[i].sum() == len(raw)
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert np.abs(bunny.points[i][: len(raw)] - raw).max() > 1.0  # really shifted (~1.35 m)


def test_bunny_sensor_faces_the_scanned_surface(bunny):
    """From a point towards its (assumed) sensor the ray stays clear of the other scans; the
    opposite ray enters the bunny and meets them."""
    w = world(bunny)
    rng = np.random.default_rng(0)
    for i in (0, bunny.names.index("top2")):
        assert (bunny.points[i][bunny.valid[i], 2] < -1.0).all()  # the sensor is on the +z side
        tree = cKDTree(np.concatenate([w[k][bunny.valid[k]] for k in range(len(w)) if k != i]))
        p = w[i][rng.choice(bunny.valid[i].sum(), 150, replace=False)]
        toward = bunny.gt_poses[i, :3, 3] - p
        toward /= np.linalg.norm(toward, axis=1, keepdims=True)
        steps = np.arange(0.003, 0.25, 0.0005)
        blocked = {}
        for sign in (1, -1):
            q = p[:, None] + sign * steps[None, :, None] * toward[:, None]
            d, _ = tree.query(q.reshape(-1, 3), distance_upper_bound=0.0008)
            blocked[sign] = (d.reshape(len(p), -1) < 0.0008).any(axis=1).mean()
        # excerpt (one point per 2 mm), rng seeds 0-2: toward 0.06-0.11, away 0.89-0.97
        assert blocked[1] < 0.2 and blocked[-1] > 0.8, (bunny.names[i], blocked)


def test_bunny_pose_errors(bunny):
    gt, names = bunny.gt_poses, bunny.names
    cen = scan_centroids(bunny.points, bunny.valid)
    zero = bunny_pose_errors(gt, gt, names, cen)
    assert [e["name"] for e in zero] == names and max(e["rot_deg"] + e["trans_mm"] for e in zero) < 1e-6
    glob = se3.from_rt(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix(), [1.0, 2.0, 3.0])
    moved = bunny_pose_errors(glob @ gt, gt, names, cen)  # a common motion is no error
    assert max(e["rot_deg"] + e["trans_mm"] for e in moved) < 1e-6
    est = gt.copy()
    spin = se3.from_rt(Rotation.from_rotvec(np.radians(2.0) * np.array([0, 0.6, 0.8])).as_matrix(), [0, 0, 0])
    about_c = se3.from_rt(np.eye(3), cen[3]) @ spin @ se3.from_rt(np.eye(3), -cen[3])
    est[3] = gt[3] @ about_c  # 2 degrees about scan 3's centroid
    est[5] = gt[5] @ se3.from_rt(np.eye(3), [0.003, 0.0, 0.0])  # 3 mm shift
    err = bunny_pose_errors(est, gt, names, cen)
    assert err[3]["rot_deg"] == pytest.approx(2.0, abs=1e-9) and err[3]["trans_mm"] < 1e-6
    assert err[5]["rot_deg"] < 1e-6 and err[5]["trans_mm"] == pytest.approx(3.0, abs=1e-6)
    assert all(e["at"] == "centroid" for e in err)
    at_origin = bunny_pose_errors(est, gt, names)
    assert at_origin[3]["trans_mm"] > 10 and at_origin[3]["at"] == "origin"  # lever arm of ~1.3 m


def test_bunny_errors(tmp_path):
    with pytest.raises(InputError, match="bun.conf"):
        load_bunny(tmp_path)
    conf = "camera 0 0 0 0 0 0 1\nbmesh a.ply 0 0 0 0 0 0 1\nbmesh gone.ply 0 0 0 0 0 0 1\n"
    (tmp_path / "bun.conf").write_text(conf)
    shutil.copy(BUNNY / "bun000.ply", tmp_path / "a.ply")
    with pytest.raises(InputError, match="gone.ply"):
        load_bunny(tmp_path)
    (tmp_path / "bun.conf").write_text("bmesh a.ply 0 0 0 0 0 1\nbmesh a.ply 0 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match=r"bun.conf: line 1"):
        load_bunny(tmp_path)


def test_3dtk_load():
    s = load_3dtk(TDTK)
    assert is_3dtk_folder(TDTK) and not is_3dtk_folder(BUNNY)
    assert s.names == ["scan000", "scan001", "scan002"] and s.points.shape == (3, 3836, 3)  # excerpt: <= 3836 points in range
    assert (s.unit, s.unit_scale, s.ordered, s.pose_dof) == ("cm", 100.0, True, 6)
    assert s.valid.sum() < 3 * 4005  # the excerpt's points out of range (cm: [48, 3276]) or behind are dropped
    r = np.linalg.norm(s.points[s.valid], axis=1)
    assert r.min() >= 0.48 - 1e-6 and r.max() <= 32.76 + 1e-5 and (s.points[s.valid][:, 2] > -0.001).all()
    for k in range(3):  # y points down: the ground (the densest height) ~0.4 m below, trees up to -6 m
        y = s.points[k][s.valid[k], 1]
        h, edges = np.histogram(y, bins=np.arange(-3.0, 3.0, 0.05))
        assert 0.2 < edges[h.argmax()] < 0.6 and np.percentile(y, 1) < -3.0
    for k, name in enumerate(s.names):
        frames = read_frames(TDTK / f"{name}.frames")
        np.testing.assert_array_equal(s.gt_poses[k], frames[-1])
    np.testing.assert_allclose(np.linalg.det(s.init_poses[:, :3, :3]), 1.0, atol=1e-12)
    use = load_3dtk(TDTK, use_frames=True, max_points=100)
    np.testing.assert_array_equal(use.init_poses, use.gt_poses)


def test_3dtk_points_are_mirrored_metres():
    s = load_3dtk(TDTK, max_points=None, min_range=0.0, max_range=np.inf)
    raw = read_3d(TDTK / "scan001.3d")
    np.testing.assert_allclose(s.points[1][: len(raw)], raw * [0.01, -0.01, 0.01], rtol=1e-6, atol=1e-7)


def test_3dtk_pose_matches_first_frame():
    """scan002's first .frames line (code 0) is its .pose: R = Rx Ry Rz, p_world = R p + t."""
    frames, codes = read_frames(TDTK / "scan002.frames", return_codes=True)
    assert list(codes) == [0, 0, 1]
    init = load_3dtk(TDTK, max_points=10).init_poses
    np.testing.assert_allclose(init[2][:3, :3], frames[0][:3, :3], atol=1e-6)  # 6 printed digits
    np.testing.assert_array_equal(init[2][:3, 3], frames[0][:3, 3])
    raw = read_pose(TDTK / "scan002.pose")
    rzyx = Rotation.from_euler("ZYX", np.radians([-0.479231, -0.470508, 1.11333])).as_matrix()  # = Rz Ry Rx
    assert np.abs(raw[:3, :3] - rzyx).max() > 1e-4  # the other order is measurably wrong


def test_frames_round_trip(tmp_path):
    files = sorted(TDTK.glob("*.frames"))
    assert [f.name for f in files] == ["scan000.frames", "scan001.frames", "scan002.frames"]  # not vacuous
    for f in files:
        poses, codes = read_frames(f, return_codes=True)
        write_frames(tmp_path / f.name, poses, codes)
        a = np.loadtxt(f)
        b = np.loadtxt(tmp_path / f.name)
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(read_frames(tmp_path / f.name), poses)


def test_pose_round_trip(tmp_path):
    """write_pose (loaded frame) -> read_pose (3DTK numbers) is the loader's own .pose reading."""
    init = load_3dtk(TDTK, max_points=10).init_poses
    for k, pose in enumerate(init):
        write_pose(tmp_path / f"scan{k:03d}.pose", pose)
        raw_ours = read_pose(tmp_path / f"scan{k:03d}.pose")
        raw_theirs = read_pose(TDTK / f"scan{k:03d}.pose")
        np.testing.assert_allclose(raw_ours, raw_theirs, atol=1e-9)


def test_3dtk_xyz_is_read_like_3d(tmp_path):
    """A scanNNN.xyz (right-handed, z up) holds uos (x, y, z) as (z, -x, y); 3DTK turns it back."""
    uos = read_3d(TDTK / "scan001.3d")[:500]
    np.savetxt(tmp_path / "scan001.xyz", np.column_stack([uos[:, 2], -uos[:, 0], uos[:, 1]]))
    np.testing.assert_allclose(read_3d(tmp_path / "scan001.xyz"), uos, atol=1e-9)
    (tmp_path / "scan000.xyz").write_text("100 0 0\n0 100 0\n0 0 100\n")
    for k in (0, 1):
        (tmp_path / f"scan{k:03d}.pose").write_text("0 0 0\n0 0 0\n")
    assert is_3dtk_folder(tmp_path)
    scans = load_3dtk(tmp_path, min_range=0.0)
    np.testing.assert_allclose(scans.points[0][:3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-6)  # metres, y down


def _tiny_3dtk(folder: Path, pose1="1 2 3\n4 5 6\n", points1="100 0 50\n0 -40 200\n"):
    folder.mkdir()
    (folder / "scan000.3d").write_text("2 x 3\n100 10 100\n-100 -40 150\n")  # a header line
    (folder / "scan000.pose").write_text("0 0 0\n0 0 0\n")
    (folder / "scan001.3d").write_text(points1)
    (folder / "scan001.pose").write_text(pose1)
    return folder


def test_3dtk_errors(tmp_path):
    s = load_3dtk(_tiny_3dtk(tmp_path / "ok"))
    assert s.points.shape == (2, 2, 3) and s.gt_poses is None
    np.testing.assert_allclose(s.points[0, 0], [1.0, -0.1, 1.0])
    with pytest.raises(InputError, match="scan001.pose"):
        load_3dtk(_tiny_3dtk(tmp_path / "pose", pose1="1 2 3\n4 five 6\n"))
    with pytest.raises(InputError, match="scan001.pose"):
        load_3dtk(_tiny_3dtk(tmp_path / "short", pose1="1 2 3\n4 5\n"))
    with pytest.raises(InputError, match=r"scan001.3d: line 2"):
        load_3dtk(_tiny_3dtk(tmp_path / "nan", points1="100 0 50\nnan 1 2\n"))
    with pytest.raises(InputError, match="scan001.3d"):
        load_3dtk(_tiny_3dtk(tmp_path / "bad", points1="100 0 50\n1 2 x\n"))
    with pytest.raises(InputError, match="scan.frames: line 1"):
        (tmp_path / "scan.frames").write_text("1 0 0 0\n")
        read_frames(tmp_path / "scan.frames")
