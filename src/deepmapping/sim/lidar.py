"""Simulated spinning LiDAR moving smoothly through a ``scene3d`` scene, with 6-DoF ground truth.

Sensor frame: x forward, y left, z up (the usual LiDAR frame). The world is the y-down frame
of ``scene3d`` (x right, y down, z forward), so at yaw 0 the sensor x axis is world +z, y is
world -x and z is world -y (up). A pose maps sensor -> world:
``R = R_y(yaw) @ BASE @ R_y(pitch) @ R_x(roll)``, ``t = [x, -dh, z]`` with dh the height above
the nominal sensor height (world y = 0, ``camera_height`` above the floor).

Beams: ``beams`` elevations evenly spread over ``vfov_deg`` (defaults: 16 -> ±15 deg like a
VLP-16, 32 -> -30.67..+10.67 like an HDL-32E, 64 -> -24.9..+2 like an HDL-64E), azimuths every
``azimuth_res_deg`` over 360 deg. Returns beyond ``max_range_m`` (or none) are dropped.

Trajectory: a random walk over the free grid of the scene that keeps going straight for
at least 2 grid steps after a turn (then with p = 0.75) and never enters dead ends, smoothed
(Gaussian, sigma 0.3 m) and resampled every ``step_m`` (0.4 m) along its length; yaw follows
the path tangent (smoothed, sigma 0.5 m); roll/pitch wobble (±``wobble_deg``, 3 deg) and the
height (±``height_var_m``, 0.1 m) vary as random sinusoids of the distance travelled.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from deepmapping.geometry import se3
from deepmapping.io.atomic import write_json
from deepmapping.io.ply import write_ply
from deepmapping.io.poses3d import write_kitti_poses
from deepmapping.sim.raycast import caster_for
from deepmapping.sim.scene3d import make_scene

__all__ = ["LidarConfig", "BASE", "lidar_pose", "smooth_trajectory", "scan", "simulate_lidar_trajectory",
           "write_lidar_dataset"]

BASE = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # sensor axes in world, yaw 0
_VFOV = {16: (-15.0, 15.0), 32: (-30.67, 10.67), 64: (-24.9, 2.0)}


@dataclass(frozen=True)
class LidarConfig:
    beams: int = 16
    vfov_deg: tuple[float, float] | None = None  # None: by beam count (module docstring)
    azimuth_res_deg: float = 1.0
    max_range_m: float = 20.0
    min_range_m: float = 0.1
    noise_std_m: float = 0.0

    def directions(self) -> np.ndarray:
        """(beams * azimuths, 3) unit ray directions in the sensor frame, beam-major."""
        lo, hi = self.vfov_deg or _VFOV.get(self.beams, (-15.0, 15.0))
        el = np.radians(np.linspace(lo, hi, self.beams))[:, None]
        az = np.radians(np.arange(0.0, 360.0, self.azimuth_res_deg))[None, :]
        d = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), axis=-1)
        return d.reshape(-1, 3)


def lidar_pose(x, z, yaw, dh=0.0, roll=0.0, pitch=0.0) -> np.ndarray:
    """Sensor-to-world poses (..., 4, 4) from position, heading (about world y) and wobble."""
    yaw_rot = se3.from_planar_xz(np.stack(np.broadcast_arrays(x, z, yaw), axis=-1))
    rp = Rotation.from_euler("xy", np.stack(np.broadcast_arrays(roll, pitch), axis=-1)).as_matrix()
    T = se3.from_rt(yaw_rot[..., :3, :3] @ BASE @ rp, yaw_rot[..., :3, 3])
    T[..., 1, 3] = -np.asarray(dh, dtype=np.float64)
    return T


def _prune_dead_ends(free: set) -> set:
    """Drop grid points with fewer than 2 free 4-neighbours, repeatedly (keeps ``free`` if all go)."""
    cells = set(free)
    while True:
        dead = {(i, j) for i, j in cells
                if sum((i + a, j + b) in cells for a, b in ((1, 0), (-1, 0), (0, 1), (0, -1))) < 2}
        if not dead:
            return cells or free
        cells -= dead


def _grid_walk(scene, length: float, rng) -> np.ndarray:
    """(M, 2) grid points [x, z] of a momentum random walk at least ``length`` metres long."""
    g = scene.grid_m
    free = _prune_dead_ends({tuple(ij) for ij in np.round(scene.free_positions / g).astype(int).tolist()})
    if not free:
        raise ValueError("scene has no free grid position")
    cur = sorted(free)[rng.integers(len(free))]
    steps = [(1, 0), (-1, 0), (0, 1), (0, -1)]
    heading = steps[rng.integers(4)]
    path, run = [cur], 0
    while (len(path) - 1) * g < length:
        nxt = [s for s in steps if (cur[0] + s[0], cur[1] + s[1]) in free]
        if not nxt:  # isolated point: cannot happen for the largest component of > 1 point
            raise ValueError("free grid position without free neighbour")
        forward = heading in nxt and (run < 2 or rng.random() < 0.75)  # >= 2 steps between turns
        options = [s for s in nxt if s != (-heading[0], -heading[1])] or nxt
        new = heading if forward else options[rng.integers(len(options))]
        run = run + 1 if new == heading else 0
        heading = new
        cur = (cur[0] + heading[0], cur[1] + heading[1])
        path.append(cur)
    return g * np.array(path, dtype=np.float64)


def smooth_trajectory(scene, frames: int, rng: np.random.Generator, step_m: float = 0.4,
                      wobble_deg: float = 3.0, height_var_m: float = 0.1) -> np.ndarray:
    """(frames, 4, 4) sensor-to-world poses ``step_m`` apart along a smoothed grid walk."""
    from scipy.ndimage import gaussian_filter1d

    s = 0.5 + step_m * np.arange(frames)
    for extra in range(1, 21):  # smoothing shortens walks that turn back: retry longer ones
        walk = _grid_walk(scene, s[-1] + extra, rng)
        dense = np.concatenate([a + np.linspace(0, 1, 6, endpoint=False)[:, None] * (b - a)
                                for a, b in zip(walk[:-1], walk[1:])] + [walk[-1:]])
        dense = gaussian_filter1d(dense, sigma=0.3 / (scene.grid_m / 6), axis=0, mode="nearest")
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
        if arc[-1] >= s[-1] + 0.5:
            break
    else:
        raise ValueError(f"no {frames}-frame LiDAR trajectory found in this scene")
    x, z = np.interp(s, arc, dense[:, 0]), np.interp(s, arc, dense[:, 1])
    tangent = np.gradient(dense, axis=0)
    heading = np.unwrap(np.arctan2(tangent[:, 0], tangent[:, 1]))  # yaw 0 faces world +z
    step = arc[-1] / max(len(arc) - 1, 1)
    yaw = np.interp(s, arc, gaussian_filter1d(heading, sigma=0.5 / step, mode="nearest"))
    def wav(amp: float) -> np.ndarray:  # a sinusoid of the distance travelled, period 2-5 m
        return amp * np.sin(2 * np.pi * s / rng.uniform(2.0, 5.0) + rng.uniform(0, 2 * np.pi))

    w = np.radians(wobble_deg)
    return lidar_pose(x, z, yaw, dh=wav(height_var_m), roll=wav(w), pitch=wav(w))


def scan(scene, pose: np.ndarray, config: LidarConfig | None = None,
         rng: np.random.Generator | None = None) -> np.ndarray:
    """One sweep from sensor-to-world ``pose``: (N, 3) float32 sensor-frame points (no-returns dropped)."""
    cfg = config or LidarConfig()
    dirs = cfg.directions()
    rays = np.concatenate([np.broadcast_to(pose[:3, 3], dirs.shape), dirs @ pose[:3, :3].T], axis=1)
    r = caster_for(scene).cast(rays)
    if cfg.noise_std_m > 0:
        r = r + (rng or np.random.default_rng()).normal(0.0, cfg.noise_std_m, r.shape)
    ok = np.isfinite(r) & (r >= cfg.min_range_m) & (r <= cfg.max_range_m)
    return (dirs[ok] * r[ok, None]).astype(np.float32)


def simulate_lidar_trajectory(scene, frames: int, rng: np.random.Generator, config: LidarConfig | None = None,
                              step_m: float = 0.4):
    """(list of K sensor-frame clouds (N_k, 3) float32, sensor-to-world poses (K, 4, 4))."""
    poses = smooth_trajectory(scene, frames, rng, step_m)
    return [scan(scene, T, config, rng) for T in poses], poses


def write_lidar_dataset(out_dir: str | os.PathLike, num_trajectories: int = 10, frames: int = 16, seed: int = 0,
                        beams: int = 16, azimuth_res_deg: float = 1.0, max_range_m: float = 20.0,
                        noise_std_m: float = 0.0, step_m: float = 0.4, trajectories_per_scene: int = 2) -> list[Path]:
    """Write ``traj_000/ ...`` folders (scans/NNNNNN.ply, gt_poses.txt, meta.json); scene seeds as in sim.rgbd."""
    cfg = LidarConfig(beams, None, azimuth_res_deg, max_range_m, 0.1, noise_std_m)
    scenes: dict = {}
    folders = []
    for t in range(num_trajectories):
        scene_seed = 1000 * seed + t // trajectories_per_scene
        if scene_seed not in scenes:
            scenes[scene_seed] = make_scene(scene_seed)
        clouds, poses = simulate_lidar_trajectory(scenes[scene_seed], frames, np.random.default_rng([seed, t, 2]),
                                                  cfg, step_m)
        folder = Path(out_dir) / f"traj_{t:03d}"
        (folder / "scans").mkdir(parents=True, exist_ok=True)
        for k, cloud in enumerate(clouds):
            write_ply(folder / "scans" / f"{k:06d}.ply", cloud)
        write_kitti_poses(folder / "gt_poses.txt", poses)
        write_json(folder / "meta.json", {
            "kind": "lidar", "pose_dof": 6, "seed": seed, "trajectory": t, "scene": scene_seed, "frames": frames,
            "beams": beams, "vfov_deg": list(_VFOV.get(beams, (-15.0, 15.0))), "azimuth_res_deg": azimuth_res_deg,
            "max_range_m": max_range_m, "noise_std_m": noise_std_m, "step_m": step_m,
            "frame": "sensor x forward, y left, z up; world y down; poses sensor-to-world, metres"})
        folders.append(folder)
    return folders
