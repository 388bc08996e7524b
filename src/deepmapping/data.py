"""The scan set every method works on: K organized 2D scans in their sensor frames."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from deepmapping.errors import InputError


@dataclass
class ScanSet:
    """K scans of N points each, in sensor frames.

    points: (K, N, D) float32, D = 2 for 2D scans. Organized: point j of every scan is beam j.
    valid:  (K, N) bool; False for a beam without return (stored as the all-zero point).
    gt_poses / init_poses: (K, 3) [x, y, theta] in the units of ``points``, or None.
    unit_scale: multiply a length in ``points`` units by this to report it in ``unit``
        (the authors' layout stores px/512, so unit_scale = 512 and unit = "px").
    ordered: True when scans are a temporal sequence (enables the Chamfer term).
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

    @property
    def num_scans(self) -> int:
        return int(self.points.shape[0])

    @property
    def dim(self) -> int:
        return int(self.points.shape[2])

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
        for label, poses in (("ground truth", self.gt_poses), ("initial poses", self.init_poses)):
            if poses is None:
                continue
            if poses.ndim != 2 or poses.shape[1] != 3:
                raise InputError(f"{self.source}: {label} must be K x 3 [x y theta], got {poses.shape}")
            if poses.shape[0] != pts.shape[0]:
                raise InputError(
                    f"{self.source}: {poses.shape[0]} {label} for {pts.shape[0]} scans (counts differ)"
                )
            if not np.isfinite(poses).all():
                raise InputError(f"{self.source}: {label} contain NaN or inf")
        return self
