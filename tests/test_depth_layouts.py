"""Depth-image layouts of real data: 7-Scenes / 3DMatch and TUM RGB-D, the frame and pixel
options they share with the rgbd layout, and their errors. Tiny synthetic folders written here with
PIL, the library the readers use."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from deepmapping.errors import ConfigError, InputError
from deepmapping.geometry import se3
from deepmapping.io.depth import (
    INTRINSICS_PRESETS,
    DepthOptions,
    parse_frames,
    parse_image_size,
    pixel_grid,
    select_frames,
)
from deepmapping.io.loaders import detect_format, load_scans
from deepmapping.io.sevenscenes import load_7scenes
from deepmapping.io.tum_rgbd import MAX_DT_S, load_tum_rgbd, match_timestamps

W, H, F, C = 16, 12, 20.0, (7.5, 5.5)  # a small pinhole camera: fx = fy = 20, principal point (7.5, 5.5)
K_TEXT = f"{F} 0 {C[0]}\n0 {F} {C[1]}\n0 0 1\n"


def png16(path: Path, img) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(img, np.uint16)).save(path)


def plane_depth(scale: float, n=(0.1, -0.2, 1.0), d=2.0, cam=None) -> np.ndarray:
    """Depth (H, W) in 1/scale metres of the plane n . p = d seen by the small camera (or by ``cam``,
    a preset: its image size)."""
    h, w, fx, fy, cx, cy = (H, W, F, F, *C) if cam is None else (cam.height, cam.width, cam.fx, cam.fy, cam.cx, cam.cy)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    ray = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1)
    return np.round(d / (ray @ np.asarray(n)) * scale)


def poses(k: int) -> np.ndarray:
    """Camera-to-world poses: a slow 6-DoF drift."""
    out = np.tile(np.eye(4), (k, 1, 1))
    for i in range(k):
        a = 0.02 * i
        out[i, :3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
        out[i, :3, 3] = [0.01 * i, -0.005 * i, 0.02 * i]
    return out


def seven_scenes(root: Path, k: int = 5, with_poses: bool = True, k_file: bool = True) -> Path:
    for i in range(k):
        png16(root / f"frame-{i:06d}.depth.png", plane_depth(1000.0) + i)
        if with_poses:
            (root / f"frame-{i:06d}.pose.txt").write_text("\n".join(" ".join(f"{x:.9e}" for x in row)
                                                                     for row in poses(k)[i]) + "\n")
    if k_file:
        (root / "camera-intrinsics.txt").write_text(K_TEXT)
    return root


def tum(root: Path, k: int = 6, gt_offset_s: float = 0.004, gt_span: tuple[int, int] | None = None,
        default_camera: bool = False) -> Path:
    """depth at 30 Hz from t = 100 s; ground truth at 100 Hz (shifted by gt_offset_s) over gt_span frames.

    The small camera in camera-intrinsics.txt, or TUM's own folder (no camera file, 640 x 480 images)."""
    stamps = 100.0 + np.arange(k) / 30.0
    lines = ["# depth maps", "# file: 'fuzz.bag'", "# timestamp filename"]
    img = plane_depth(5000.0, cam=INTRINSICS_PRESETS["tum"] if default_camera else None)
    for t in stamps:
        png16(root / "depth" / f"{t:.6f}.png", img)
        lines.append(f"{t:.6f} depth/{t:.6f}.png")
    if not default_camera:
        (root / "camera-intrinsics.txt").write_text(K_TEXT)
    (root / "depth.txt").write_text("\n".join(lines) + "\n")
    first, last = gt_span or (0, k)
    gt_t = np.arange(stamps[first] - 0.005, stamps[last - 1] + 0.005, 0.01) + gt_offset_s
    q = se3.to_xyz_quat(np.tile(poses(1)[0], (len(gt_t), 1, 1)))
    q[:, 0] = gt_t  # x = the time: which gt line a frame took is visible in its pose
    (root / "groundtruth.txt").write_text("# ground truth\n" + "".join(
        f"{t:.4f} " + " ".join(f"{v:.9g}" for v in row) + "\n" for t, row in zip(gt_t, q)))
    return root


