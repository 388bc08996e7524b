"""Simulated AVD-style RGB-D (depth only) trajectories (section 4.2 of the paper).

Camera: pinhole, OpenCV frame (x right, y down, z forward), upright, at height y = 0 of the
y-down world of ``scene3d``; a camera-to-world pose is ``se3.from_planar_xz([x, z, theta])``.
Default intrinsics: 80 x 60 px, fx = fy = 69.28 (60 deg horizontal, 46.8 deg vertical field
of view, close to AVD's Kinect-like ~60 x 45 deg), principal point at the image centre
(39.5, 29.5). Depth images store z (not ray length) as uint16 millimetres, 0 = no return
(nothing hit or beyond ``max_depth_m``, default 7 m).

AVD protocol: camera positions on a 0.3 m grid, 12 views per position, 30 deg apart. A
trajectory starts at a random free position and view; each step is a move to a random
4-neighbouring free grid position (view kept) with probability ``p_move`` = 0.5, else a
rotation by +30 or -30 deg (equally likely, position kept). A step never returns to a
(position, view) already in the trajectory; when no step is possible the walk restarts.

``write_rgbd_dataset`` lets ``trajectories_per_scene`` (default 2) consecutive trajectories
share one scene: trajectory t uses scene seed ``1000 * seed + t // trajectories_per_scene``.
"""

from __future__ import annotations

import io
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from deepmapping.geometry import se3
from deepmapping.io.atomic import atomic_write, write_json
from deepmapping.io.poses3d import write_kitti_poses
from deepmapping.sim.raycast import caster_for
from deepmapping.sim.scene3d import make_scene

__all__ = ["Intrinsics", "render_depth", "grid_trajectory", "simulate_rgbd_trajectory",
           "write_rgbd_dataset"]

