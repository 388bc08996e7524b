"""Tests of the 2D lidar simulator: maps, exact DDA ray casting, trajectories, data set files."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.io
from scipy import ndimage

from deepmapping.errors import InputError
from deepmapping.io.pcd import read_pcd
from deepmapping.sim.dataset import simulate, write_authors_layout
from deepmapping.sim.maps import load_map_png, procedural_indoor_map, save_map_png
from deepmapping.sim.scanner import cast_rays, simulate_scan, simulate_scans
from deepmapping.sim.trajectory import clearance_map, sample_trajectory


def box_room(n: int = 100, wall: int = 1) -> np.ndarray:
    occ = np.full((n, n), 255, np.uint8)
    occ[:wall, :] = occ[-wall:, :] = occ[:, :wall] = occ[:, -wall:] = 0
    return occ


def cluttered_room(n: int = 400) -> np.ndarray:
    occ = box_room(n, 4)
    occ[100:130, 150:190] = 0
    occ[260:300, 60:80] = 0
    rr, cc = np.ogrid[:n, :n]
    occ[(rr + 0.5 - 280) ** 2 + (cc + 0.5 - 300) ** 2 <= 20**2] = 0
    return occ


def rot(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


# ---------------------------------------------------------------- scanner


def test_box_room_hand_computed_hits() -> None:
    occ = box_room(100)
    pts, valid = simulate_scan(occ, np.array([50.5, 50.5, 0.0]), num_beams=256)
    assert valid.all()
    # beam 0 (+x) hits the left edge of the right wall column 99: x = 99 exactly
    np.testing.assert_allclose(pts[0], [48.5, 0.0], atol=1e-12)
    # beam 64 (+y, down in the image) hits the top edge of row 99
    np.testing.assert_allclose(pts[64], [0.0, 48.5], atol=1e-12)
    # beam 128 (-x) hits the right edge of column 0: x = 1
    np.testing.assert_allclose(pts[128], [-49.5, 0.0], atol=1e-12)
    # beam 32 (45 deg) reaches the corner (99, 99)
    np.testing.assert_allclose(pts[32], [48.5, 48.5], atol=1e-9)
    # a rotated sensor sees the same wall in its own frame
    pts_r, _ = simulate_scan(occ, np.array([50.5, 50.5, np.pi / 2]), num_beams=4)
    np.testing.assert_allclose(pts_r[0], [48.5, 0.0], atol=1e-9)  # global +y
    np.testing.assert_allclose(pts_r[1], [0.0, 49.5], atol=1e-9)  # sensor +y = global -x


def test_hits_are_exact_on_obstacle_pixel_boundaries() -> None:
    occ = procedural_indoor_map(3, size=256)
    rng = np.random.default_rng(0)
    free = np.argwhere(clearance_map(occ) >= 2)
    cells = free[rng.choice(len(free), 50)]
    origins = np.repeat(cells[:, ::-1] + rng.uniform(0, 1, (50, 2)), 64, axis=0)
    angles = rng.uniform(-np.pi, np.pi, origins.shape[0])
    hits, ranges, valid = cast_rays(occ, origins, angles)
    assert valid.all()
    integral = (hits == np.round(hits))
    assert integral.any(axis=1).all()  # one coordinate lies exactly on a grid line
    # the hit is on the ray ...
    d = np.stack([np.cos(angles), np.sin(angles)], 1)
    np.testing.assert_allclose(origins + ranges[:, None] * d, hits, atol=1e-9)
    # ... and on the boundary of an obstacle pixel square (or of the image)
    h, w = occ.shape
    eps = 1e-6
    probe = hits + eps * d
    c = np.floor(probe[:, 0]).astype(int)
    r = np.floor(probe[:, 1]).astype(int)
    outside = (c < 0) | (r < 0) | (c >= w) | (r >= h)
    assert (outside | (occ[np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)] == 0)).all()
    # nothing is skipped: a fine march along the ray meets no obstacle before the hit
    s = np.linspace(0, 1, 4000)[None, :, None]
    march = origins[:, None, :] + s * (ranges[:, None, None] - 1e-6) * d[:, None, :]
    mc = np.floor(march[..., 0]).astype(int)
    mr = np.floor(march[..., 1]).astype(int)
    assert (occ[mr, mc] == 255).all()


def test_sensor_frame_points_match_global_hits() -> None:
    occ = procedural_indoor_map(1, size=256)
    poses = sample_trajectory(occ, num_poses=6, seed=2)
    pts, valid = simulate_scans(occ, poses, num_beams=32)
    for k, pose in enumerate(poses):
        ang = pose[2] + 2 * np.pi * np.arange(32) / 32
        hits, _, _ = cast_rays(occ, np.repeat(pose[None, :2], 32, 0), ang)
        np.testing.assert_allclose(pts[k] @ rot(pose[2]).T + pose[:2], hits, atol=1e-9)
        one, _ = simulate_scan(occ, pose, num_beams=32)
        np.testing.assert_array_equal(one, pts[k])


def test_unlimited_range_returns_image_border() -> None:
    occ = np.full((64, 64), 255, np.uint8)
    pts, valid = simulate_scan(occ, np.array([10.25, 20.5, 0.0]), num_beams=4)
    assert valid.all()
    np.testing.assert_allclose(pts, [[53.75, 0], [0, 43.5], [-10.25, 0], [0, -20.5]], atol=1e-9)


def test_max_range_invalidates_far_beams() -> None:
    occ = box_room(100)
    pose = np.array([50.5, 50.5, 0.0])
    pts, valid = simulate_scan(occ, pose, num_beams=4, max_range=49.0)
    assert valid.tolist() == [True, True, False, False]
    np.testing.assert_array_equal(pts[2:], 0.0)
    pts, valid = simulate_scan(occ, pose, num_beams=8, max_range=30.0)
    assert not valid.any() and (pts == 0).all()


def test_sensor_inside_obstacle_raises() -> None:
    with pytest.raises(ValueError):
        simulate_scan(box_room(100), np.array([0.5, 40.0, 0.0]))


# ---------------------------------------------------------------- maps


def test_procedural_map_connected_and_deterministic() -> None:
    for size in (256, 1024):
        a = procedural_indoor_map(7, size=size)
        assert a.shape == (size, size) and a.dtype == np.uint8
        assert set(np.unique(a).tolist()) == {0, 255}
        assert (a[0] == 0).all() and (a[-1] == 0).all() and (a[:, 0] == 0).all() and (a[:, -1] == 0).all()
        _, n = ndimage.label(a == 255)
        assert n == 1
        np.testing.assert_array_equal(a, procedural_indoor_map(7, size=size))
    assert not np.array_equal(procedural_indoor_map(1, 256), procedural_indoor_map(2, 256))


def test_map_png_roundtrip_and_errors(tmp_path) -> None:
    occ = procedural_indoor_map(0, size=128)
    save_map_png(tmp_path / "m.png", occ)
    np.testing.assert_array_equal(load_map_png(tmp_path / "m.png"), occ)
    missing = tmp_path / "nope.png"
    with pytest.raises(InputError, match=f"^{missing}: "):
        load_map_png(missing)
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not a png")
    with pytest.raises(InputError, match=f"^{bad}: "):
        load_map_png(bad)


# ---------------------------------------------------------------- trajectory


def test_trajectory_statistics_clearance_and_determinism() -> None:
    occ = cluttered_room(400)
    poses = sample_trajectory(occ, num_poses=256, seed=3)
    assert poses.shape == (256, 3) and poses.dtype == np.float64
    d = np.diff(poses, axis=0)
    dth = (d[:, 2] + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(dth).max() <= np.deg2rad(10.0) + 1e-9
    assert np.all((poses[:, 2] > -np.pi) & (poses[:, 2] <= np.pi))
    steps = np.hypot(d[:, 0], d[:, 1])
    assert abs(steps.mean() - 8.16) <= 0.2 * 8.16
    # translation is along the new heading
    moving = steps > 0
    heading = np.arctan2(d[moving, 1], d[moving, 0])
    err = (heading - poses[1:][moving, 2] + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(err).max() < 1e-9
    # every pose (and points along every segment) keeps the clearance
    dist = clearance_map(occ)
    s = np.linspace(0, 1, 33)[None, :, None]
    seg = poses[:-1, None, :2] + s * d[:, None, :2]
    pts = np.concatenate([poses[:, :2], seg.reshape(-1, 2)])
    assert (dist[np.floor(pts[:, 1]).astype(int), np.floor(pts[:, 0]).astype(int)] >= 8.0).all()
    np.testing.assert_array_equal(poses, sample_trajectory(occ, num_poses=256, seed=3))
    assert not np.array_equal(poses, sample_trajectory(occ, num_poses=256, seed=4))


def test_trajectory_never_stuck_in_a_dead_end() -> None:
    occ = np.zeros((80, 200), np.uint8)
    occ[30:50, 5:195] = 255  # a 20 px corridor: no U-turn possible, must turn in place
    poses = sample_trajectory(occ, num_poses=120, seed=0)
    assert len(poses) == 120
    dist = clearance_map(occ)
    assert (dist[np.floor(poses[:, 1]).astype(int), np.floor(poses[:, 0]).astype(int)] >= 8.0).all()


# ---------------------------------------------------------------- data set files


def test_simulate_and_authors_layout_roundtrip(tmp_path) -> None:
    occ = procedural_indoor_map(5, size=256)
    scans = simulate(occ, num_poses=6, seed=1, num_beams=64, max_range=60.0)
    scans.validate()
    assert scans.points.shape == (6, 64, 2) and scans.points.dtype == np.float32
    assert scans.unit_scale == 512 and scans.unit == "px" and scans.ordered
    assert scans.names[:2] == ["000", "001"]
    assert (~scans.valid).any()
    assert (scans.points[~scans.valid] == 0).all()
    gt_px = scans.gt_poses.copy()
    gt_px[:, :2] *= 512
    np.testing.assert_array_equal(gt_px, sample_trajectory(occ, 6, seed=1))

    out = write_authors_layout(tmp_path / "traj", scans, occ=occ)
    for k in range(6):
        xyz = read_pcd(out / f"{k:03d}.pcd")
        assert xyz.shape == (64, 3)
        np.testing.assert_array_equal(xyz[:, :2], scans.points[k])
        assert (xyz[:, 2] == 0).all()
    pose = scipy.io.loadmat(out / "gt_pose.mat")["pose"]
    np.testing.assert_allclose(pose, gt_px, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(load_map_png(out / "env.png"), occ)
    assert (out / "map.png").stat().st_size > 0
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temp files left