def one_line_error(fn, *names):
    with pytest.raises(InputError) as e:
        fn()
    msg = str(e.value)
    assert "\n" not in msg and all(n in msg for n in names), msg
    return msg


# ---------------------------------------------------------------------------------------------
def test_formats_are_picked_from_the_path(tmp_path):
    assert detect_format(seven_scenes(tmp_path / "7s")) == "7scenes"
    assert detect_format(tum(tmp_path / "tum")) == "tum-rgbd"
    png16(tmp_path / "avd" / "depth" / "000000.png", plane_depth(1000.0))  # depth/ without depth.txt
    assert detect_format(tmp_path / "avd") == "rgbd"


def test_7scenes_back_projects_a_known_plane_and_reads_its_poses(tmp_path):
    s = load_7scenes(seven_scenes(tmp_path), depth=DepthOptions(pixel_stride=1))
    assert (s.grid_shape, s.unit, s.unit_scale, s.pose_dof, s.num_scans) == ((H, W), "mm", 1000.0, 6, 5)
    p = s.points[0].reshape(H, W, 3).astype(np.float64)
    assert np.abs(p @ [0.1, -0.2, 1.0] - 2.0).max() < 1e-3  # on the plane, up to the mm rounding
    z = plane_depth(1000.0)[3, 10] / 1000.0
    np.testing.assert_allclose(p[3, 10], [(10 - C[0]) * z / F, (3 - C[1]) * z / F, z], rtol=1e-6)
    np.testing.assert_allclose(s.gt_poses, poses(5), atol=1e-8)
    assert s.names[1] == "frame-000001.depth.png" and s.valid.all()


def test_gt_poses_map_frames_into_one_world(tmp_path):
    """The frames see one plane from drifting poses: with the pose files, their points coincide."""
    root = tmp_path / "7s"
    gt = poses(3)
    n_world, d_world = np.array([0.1, -0.2, 1.0]), 2.5
    for i, pose in enumerate(gt):  # the world plane in camera i's frame: (R^T n) . p = d - n . t
        in_camera = plane_depth(1000.0, pose[:3, :3].T @ n_world, d_world - n_world @ pose[:3, 3])
        png16(root / f"frame-{i:06d}.depth.png", in_camera)
        (root / f"frame-{i:06d}.pose.txt").write_text("\n".join(" ".join(f"{v:.17g}" for v in r) for r in pose))
    (root / "camera-intrinsics.txt").write_text(K_TEXT)
    s = load_scans(root, depth=DepthOptions(pixel_stride=1))
    world = se3.transform_points(s.gt_poses, s.points.astype(np.float64))
    assert np.abs(world.reshape(-1, 3) @ n_world - d_world).max() < 2e-3


def test_invalid_depths_are_masked(tmp_path):
    root = seven_scenes(tmp_path, k=2)
    img = plane_depth(1000.0)
    img[0, 0], img[1, 1], img[2, 2] = 0, 65535, 3500
    png16(root / "frame-000000.depth.png", img)
    s = load_7scenes(root, depth=DepthOptions(pixel_stride=1, max_depth_m=3.0))
    bad = [0, W + 1, 2 * W + 2]
    assert not s.valid[0, bad].any() and s.valid[0].sum() == H * W - 3
    assert (s.points[0, bad] == 0).all()  # the all-zero point, as every loader's invalid beam
    assert load_7scenes(root, depth=DepthOptions(pixel_stride=1)).valid[0].sum() == H * W - 2


def test_frame_and_pixel_selection(tmp_path):
    root = seven_scenes(tmp_path, k=7)
    s = load_scans(root, depth=DepthOptions(every=2, frames=(1, 6), pixel_stride=4))
    assert s.names == ["frame-000001.depth.png", "frame-000003.depth.png", "frame-000005.depth.png"]
    np.testing.assert_allclose(s.gt_poses, poses(7)[[1, 3, 5]], atol=1e-8)
    assert s.grid_shape == (3, 4)
    sized = load_scans(root, depth=DepthOptions(image_size=(4, 3)))
    assert sized.grid_shape == (3, 4) and sized.num_scans == 7
    rows, cols = pixel_grid("x", 480, 640, DepthOptions(image_size=(80, 60)))
    assert rows[:2].tolist() == [4, 12] and cols[-1] == 636 and len(cols) == 80  # cell centres, stride 8
    assert load_scans(root).grid_shape == (H, W)  # at most ~80 pixels across by default: 16 stays 16
    assert select_frames("x", 50, DepthOptions(every=3, frames=(2, 48))).tolist() == list(range(2, 48, 3))
    assert parse_frames("0:48") == (0, 48) and parse_frames(":-2") == (None, -2) and parse_image_size("80x60") == (80, 60)


