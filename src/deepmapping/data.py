"""The scan set every method works on: K scans (2D or 3D) in their sensor frames."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from deepmapping.errors import InputError


def identity_poses(num: int, is_3d: bool) -> np.ndarray:
    """``num`` poses at the origin: (num, 4, 4) identity matrices (3D) or (num, 3) zeros (2D, [x, y, theta])."""
    return np.tile(np.eye(4), (num, 1, 1)) if is_3d else np.zeros((num, 3))


@dataclass
class FullSequence:
    """The whole input sequence when only keyframes are registered (e.g. a CARMEN log).

    stamps (S,): each scan's timestamp as written in the input (exact matching of relations);
    timestamps (S,) the same as numbers; odometry (S, 3) [x, y, theta]; keyframes (K,) the
    indices of the registered scans.
    """

    stamps: list[str]
    timestamps: np.ndarray
    odometry: np.ndarray
    keyframes: np.ndarray
    relations_path: str | None = None  # Kümmerle et al. relations to score against
    # every scan's points (S, N, 2) and mask, for placing non-keyframes by scan matching
    points: np.ndarray | None = None
    valid: np.ndarray | None = None
    placement: str = "icp"  # non-keyframes: "odometry" (from the nearest keyframe) or "icp" (then refined)
    # methods.keyframes.place_all_scans's last (keyframe poses as bytes, every scan's poses)
    placed_cache: tuple = field(default=(None, None), repr=False, compare=False)


@dataclass
class ScanSet:
    """K scans of N points each, in sensor frames.

    points: (K, N, D) float32, D = 2 for 2D scans, 3 for 3D. The sensor sits at the origin of
        its frame: free-space samples lie on the segment from the origin to each point.
        2D: organized, point j of every scan is beam j. 3D: organized depth images when
        ``grid_shape`` = (H, W) is set (point j = pixel (j // W, j % W)), else unorganized
        clouds padded to a common N (padding is invalid).
    valid:  (K, N) bool; False for a beam without return (stored as the all-zero point).
    gt_poses / init_poses: 2D (K, 3) [x, y, theta]; 3D (K, 4, 4) sensor-to-global matrices;
        in the units of ``points``, or None.
    grid_shape: (H, W) of organized 3D scans (depth images), None otherwise.
    sequence: the whole input when the scans are its keyframes (CARMEN logs): poses are then
        written for every input scan.
    pose_dof: 3D only: 3 = planar poses [x, z, theta about the vertical y axis] (AVD), 6 = full.
    unit_scale: multiply a length in ``points`` units by this to report it in ``unit``
        (the authors' layout stores px/512, so unit_scale = 512 and unit = "px").
    ordered: True when scans are a temporal sequence (enables the Chamfer term).
    recorded_poses: ``init_poses`` are the sensor's own recorded poses that came with the data
        (3DTK's .pose files), not a start someone computed or gave: 3D ``--warm-start auto`` then
        starts from them, held by the odometry factor (api.resolve_odometry_sigma).
    """

    points: np.ndarray
    valid: np.ndarray
    gt_poses: np.ndarray | None = None
    init_poses: np.ndarray | None = None
    unit_scale: float = 1.0
    unit: str = "m"
    ordered: bool = True
    names: list[str] = field(default_factory=list)
    source: str = "<memory>"
    grid_shape: tuple[int, int] | None = None
    pose_dof: int = 3
    sequence: FullSequence | None = None  # every scan of the input, when these are keyframes
    notes: list[str] = field(default_factory=list)  # what the loader left out or assumed (the CLI prints them)
    recorded_poses: bool = False

    @property
    def num_scans(self) -> int:
        return int(self.points.shape[0])

    @property
    def dim(self) -> int:
        return int(self.points.shape[2])

    @property
    def is_3d(self) -> bool:
        return self.dim == 3

    @property
    def handheld(self) -> bool:
        """Depth images with 6-DoF poses: a camera carried through a room (7-Scenes, TUM RGB-D); the
        default profile is then ``handheld``."""
        return self.is_3d and self.grid_shape is not None and self.pose_dof == 6

    def pose_shape(self) -> tuple[int, ...]:
        return (4, 4) if self.is_3d else (3,)

    def identity_poses(self) -> np.ndarray:
        """Every scan at the origin (no registration; the start of a cold start)."""
        return identity_poses(self.num_scans, self.is_3d)

    def validate(self) -> "ScanSet":
        """Check shapes and values; raise InputError naming the offending scan."""
        pts = self.points
        if pts.ndim != 3 or pts.shape[2] not in (2, 3):
            raise InputError(f"{self.source}: expected scans of shape (K, N, 2|3), got {pts.shape}")
        if pts.shape[0] < 2:
            raise InputError(f"{self.source}: need at least two scans, got {pts.shape[0]}")
        if self.valid.shape != pts.shape[:2]:
            raise InputError(f"{self.source}: valid mask shape {self.valid.shape} != {pts.shape[:2]}")
        for k in range(pts.shape[0]):
            name = self.names[k] if k < len(self.names) else f"scan {k}"
            if not np.isfinite(pts[k]).all():
                raise InputError(f"{self.source}/{name}: contains NaN or inf coordinates")
            if not self.valid[k].any():
                raise InputError(f"{self.source}/{name}: scan has no valid point")
        if self.grid_shape is not None and int(np.prod(self.grid_shape)) != pts.shape[1]:
            raise InputError(f"{self.source}: image size {self.grid_shape} does not match {pts.shape[1]} points per scan")
        if self.pose_dof not in (3, 6) or (self.pose_dof == 6 and pts.shape[2] != 3):
            raise InputError(f"{self.source}: pose_dof must be 3 or 6 (6 only for 3D scans), got {self.pose_dof}")
        want = self.pose_shape()
        for label, poses in (("ground truth", self.gt_poses), ("initial poses", self.init_poses)):
            if poses is None:
                continue
            if poses.ndim != 1 + len(want) or poses.shape[1:] != want:
                what = "K x 4 x 4 matrices" if self.is_3d else "K x 3 [x y theta]"
                raise InputError(f"{self.source}: {label} must be {what}, got {poses.shape}")
            if poses.shape[0] != pts.shape[0]:
                raise InputError(
                    f"{self.source}: {poses.shape[0]} {label} for {pts.shape[0]} scans (counts differ)"
                )
            if not np.isfinite(poses).all():
                raise InputError(f"{self.source}: {label} contain NaN or inf")
        return self
