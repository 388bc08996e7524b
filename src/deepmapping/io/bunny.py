"""Stanford Bunny range scans (``bun.conf`` + ``*.ply``) -> an unorganized 3D ScanSet.

``bun.conf``: a ``bmesh FILE tx ty tz qx qy qz qw`` line per scan maps a scan point p to
``R(q)^T p + t`` in the bun000 frame (shared/README.md, checked there numerically); the
``camera`` line is a viewer setting and is ignored. Points are metres; errors are reported
in mm (``unit_scale`` 1000). The scans are views of one object from all around, not a
trajectory: ``ordered`` is False and poses are scored against bun000 (``bunny_pose_errors``).

The sensor position (DeepMapping draws free-space samples on the segment sensor -> point,
Fig. 3) is not in the files; it was measured on the scans themselves:

- Viewed from +z. From each point, a ray along +z of its scan frame passes within 0.8 mm of
  another (gt-registered) scan for only 1-8 % of the points; along -z for 96-100 % (it
  enters the bunny and meets the far side). Every scan is a height field z(x, y) seen from +z.
- A line sensor sweeping along x (Cyberware 3030MS: x is quantised in 0.25-0.5 mm steps, one
  step per frame). In the ``range_grid`` of each file, the points of one image row lie on a
  line of the y-z plane (median rms 5-45 um) and these lines meet near y = 0.165-0.184 m,
  z = 1.20-1.55 m (least-squares apex of each scan; the rows fan out over 0-6.5 degrees).
- Assumed sensor of scan k, in its own frame: ``o_k = (x_mid_k, SENSOR_Y, SENSOR_Z)`` with
  x_mid_k the middle of the scan's x extent (the true viewpoints lie on the line
  {(x, SENSOR_Y, SENSOR_Z)}, so the assumed rays deviate by at most ~3.5 degrees in x).
  Rays from 300 points of each scan towards o_k meet another scan for 3-9 % of them, towards
  the mirror point (z -> -z) for 97-100 %.

Each scan is then shifted so that o_k is the origin of its frame (points p - o_k) and its
pose becomes ``T @ translate(o_k)``: world points are unchanged. The sensor is ~1.3 m from
the 0.15 m object, so uniform free-space samples mostly fall far from it (near-hit samples
help).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from deepmapping.data import ScanSet
from deepmapping.errors import InputError
from deepmapping.geometry import se3
from deepmapping.io.atomic import read_user_text
from deepmapping.io.clouds import check_max_points, pad_clouds, subsample
from deepmapping.io.ply import read_ply
from deepmapping.io.poses3d import read_poses_3d

__all__ = ["SENSOR_Y", "SENSOR_Z", "is_bunny_folder", "read_bun_conf", "load_bunny",
           "scan_centroids", "bunny_pose_errors"]

SENSOR_Y = 0.175  # metres, scan frame: measured apex of the scanner's rays (see above)
SENSOR_Z = 1.35


def is_bunny_folder(path: str | os.PathLike) -> bool:
    """True for a folder holding a ``bun.conf``."""
    return (Path(path) / "bun.conf").is_file()


def read_bun_conf(path: str | os.PathLike) -> list[tuple[str, np.ndarray]]:
    """[(file name, (4, 4) pose R(q)^T p + t)] of the ``bmesh`` lines, in file order."""
    path = Path(path)
    text = read_user_text(path)
    out = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        tok = line.split()
        if not tok or tok[0] != "bmesh":
            continue
        try:
            if len(tok) != 9:
                raise ValueError
            v = np.array([float(t) for t in tok[2:]])
        except ValueError:
            raise InputError(f"{path}: line {lineno}: expected 'bmesh FILE tx ty tz qx qy qz qw'") from None
        if not np.isfinite(v).all() or np.linalg.norm(v[3:]) < 1e-9:
            raise InputError(f"{path}: line {lineno}: NaN, inf or zero quaternion")
        pose = se3.from_xyz_quat(v)
        pose[:3, :3] = pose[:3, :3].T  # the conf's rotation is R(q)^T
        out.append((tok[1], pose))
    if len(out) < 2:
        raise InputError(f"{path}: need at least two 'bmesh' lines, found {len(out)}")
    return out


def _override(path, k: int, names: list[str], origins: np.ndarray) -> np.ndarray:
    """Poses from a .conf (bmesh lines matched by file name, shifted) or read_poses_3d (as is)."""
    path = Path(path)
    if path.suffix.lower() == ".conf":
        table = dict(read_bun_conf(path))
        missing = [n for n in names if n not in table]
        if missing:
            raise InputError(f"{path}: no bmesh line for {', '.join(missing)}")
        return np.stack([table[n] for n in names]) @ _translations(origins)

    poses = read_poses_3d(path)
    if len(poses) != k:
        raise InputError(f"{path}: {len(poses)} poses for {k} scans (counts differ)")
    return poses


def _translations(origins: np.ndarray) -> np.ndarray:
    return se3.from_rt(np.broadcast_to(np.eye(3), origins.shape[:1] + (3, 3)), origins)


def load_bunny(folder: str | os.PathLike, gt_path=None, init_path=None, max_points: int | None = 4000,
               seed: int = 0) -> ScanSet:
    """Read the scans listed in ``folder/bun.conf``, sensor at each frame's origin (see above).

    At most ``max_points`` random points per scan (seeded; None keeps all, padding with
    invalid points). gt = bun.conf's poses, shifted; ``gt_path``/``init_path``: a .conf
    (shifted likewise) or a pose file read by ``read_poses_3d`` in the loaded (shifted) frames.
    """
    folder = Path(folder)
    entries = read_bun_conf(folder / "bun.conf")
    check_max_points(folder, max_points)
    rng = np.random.default_rng(seed)
    clouds, origins = [], []
    for name, _ in entries:
        xyz = read_ply(folder / name).astype(np.float64)
        if len(xyz) == 0 or not np.isfinite(xyz).all():
            raise InputError(f"{folder / name}: no point, or NaN/inf coordinates")
        o = np.array([(xyz[:, 0].min() + xyz[:, 0].max()) / 2, SENSOR_Y, SENSOR_Z])
        clouds.append(subsample(xyz, max_points, rng) - o)
        origins.append(o)
    origins = np.array(origins)
    k = len(clouds)
    points, valid = pad_clouds(clouds)
    names = [n for n, _ in entries]
    gt = np.stack([p for _, p in entries]) @ _translations(origins)
    if gt_path is not None:
        gt = _override(gt_path, k, names, origins)
    init = None if init_path is None else _override(init_path, k, names, origins)
    return ScanSet(points=points, valid=valid, gt_poses=gt, init_poses=init, unit_scale=1000.0, unit="mm",
                   ordered=False, names=[Path(n).stem for n in names], source=str(folder),
                   grid_shape=None, pose_dof=6).validate()


def scan_centroids(points, valid) -> np.ndarray:
    """(K, 3) mean of each scan's valid points, in its own frame."""
    pts, val = np.asarray(points, np.float64), np.asarray(valid, bool)
    return (pts * val[..., None]).sum(1) / np.maximum(val.sum(1), 1)[:, None]