@pytest.mark.parametrize("opts, match", [
    (dict(every=0), "every"), (dict(pixel_stride=2, image_size=(4, 3)), "not both"),
    (dict(max_depth_m=-1.0), "max depth"), (dict(image_size=(0, 3)), "image size"),
])
def test_bad_options_are_config_errors(opts, match):
    with pytest.raises(ConfigError, match=match):
        DepthOptions(**opts)


def test_bad_selections_name_the_folder(tmp_path):
    root = seven_scenes(tmp_path, k=3)
    one_line_error(lambda: load_scans(root, depth=DepthOptions(frames=(2, None))), str(root), "1 frame(s) of 3")
    with pytest.raises(ConfigError, match="larger than the images"):
        load_scans(root, depth=DepthOptions(image_size=(W + 1, H)))
    with pytest.raises(ConfigError, match="depth images"):
        load_scans(root, fmt="folder", depth=DepthOptions(every=2))


def test_7scenes_errors_name_the_file(tmp_path):
    root = seven_scenes(tmp_path / "a", k_file=False)
    one_line_error(lambda: load_7scenes(root), "camera-intrinsics.txt", "not found")
    one_line_error(lambda: load_7scenes(root, depth=DepthOptions(intrinsics="7scenes")), "frame-000000.depth.png",
                   "image is 16x12 but the camera was given for 640x480")  # the preset is for 7-Scenes' images
    (root.parent / "camera-intrinsics.txt").write_text(K_TEXT)  # 3DMatch keeps K next to its seq-NN folders
    assert load_7scenes(root).num_scans == 5
    root = seven_scenes(tmp_path / "b")
    (root / "frame-000003.pose.txt").unlink()
    one_line_error(lambda: load_7scenes(root), "frame-000003.pose.txt", "4 pose files for 5 depth images")
    (root / "frame-000003.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 nan\n0 0 0 1\n")
    one_line_error(lambda: load_7scenes(root), "frame-000003.pose.txt", "NaN")
    (root / "frame-000003.pose.txt").write_text("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    one_line_error(lambda: load_7scenes(root), "frame-000003.pose.txt", "not a rotation")
    (root / "frame-000003.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    one_line_error(lambda: load_7scenes(root), "frame-000003.pose.txt", "16 numbers")
    Image.fromarray(np.full((H, W), 7, np.uint8)).save(root / "frame-000002.depth.png")
    one_line_error(lambda: load_7scenes(root, depth=DepthOptions(frames=(0, 3))), "frame-000002.depth.png", "16-bit")
    (root / "camera-intrinsics.txt").write_text("585 0 320\n0 585 240\n")
    one_line_error(lambda: load_7scenes(root), "camera-intrinsics.txt", "9 numbers")


def test_tum_matches_timestamps_and_scales_depth(tmp_path):
    cam = INTRINSICS_PRESETS["tum"]  # no camera file: TUM's default camera, 640 x 480
    s = load_tum_rgbd(tum(tmp_path, default_camera=True))
    assert (s.num_scans, s.pose_dof, s.unit, s.notes, s.grid_shape) == (6, 6, "mm", [], (60, 80))  # stride 8
    z = plane_depth(5000.0, cam=cam)[24, 80] / 5000.0  # grid cell (3, 10) is pixel (24, 80)
    np.testing.assert_allclose(s.points[0].reshape(60, 80, 3)[3, 10], [(80 - cam.cx) * z / cam.fx,
                                                                       (24 - cam.cy) * z / cam.fy, z], rtol=1e-6)
    stamps = 100.0 + np.arange(6) / 30.0
    assert np.abs(s.gt_poses[:, 0, 3] - stamps).max() <= 0.005 + 1e-9  # each frame took the nearest gt line


def test_tum_drops_frames_without_ground_truth_and_says_so(tmp_path):
    root = tum(tmp_path, k=6, gt_span=(2, 6))  # mocap starts late: frames 0 and 1 have no pose within 20 ms
    s = load_tum_rgbd(root)
    assert s.num_scans == 4 and s.names[0] == f"{100 + 2 / 30:.6f}.png"
    assert len(s.notes) == 1 and "2 of 6 depth frames" in s.notes[0] and "groundtruth.txt" in s.notes[0]
    assert load_tum_rgbd(root, depth=DepthOptions(every=3)).names == [s.names[0], s.names[3]]  # selection after matching


def test_match_timestamps():
    ref = np.array([0.0, 0.1, 0.2, 0.5])
    got = match_timestamps(np.array([-0.03, 0.01, 0.149, 0.185, 0.34, 0.515, 0.9]), ref, MAX_DT_S)
    assert got.tolist() == [-1, 0, -1, 2, -1, 3, -1]
    assert match_timestamps(np.array([0.11]), ref[::-1]).tolist() == [2]  # unsorted reference


def test_tum_camera_override_and_presets(tmp_path):
    big = tum(tmp_path / "big", k=2, default_camera=True)
    fr1 = load_tum_rgbd(big, depth=DepthOptions(intrinsics="fr1"))
    cam = INTRINSICS_PRESETS["fr1"]
    assert fr1.points[0, 0, 0] == pytest.approx((0 - cam.cx) * fr1.points[0, 0, 2] / cam.fx, rel=1e-6)
    root = tum(tmp_path / "small")
    one_line_error(lambda: load_tum_rgbd(root, depth=DepthOptions(intrinsics="fr1")), "16x12", "640x480")
    own = load_tum_rgbd(root, depth=DepthOptions(pixel_stride=1))
    assert np.abs(own.points[0].reshape(H, W, 3).astype(float) @ [0.1, -0.2, 1.0] - 2.0).max() < 1e-3
    (root / "camera-intrinsics.txt").unlink()
    (root / "intrinsics.json").write_text(json.dumps({"width": W, "height": H, "fx": F, "fy": F, "cx": C[0],
                                                      "cy": C[1], "depth_scale": 5000.0}))
    np.testing.assert_array_equal(load_tum_rgbd(root, depth=DepthOptions(pixel_stride=1)).points, own.points)
    one_line_error(lambda: load_tum_rgbd(root, depth=DepthOptions(intrinsics=str(tmp_path / "nope.txt"))), "nope.txt")


def test_tum_errors_name_the_file(tmp_path):
    root = tum(tmp_path / "a")
    (root / "groundtruth.txt").unlink()
    (root / "depth.txt").write_text((root / "depth.txt").read_text() + "100.5 depth/missing.png\n")
    one_line_error(lambda: load_tum_rgbd(root, depth=DepthOptions(frames=(5, None))), "missing.png", "not found")
    (root / "depth.txt").write_text("100.0 depth/a.png\n99.0 depth/b.png\n")
    one_line_error(lambda: load_tum_rgbd(root), "depth.txt", "line 2", "increasing")
    (root / "depth.txt").write_text("# nothing\n")
    one_line_error(lambda: load_tum_rgbd(root), "depth.txt", "no depth frame")
    root = tum(tmp_path / "b")
    gt = root / "groundtruth.txt"
    gt.write_text(gt.read_text().replace("\n", " 7\n", 3))
    one_line_error(lambda: load_tum_rgbd(root), "groundtruth.txt", "expected 8 columns")
    gt.write_text("5.0 0 0 0 0 0 0 1\n5.1 0 0 0 0 0 0 1\n")  # another sequence's times
    one_line_error(lambda: load_tum_rgbd(root), "groundtruth.txt", "0 of 6 depth frames")
    gt.unlink()
    assert load_tum_rgbd(root).gt_poses is None  # no ground truth: every frame, nothing to evaluate


def test_auto_warm_start_is_icp_for_handheld_depth(tmp_path):
    from deepmapping.api import auto_warm_start

    s = load_scans(seven_scenes(tmp_path), depth=DepthOptions(pixel_stride=1))
    assert auto_warm_start(s) == "icp-plane"  # handheld, 6-DoF depth images (was a cold start)
    s.pose_dof = 3
    assert auto_warm_start(s) == "icp-planar"  # AVD-like: planar poses


def test_handheld_depth_gets_the_handheld_profile(tmp_path):
    from deepmapping.cli.register_cmd import build_config, settings_line

    s = load_scans(seven_scenes(tmp_path), depth=DepthOptions(pixel_stride=1))
    assert s.handheld
    cfg = build_config("default", None, "deepmapping", None, None, None, None, None, {}, s.is_3d, handheld=s.handheld)
    assert cfg.profile == "handheld" and cfg.loss.chamfer_metric == "plane" and cfg.optim.batch_size == 16
    cold = build_config("default", None, "deepmapping", None, "none", None, None, None, {}, True, handheld=True)
    assert cold.profile == "default-3d"
    # what the command prints before it starts
    assert settings_line(s, cfg) == "settings: profile handheld, warm start icp-plane (auto), 200 epochs"
    assert settings_line(s, cold) == "settings: profile default-3d, warm start none, 200 epochs"
    assert settings_line(s, cfg.with_overrides({"method": "multiway"})) == "settings: profile handheld, method multiway"
    s.pose_dof = 3  # AVD-like: planar poses
    assert not s.handheld


def test_success_threshold_follows_the_data(tmp_path):
    """450 mm only for the AVD protocol (depth images, planar poses); 2 % of the typical range else."""
    from deepmapping.api import evaluate_poses
    from deepmapping.evaluation.metrics3d import AVD_SUCCESS_M, RELATIVE_SUCCESS, typical_range

    s = load_scans(seven_scenes(tmp_path), depth=DepthOptions(pixel_stride=1))
    m = evaluate_poses(s, poses(5))
    assert m["unit"] == "mm" and m["success"]
    assert m["success_threshold"] == pytest.approx(1000 * RELATIVE_SUCCESS * typical_range(s.points, s.valid))
    assert 40 < m["success_threshold"] < 50  # the plane is about 2.2 m away
    s.pose_dof = 3
    assert evaluate_poses(s, s.gt_poses)["success_threshold"] == pytest.approx(1000 * AVD_SUCCESS_M)
    assert evaluate_poses(s, s.gt_poses, success_threshold=5.0)["success_threshold"] == 5.0


def test_rendered_room_through_the_7scenes_layout(tmp_path):
    """A simulated room saved as 7-Scenes (K file, 6-DoF camera-to-world pose files, OpenCV axes):
    the loaded gt poses put the frames' points on each other."""
    from deepmapping.sim.rgbd import Intrinsics, render_depth
    from deepmapping.sim.scene3d import make_scene

    scene, intr = make_scene(1), Intrinsics()
    x, z = scene.free_positions[len(scene.free_positions) // 2]
    gt = []
    for i in range(4):  # turning about y (6 deg a frame), tilting, rising and moving: 6-DoF
        rot = Rotation.from_euler("yxz", [0.1 * i, 0.03 * i, 0.02]).as_matrix()
        r = se3.from_rt(rot, [x + 0.05 * i, -0.02 * i, z + 0.03 * i])
        gt.append(r)
        png16(tmp_path / f"frame-{i:06d}.depth.png", render_depth(scene, r, intr))
        (tmp_path / f"frame-{i:06d}.pose.txt").write_text("\n".join(" ".join(f"{v:.17g}" for v in row) for row in r))
    (tmp_path / "camera-intrinsics.txt").write_text(f"{intr.fx} 0 {intr.cx}\n0 {intr.fy} {intr.cy}\n0 0 1\n")
    s = load_scans(tmp_path)
    assert s.grid_shape == (60, 80) and s.valid.mean() > 0.5
    world = se3.transform_points(s.gt_poses, s.points.astype(np.float64))
    d, _ = cKDTree(world[0][s.valid[0]]).query(world[1][s.valid[1]])
    assert np.median(d) < 0.02
    wrong = se3.compose(s.gt_poses, np.diag([1.0, -1.0, -1.0, 1.0]))  # an OpenGL camera (y up, z back) instead
    world = se3.transform_points(wrong, s.points.astype(np.float64))
    assert np.median(cKDTree(world[0][s.valid[0]]).query(world[1][s.valid[1]])[0]) > 0.05
