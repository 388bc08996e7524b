"""A 2D distance transform of a point set: fast approximate nearest-point distances.

Go-ICP (Yang et al., 2016) evaluates its bounds with a distance transform of the target
instead of nearest-neighbour searches; :mod:`deepmapping.methods.goicp` and
:mod:`deepmapping.methods.pso` use this one for every evaluation of a candidate pose.
"""

from __future__ import annotations

import numpy as np

__all__ = ["DistanceField2D", "clean_points_2d"]


class DistanceField2D:
    """Distances to the nearest of ``points`` (M, 2) on a ``size`` x ``size`` grid over
    ``[-half_extent, half_extent]^2`` (centred at ``center``).

    ``lookup`` returns the distance stored for the cell that holds each query; it is within
    ``slack`` (= cell size x sqrt 2) of the exact nearest-point distance for queries inside
    the grid. Queries outside it are clamped to the border and get the distance to the
    border added (an over-estimate there).
    """

    def __init__(self, points, half_extent: float, size: int = 1024, center=(0.0, 0.0)):
        from scipy import ndimage

        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        pts = pts[np.isfinite(pts).all(axis=1)]
        if pts.shape[0] == 0:
            raise ValueError("a distance field needs at least one point")
        if not half_extent > 0 or size < 2:
            raise ValueError("half_extent must be > 0 and size >= 2")
        self.size = int(size)
        self.center = np.asarray(center, dtype=np.float64).reshape(2)
        self.lo = self.center - half_extent
        self.cell = 2.0 * half_extent / self.size
        self.slack = self.cell * np.sqrt(2.0)
        idx = self._index(pts)
        empty = np.ones((self.size, self.size), dtype=bool)
        empty[idx[:, 1], idx[:, 0]] = False
        self.grid = (ndimage.distance_transform_edt(empty) * self.cell).astype(np.float32)

    def _index(self, q: np.ndarray) -> np.ndarray:
        return np.clip(np.floor((q - self.lo) / self.cell).astype(np.int64), 0, self.size - 1)

    def lookup(self, queries) -> np.ndarray:
        """Approximate nearest-point distance of each query (..., 2) -> (...)."""
        q = np.asarray(queries, dtype=np.float64)
        idx = self._index(q)
        d = self.grid[idx[..., 1], idx[..., 0]].astype(np.float64)
        hi = self.lo + self.cell * self.size
        outside = np.linalg.norm(q - np.clip(q, self.lo, hi), axis=-1)
        return d + outside

    def within(self, queries, distance: float) -> np.ndarray:
        """``lookup(queries) <= distance``, faster: the distance to the border is computed only for
        the queries outside the grid (a correlative search scores millions of poses)."""
        q = np.asarray(queries, dtype=np.float64)
        raw = np.floor((q - self.lo) / self.cell).astype(np.int64)
        far = (raw.view(np.uint64) >= self.size).any(axis=-1)  # a negative index wraps to a huge one
        idx = np.minimum(raw.view(np.uint64), self.size - 1).view(np.int64)
        out = self.grid[idx[..., 1], idx[..., 0]].astype(np.float64) <= np.float64(distance)
        if far.any():
            out[far] = self.lookup(q[far]) <= np.float64(distance)
        return out


def clean_points_2d(points, name: str) -> np.ndarray:
    """(N, 2) float64 without non-finite rows; ValueError naming ``name`` if fewer than 3 remain."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if pts.shape[0] < 3:
        raise ValueError(f"{name} needs at least 3 finite points, got {pts.shape[0]}")
    return pts