def bunny_pose_errors(est, gt, names, centroids=None) -> list[dict]:
    """Per scan: rotation error ``rot_deg`` and translation error ``trans_mm`` (poses in metres)
    of inv(est_0) est_i against inv(gt_0) gt_i, the first scan fixed; ``at`` says where.

    Translation error at the scan's centroid c_i (``centroids`` (K, 3), in its frame:
    |est_rel(c_i) - gt_rel(c_i)|, independent of where the sensor is assumed) when given,
    else at the pose origin (the assumed sensor, ~1.3 m away, magnifies rotation errors).
    """
    est, gt = np.asarray(est, np.float64), np.asarray(gt, np.float64)
    if est.ndim != 3 or est.shape[1:] != (4, 4) or est.shape != gt.shape or len(names) != len(est):
        raise ValueError(f"est, gt must be (K, 4, 4) with K names, got {est.shape}, {gt.shape}, {len(names)}")
    rel_e, rel_g = se3.relative(est[:1], est), se3.relative(gt[:1], gt)
    rot = se3.rotation_angle_deg(np.swapaxes(rel_g[:, :3, :3], 1, 2) @ rel_e[:, :3, :3])
    c = np.zeros((len(est), 3)) if centroids is None else np.asarray(centroids, np.float64)
    diff = se3.transform_points(rel_e, c[:, None])[:, 0] - se3.transform_points(rel_g, c[:, None])[:, 0]
    trans = np.linalg.norm(diff, axis=1) * 1000.0
    where = "origin" if centroids is None else "centroid"
    return [{"name": str(nm), "rot_deg": float(r), "trans_mm": float(t), "at": where}
            for nm, r, t in zip(names, rot, trans)]