VIEW_STEP_DEG = 30.0


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels; pixel (u, v) has its centre at (u, v)."""

    width: int = 80
    height: int = 60
    fx: float = float(40.0 / np.tan(np.radians(30.0)))
    fy: float = float(40.0 / np.tan(np.radians(30.0)))
    cx: float = 39.5
    cy: float = 29.5

    @classmethod
    def from_hfov(cls, width: int, height: int, hfov_deg: float) -> "Intrinsics":
        f = (width / 2) / np.tan(np.radians(hfov_deg) / 2)
        return cls(width, height, float(f), float(f), (width - 1) / 2, (height - 1) / 2)

    def ray_directions(self) -> np.ndarray:
        """(H*W, 3) camera-frame directions with z = 1, row-major pixels (j = v * W + u)."""
        v, u = np.mgrid[0 : self.height, 0 : self.width]
        d = np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones(u.shape)], axis=-1)
        return d.reshape(-1, 3)


def render_depth(scene, pose: np.ndarray, intrinsics: Intrinsics | None = None, max_depth_m: float = 7.0,
                 noise_std_m: float = 0.0, rng: np.random.Generator | None = None) -> np.ndarray:
    """Depth image (H, W) uint16 mm seen from camera-to-world ``pose`` (4x4); 0 = no return.

    ``noise_std_m`` > 0 adds Gaussian noise to z (drawn from ``rng``) before rounding to mm.
    """
    intr = intrinsics or Intrinsics()
    pose = np.asarray(pose, dtype=np.float64)
    dirs = intr.ray_directions() @ pose[:3, :3].T
    rays = np.concatenate([np.broadcast_to(pose[:3, 3], dirs.shape), dirs], axis=1)
    z = caster_for(scene).cast(rays)
    if noise_std_m > 0:
        z = z + (rng or np.random.default_rng()).normal(0.0, noise_std_m, z.shape)
    ok = np.isfinite(z) & (z <= max_depth_m) & (z > 0)
    mm = np.where(ok, np.round(np.where(ok, z, 0.0) * 1000.0), 0.0)
    return np.clip(mm, 0, 65535).astype(np.uint16).reshape(intr.height, intr.width)


def _walk(free: set, frames: int, rng, p_move: float, views: int):
    start = sorted(free)[rng.integers(len(free))]
    state = (start, int(rng.integers(views)))
    path, seen = [state], {state}
    while len(path) < frames:
        (i, j), v = path[-1]
        moves = [((i + di, j + dj), v) for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1))]
        moves = [s for s in moves if s[0] in free and s not in seen]
        turns = [s for s in (((i, j), (v + 1) % views), ((i, j), (v - 1) % views)) if s not in seen]
        if not moves and not turns:
            return None
        pick = moves if (moves and (not turns or rng.random() < p_move)) else turns
        state = pick[rng.integers(len(pick))]
        path.append(state)
        seen.add(state)
    return path


def grid_trajectory(scene, frames: int, rng: np.random.Generator, p_move: float = 0.5) -> np.ndarray:
    """(frames, 3) planar poses [x, z, theta] following the AVD grid protocol (module docstring)."""
    g = scene.grid_m
    free = {tuple(ij) for ij in np.round(scene.free_positions / g).astype(int).tolist()}
    if not free:
        raise ValueError("scene has no free grid position")
    views = int(round(360.0 / VIEW_STEP_DEG))
    for _ in range(100):
        path = _walk(free, frames, rng, p_move, views)
        if path is not None:
            return np.array([[i * g, j * g, np.radians(v * VIEW_STEP_DEG)] for (i, j), v in path])
    raise ValueError(f"no {frames}-frame trajectory without revisits found in this scene")


def simulate_rgbd_trajectory(scene, frames: int, rng: np.random.Generator, intrinsics: Intrinsics | None = None,
                             max_depth_m: float = 7.0, noise_std_m: float = 0.0, p_move: float = 0.5):
    """Render one AVD-style trajectory: (depth (K, H, W) uint16 mm, camera-to-world poses (K, 4, 4))."""
    poses = se3.from_planar_xz(grid_trajectory(scene, frames, rng, p_move))
    depth = np.stack([render_depth(scene, T, intrinsics, max_depth_m, noise_std_m, rng) for T in poses])
    return depth, poses


def _write_png16(path, img: np.ndarray) -> None:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(img, dtype=np.uint16)).save(buf, format="PNG")
    atomic_write(path, lambda f: f.write(buf.getvalue()))


def write_rgbd_dataset(out_dir: str | os.PathLike, num_trajectories: int = 10, frames: int = 16, seed: int = 0,
                       intrinsics: Intrinsics | None = None, max_depth_m: float = 7.0, noise_std_m: float = 0.0,
                       p_move: float = 0.5, trajectories_per_scene: int = 2) -> list[Path]:
    """Write ``traj_000/ ...`` folders (depth/NNNNNN.png, intrinsics.json, gt_poses.txt, meta.json)."""
    intr = intrinsics or Intrinsics()
    scenes: dict[int, object] = {}
    folders = []
    for t in range(num_trajectories):
        scene_seed = 1000 * seed + t // trajectories_per_scene
        if scene_seed not in scenes:
            scenes[scene_seed] = make_scene(scene_seed)
        scene = scenes[scene_seed]
        depth, poses = simulate_rgbd_trajectory(scene, frames, np.random.default_rng([seed, t, 1]), intr,
                                                max_depth_m, noise_std_m, p_move)
        folder = Path(out_dir) / f"traj_{t:03d}"
        (folder / "depth").mkdir(parents=True, exist_ok=True)
        for k, img in enumerate(depth):
            _write_png16(folder / "depth" / f"{k:06d}.png", img)
        write_json(folder / "intrinsics.json", {**asdict(intr), "depth_scale": 1000.0, "max_depth_m": max_depth_m})
        write_kitti_poses(folder / "gt_poses.txt", poses)
        write_json(folder / "meta.json", {
            "kind": "rgbd", "pose_dof": 3, "seed": seed, "trajectory": t, "scene": scene_seed, "frames": frames,
            "grid_m": scene.grid_m, "view_step_deg": VIEW_STEP_DEG, "p_move": p_move, "noise_std_m": noise_std_m,
            "frame": "camera OpenCV (x right, y down, z forward); world y down; poses camera-to-world, metres"})
        folders.append(folder)
    return folders
