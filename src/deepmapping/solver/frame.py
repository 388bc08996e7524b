"""Normalized working frame: the map's bounding box is mapped to about [-1, 1]^D.

The solver is then independent of the data's units (px/512, metres, ...): points are divided
by `scale`, global positions are shifted by `center` and divided by `scale`. Poses are 2D
(K, 3) [x, y, theta] or 3D (K, 4, 4) matrices (their translation column is normalized).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deepmapping.geometry import se2, se3


def _is_3d(poses: np.ndarray) -> bool:
    return np.ndim(poses) == 3


@dataclass
class Frame:
    center: np.ndarray  # (D,)
    scale: float

    @classmethod
    def from_scans(cls, points: np.ndarray, valid: np.ndarray, poses: np.ndarray) -> "Frame":
        move = se3.transform_points if _is_3d(poses) else se2.transform_points
        glob = move(poses, points)[valid]
        lo, hi = glob.min(0), glob.max(0)
        scale = float(max((hi - lo).max() / 2.0 * 1.1, 1e-9))
        return cls(center=(lo + hi) / 2.0, scale=scale)

    def to_norm(self, poses: np.ndarray) -> np.ndarray:
        out = np.array(poses, dtype=np.float64, copy=True)
        if _is_3d(out):
            out[:, :3, 3] = (out[:, :3, 3] - self.center) / self.scale
        else:
            out[..., :2] = (out[..., :2] - self.center) / self.scale
        return out

    def from_norm(self, poses: np.ndarray) -> np.ndarray:
        out = np.array(poses, dtype=np.float64, copy=True)
        if _is_3d(out):
            out[:, :3, 3] = out[:, :3, 3] * self.scale + self.center
            return out
        out[..., :2] = out[..., :2] * self.scale + self.center
        out[..., 2] = se2.wrap_angle(out[..., 2])
        return out

    def to_dict(self) -> dict:
        return {"center": self.center.tolist(), "scale": self.scale}
