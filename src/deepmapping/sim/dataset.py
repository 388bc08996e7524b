"""Simulated 2D lidar data sets: ScanSets in memory and folders in the authors' layout.

Units: the authors' layout stores points and (after loading) positions in px/512;
``gt_pose.mat`` keeps positions in px. ``ScanSet.unit_scale = 512``, ``unit = "px"``.
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

import numpy as np

from deepmapping.data import ScanSet
from deepmapping.io.atomic import atomic_write
from deepmapping.io.pcd import write_pcd
from deepmapping.sim.maps import procedural_indoor_map, save_map_png
from deepmapping.sim.scanner import simulate_scans
from deepmapping.sim.trajectory import sample_trajectory

__all__ = ["PX_SCALE", "simulate", "write_authors_layout", "paper_dataset", "paper_map", "paper_trajectory",
           "PAPER_LENGTHS"]

PX_SCALE = 512.0


def simulate(
    occ: np.ndarray,
    num_poses: int,
    seed: int,
    num_beams: int = 256,
    max_range: float | None = None,
    max_rotation_deg: float = 10.0,
    mean_step_px: float = 8.16,
    clearance_px: float = 8.0,
    range_noise_px: float = 0.0,
) -> ScanSet:
    """Sample a trajectory on ``occ`` and scan from every pose.

    ``range_noise_px``: standard deviation of Gaussian range noise added along each beam
    (0 = the paper's ideal scanner), drawn from the same seed.

    Returns a ScanSet with ``points`` (K, num_beams, 2) float32 in px/512 (sensor frames,
    invalid beams = (0, 0)), ``gt_poses`` (K, 3) [x_px/512, y_px/512, theta],
    ``unit_scale=512``, ``unit="px"``, ``ordered=True``, names "000", "001", ...
    """
    poses = sample_trajectory(
        occ,
        num_poses=num_poses,
        seed=seed,
        max_rotation_deg=max_rotation_deg,
        mean_step_px=mean_step_px,
        clearance_px=clearance_px,
    )
    points, valid = simulate_scans(occ, poses, num_beams=num_beams, max_range=max_range)
    if range_noise_px > 0:
        rng = np.random.default_rng([seed, 7919])
        ranges = np.linalg.norm(points, axis=2, keepdims=True)
        noisy = np.maximum(ranges + rng.normal(0.0, range_noise_px, ranges.shape), 1e-3)
        points = np.where(valid[..., None], points * noisy / np.maximum(ranges, 1e-9), 0.0)
    gt = poses.copy()
    gt[:, :2] /= PX_SCALE
    return ScanSet(
        points=(points / PX_SCALE).astype(np.float32),
        valid=valid,
        gt_poses=gt,
        unit_scale=PX_SCALE,
        unit="px",
        ordered=True,
        names=[f"{k:03d}" for k in range(num_poses)],
        source=f"<simulated seed={seed}>",
    )


def _trajectory_picture(occ: np.ndarray, poses_px: np.ndarray):  # type: ignore[no-untyped-def]
    """RGB picture of the map with the trajectory (green), poses (red) and headings (blue)."""
    from PIL import Image, ImageDraw

    gray = np.where(np.asarray(occ) >= 128, 255, 0).astype(np.uint8)
    img = Image.fromarray(np.stack([gray] * 3, axis=-1))
    draw = ImageDraw.Draw(img)
    xy = [(float(x), float(y)) for x, y in poses_px[:, :2]]
    if len(xy) > 1:
        draw.line(xy, fill=(0, 170, 0), width=2)
    every = max(1, len(xy) // 16)
    for k, (x, y, th) in enumerate(poses_px):
        if k % every == 0 or k == len(xy) - 1:
            draw.line([(x, y), (x + 12 * np.cos(th), y + 12 * np.sin(th))], fill=(0, 0, 255), width=2)
            draw.ellipse([x - 3, y - 3, x + 3, y + 3], outline=(255, 0, 0), width=2)
    return img


def _save_png(path: Path, image) -> None:  # type: ignore[no-untyped-def]
    atomic_write(path, lambda f: image.save(f, format="PNG"))


def write_authors_layout(
    out_dir: str | os.PathLike,
    scans: ScanSet | np.ndarray,
    gt_poses_px: np.ndarray | None = None,
    occ: np.ndarray | None = None,
    valid: np.ndarray | None = None,
) -> Path:
    """Write a folder in the authors' layout; return its path.

    ``scans`` is a ScanSet in px/512 units (its gt_poses are scaled back to px with
    ``unit_scale``) or a (K, N, 2) array of sensor-frame points in px/512 (then
    ``gt_poses_px`` (K, 3) [x_px, y_px, theta] is required, ``valid`` (K, N) optional).
    Writes ``000.pcd``, ``001.pcd``, ... (binary float32 x y z, z = 0, one point per beam
    in beam order, invalid beams = (0, 0, 0)), ``gt_pose.mat`` (key ``pose``, K x 3
    [x_px, y_px, theta_rad]) and, when ``occ`` is given, ``env.png`` (the binary map) and
    ``map.png`` (the map with the trajectory drawn). Every file is written atomically.
    """
    import scipy.io

    out = Path(out_dir)
    if isinstance(scans, ScanSet):
        points = np.asarray(scans.points, dtype=np.float32)
        mask = np.asarray(scans.valid, dtype=bool)
        if gt_poses_px is None:
            if scans.gt_poses is None:
                raise ValueError("the ScanSet has no gt_poses; pass gt_poses_px")
            gt_poses_px = np.asarray(scans.gt_poses, dtype=np.float64).copy()
            gt_poses_px[:, :2] *= scans.unit_scale
    else:
        points = np.asarray(scans, dtype=np.float32)
        mask = np.ones(points.shape[:2], bool) if valid is None else np.asarray(valid, dtype=bool)
        if gt_poses_px is None:
            raise ValueError("gt_poses_px is required when scans is an array")
    if points.ndim != 3 or points.shape[2] != 2:
        raise ValueError(f"scans must be (K, N, 2), got shape {points.shape}")
    gt = np.asarray(gt_poses_px, dtype=np.float64)
    if gt.shape != (points.shape[0], 3):
        raise ValueError(f"gt_poses_px must be ({points.shape[0]}, 3), got shape {gt.shape}")
    if mask.shape != points.shape[:2]:
        raise ValueError(f"valid must be {points.shape[:2]}, got shape {mask.shape}")

    out.mkdir(parents=True, exist_ok=True)
    k, n = points.shape[:2]
    for i in range(k):
        xyz = np.zeros((n, 3), dtype=np.float32)
        xyz[:, :2] = np.where(mask[i][:, None], points[i], 0.0)
        write_pcd(out / f"{i:03d}.pcd", xyz)  # write_pcd writes atomically itself
    atomic_write(out / "gt_pose.mat", lambda f: scipy.io.savemat(f, {"pose": gt}))
    if occ is not None:
        from PIL import Image

        env = np.where(np.asarray(occ) >= 128, 255, 0).astype(np.uint8)
        _save_png(out / "env.png", Image.fromarray(env))
        _save_png(out / "map.png", _trajectory_picture(occ, gt))
    return out


def paper_dataset(out_dir: str | os.PathLike, seed: int = 0, size: int = 1024) -> list[Path]:
    """The paper's 2D data set (section 4.1): 3 maps, 75 trajectories, 256 beams, unlimited range.

    50 trajectories of 128 poses and 25 of 256 poses, assigned to the maps in turn
    (trajectory i on map i % 3). Writes ``map0.png`` .. ``map2.png`` and one folder per
    trajectory, ``map{m}_traj{i:03d}_K{K}/``, in the authors' layout. Deterministic from
    ``seed``; returns the trajectory folders.
    """
    from rich.progress import track

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    maps = [paper_map(m, seed, size) for m in range(3)]
    for m, occ in enumerate(maps):
        save_map_png(out / f"map{m}.png", occ)

    folders: list[Path] = []
    for i in track(range(len(PAPER_LENGTHS)), description="Simulating trajectories"):
        m, k = i % 3, PAPER_LENGTHS[i]
        scans = paper_trajectory(i, seed, size)
        folders.append(write_authors_layout(out / f"map{m}_traj{i:03d}_K{k}", scans, occ=maps[m]))
    return folders


PAPER_LENGTHS = (128,) * 50 + (256,) * 25  # poses of the paper's 75 trajectories (trajectory i on map i % 3)


def _paper_seeds(seed: int) -> tuple[list[int], list[int]]:
    """(3 map seeds, 75 trajectory seeds) of the paper data set drawn from ``seed``."""
    map_ss, traj_ss = np.random.SeedSequence(seed).spawn(2)
    map_seeds = [int(s.generate_state(1)[0]) for s in map_ss.spawn(3)]
    traj_seeds = [int(s.generate_state(1)[0]) for s in traj_ss.spawn(len(PAPER_LENGTHS))]
    return map_seeds, traj_seeds


@lru_cache(maxsize=6)
def paper_map(m: int, seed: int = 0, size: int = 1024) -> np.ndarray:
    """Map ``m`` (0..2) of :func:`paper_dataset` (cached per process; do not modify it)."""
    return procedural_indoor_map(_paper_seeds(seed)[0][m], size)


def paper_trajectory(i: int, seed: int = 0, size: int = 1024, num_poses: int | None = None,
                     num_beams: int = 256) -> ScanSet:
    """Trajectory ``i`` (0..74) of :func:`paper_dataset` in memory, on map ``i % 3``.

    With the defaults it is exactly the scans that paper_dataset writes; ``num_poses`` /
    ``num_beams`` give a smaller variant (same map and trajectory seed) for quick runs.
    """
    if not 0 <= i < len(PAPER_LENGTHS):
        raise ValueError(f"trajectory index must be in 0..{len(PAPER_LENGTHS) - 1}, got {i}")
    k = PAPER_LENGTHS[i] if num_poses is None else num_poses
    scans = simulate(paper_map(i % 3, seed, size), num_poses=k, seed=_paper_seeds(seed)[1][i], num_beams=num_beams)
    scans.source = f"<paper trajectory {i} (map {i % 3}, seed={seed}, K={k}, beams={num_beams})>"
    return scans
