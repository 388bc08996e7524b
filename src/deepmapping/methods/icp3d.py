"""Incremental (frame-to-frame) 3D ICP with Open3D: the classic baseline of §4.2 / supp. C.

Scales (``voxel_size=None`` / ``max_correspondence_distance=None``), shared with
:mod:`deepmapping.methods.multiway`:

- ``d`` = median over scans of the scan's bounding-box diagonal (so metres in, metres out);
- ``g`` = median distance from a point to its nearest neighbour in the same scan (the sampling);
- voxel size = ``max(d / 100, g)`` (``0`` = no downsampling, and ``max(d / 100, g)`` still sets
  the scale ``s`` below; otherwise ``s`` = voxel size). The floor ``g`` matters for sparse scans
  only (a room seen at 40x30 pixels: points 6 cm apart, d / 100 = 3.5 cm): below it, the normals'
  radius holds almost no neighbour and ICP got worse than no registration on 7-Scenes;
- fine correspondence distance = ``1.5 s``; the coarse pass uses 10 x the fine distance;
- normals (point-to-plane) from neighbours within ``2 s``.

Every pairwise registration runs a coarse then a fine ICP pass (Choi et al. [12] as in Open3D).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from deepmapping.errors import ConfigError, InputError
from deepmapping.geometry import se3
from deepmapping.methods.open3d_utils import quiet_open3d, to_pcd

__all__ = ["incremental_icp_3d", "odometry_agreement", "check_clouds", "check_init", "Scales", "default_scales", "point_spacing",
           "prepare_clouds", "register_pair", "plausible"]

MIN_POINTS = 10
COARSE_FACTOR = 10.0


@dataclass(frozen=True)
class Scales:
    """Lengths used by the baselines, in the units of the scans."""

    voxel: float  # 0 = no downsampling
    fine: float  # max correspondence distance of the fine ICP pass (and of the pose graph)
    normals_radius: float

    @property
    def coarse(self) -> float:
        return COARSE_FACTOR * self.fine


def check_clouds(clouds) -> list[np.ndarray]:
    """Scans as (N_i, 3) float64 arrays of finite points; InputError naming the first bad scan."""
    if len(clouds) == 0:
        raise InputError("no scans given")
    out = []
    for i, c in enumerate(clouds):
        pts = np.asarray(c, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise InputError(f"scan {i}: points must be (N, 3), got {pts.shape}")
        pts = pts[np.isfinite(pts).all(axis=1)]
        if pts.shape[0] < MIN_POINTS:
            raise InputError(f"scan {i}: only {pts.shape[0]} finite points (at least {MIN_POINTS} needed)")
        out.append(pts)
    return out


def check_init(init, k: int) -> np.ndarray | None:
    """Initial sensor-to-world poses (K, 4, 4) float64, or None."""
    if init is None:
        return None
    init = np.asarray(init, dtype=np.float64)
    if init.shape != (k, 4, 4) or not np.isfinite(init).all():
        raise InputError(f"init poses must be finite and (K, 4, 4) = ({k}, 4, 4), got {init.shape}")
    return init


def point_spacing(clouds: list[np.ndarray], max_scans: int = 8, max_points: int = 2000) -> float:
    """Median nearest-neighbour distance within a scan, over a few evenly spread scans (and at most
    ``max_points`` query points of each, fixed choice): the sampling of the data, cheaply."""
    from scipy.spatial import cKDTree

    picks = np.unique(np.linspace(0, len(clouds) - 1, min(max_scans, len(clouds))).round().astype(int))
    gaps = []
    for i in picks:
        c = clouds[i]
        query = c[np.linspace(0, len(c) - 1, min(max_points, len(c))).round().astype(int)]
        d = cKDTree(c).query(query, k=2)[0][:, 1]
        gaps.append(np.median(d[np.isfinite(d)]) if np.isfinite(d).any() else 0.0)
    return float(np.median(gaps))


def default_scales(clouds: list[np.ndarray], voxel_size=None, max_correspondence_distance=None) -> Scales:
    """The rule of the module docstring; explicit values win."""
    diag = float(np.median([np.linalg.norm(c.max(0) - c.min(0)) for c in clouds]))
    if voxel_size is not None and not voxel_size >= 0:
        raise ConfigError(f"voxel_size must be >= 0, got {voxel_size}")
    if max_correspondence_distance is not None and not max_correspondence_distance > 0:
        raise ConfigError(f"max_correspondence_distance must be > 0, got {max_correspondence_distance}")
    auto = max(diag / 100.0, point_spacing(clouds)) if voxel_size is None or voxel_size == 0 else 0.0
    voxel = auto if voxel_size is None else float(voxel_size)
    s = voxel if voxel > 0 else auto
    if not s > 0:
        raise InputError("every scan collapses to a single point (zero extent)")
    fine = 1.5 * s if max_correspondence_distance is None else float(max_correspondence_distance)
    return Scales(voxel=voxel, fine=fine, normals_radius=2.0 * s)


def prepare_clouds(clouds: list[np.ndarray], scales: Scales, normals: bool = True) -> list:
    """Downsampled Open3D clouds (with normals facing each scan's sensor when ``normals``)."""
    out = []
    for i, c in enumerate(clouds):
        pcd = to_pcd(c, scales.voxel, scales.normals_radius if normals else None)
        if len(pcd.points) < 3:
            raise InputError(f"scan {i}: only {len(pcd.points)} points left after voxel downsampling "
                             f"at {scales.voxel:g}; use a smaller voxel_size")
        out.append(pcd)
    return out


def register_pair(source, target, guess: np.ndarray, scales: Scales, method: str = "plane",
                  max_iterations: int = 50):
    """Coarse-then-fine ICP; returns Open3D's RegistrationResult of the fine pass.

    Its ``transformation`` T maps ``source`` points into ``target``'s frame (target ≈ T source),
    i.e. T is the pose of the source sensor in the target sensor's frame.
    """
    with quiet_open3d() as o3d:
        reg = o3d.pipelines.registration
        if method == "plane":
            estimation = reg.TransformationEstimationPointToPlane()
        elif method == "point":
            estimation = reg.TransformationEstimationPointToPoint(False)
        else:
            raise ConfigError(f"ICP method must be 'plane' or 'point', got {method!r}")
        criteria = reg.ICPConvergenceCriteria(1e-7, 1e-7, int(max_iterations))
        guess = np.asarray(guess, dtype=np.float64)
        coarse = reg.registration_icp(source, target, scales.coarse, guess, estimation, criteria)
        return reg.registration_icp(source, target, scales.fine, coarse.transformation, estimation, criteria)


MIN_FITNESS = 0.05  # share of source points with a fine-distance correspondence


def plausible(res, guess: np.ndarray, scales, center) -> bool:
    """A pairwise ICP result is kept when it overlaps at all and did not move the source scan's
    centre further than the coarse correspondence distance from where the guess put it
    (point-to-plane ICP on one dominant plane, e.g. the floor, can slide without bound). A
    failed odometry pair keeps its guess as an uncertain edge; a failed loop-closure pair gets
    no edge."""
    c = np.append(np.asarray(center, dtype=np.float64), 1.0)
    moved = np.linalg.norm((np.asarray(res.transformation) @ c - guess @ c)[:3])
    return res.fitness >= MIN_FITNESS and float(moved) <= scales.coarse


def incremental_icp_3d(
    clouds,
    method: str = "plane",
    init: np.ndarray | None = None,
    voxel_size: float | None = None,
    max_correspondence_distance: float | None = None,
    max_iterations: int = 50,
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """Incremental ICP over an ordered sequence of K scans (each (N_i, 3) in its sensor frame).

    Scan i+1 is registered to scan i ("plane": point-to-plane, "point": point-to-point), from
    the relative motion of ``init`` (K, 4, 4) when given, else the identity; the relative
    motions are chained; an implausible pair (see ``plausible``: no overlap, or slid
    off) keeps its guess. Pose 0 = ``init[0]`` or the identity. ``progress(i, K-1)`` after each
    registered pair. Returns sensor-to-world poses (K, 4, 4).
    """
    if method not in ("plane", "point"):
        raise ConfigError(f"ICP method must be 'plane' or 'point', got {method!r}")
    clouds = check_clouds(clouds)
    k = len(clouds)
    init = check_init(init, k)
    scales = default_scales(clouds, voxel_size, max_correspondence_distance)
    pcds = prepare_clouds(clouds, scales, normals=method == "plane")
    poses = se3.identity((k,)) if init is None else init.copy()
    poses[1:] = np.eye(4)
    for i in range(k - 1):
        guess = np.eye(4) if init is None else se3.relative(init[i], init[i + 1])
        res = register_pair(pcds[i + 1], pcds[i], guess, scales, method, max_iterations)
        rel = np.asarray(res.transformation) if plausible(res, guess, scales, pcds[i + 1].get_center()) else guess
        poses[i + 1] = poses[i] @ rel
        if progress is not None:
            progress(i + 1, k - 1)
    return poses


def odometry_agreement(clouds, poses: np.ndarray, voxel_size: float | None = None,
                       max_correspondence_distance: float | None = None,
                       max_iterations: int = 50) -> tuple[float, float]:
    """How far point-to-plane ICP, started from the relative motions of ``poses`` (a recorded
    odometry), moves each of them: (median translation change (scan units), median rotation change
    (deg)). Large when the recorded poses disagree with the scans."""
    icp = incremental_icp_3d(clouds, "plane", poses, voxel_size, max_correspondence_distance, max_iterations)
    poses = np.asarray(poses, dtype=np.float64)  # checked by incremental_icp_3d
    change = [se3.relative(se3.relative(poses[i], poses[i + 1]), se3.relative(icp[i], icp[i + 1]))
              for i in range(len(clouds) - 1)]
    trans = float(np.median([np.linalg.norm(c[:3, 3]) for c in change]))
    rot = float(np.median([se3.rotation_angle_deg(c[:3, :3]) for c in change]))
    return trans, rot
