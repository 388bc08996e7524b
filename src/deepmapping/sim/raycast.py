"""Ray casting against a triangle mesh with Open3D's ``RaycastingScene`` (Embree BVH).

Building the BVH is the expensive part, so ``caster_for(scene)`` builds it once per
``Scene3D`` and keeps it in ``scene.cache``; every frame of every trajectory in that scene
then only pays for ``cast``. Triangles are hit from both sides.
"""

from __future__ import annotations

import numpy as np

__all__ = ["RayCaster", "caster_for"]


class RayCaster:
    """Cast rays against a fixed mesh: vertices (V, 3), triangles (T, 3)."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        import open3d as o3d

        self._o3d = o3d
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)),
        )

    def cast(self, rays: np.ndarray) -> np.ndarray:
        """(M, 6) rays [origin xyz, direction xyz] -> (M,) float64 hit parameter t, inf for no hit.

        The hit point is ``origin + t * direction``: t is a distance for unit directions, and
        the camera depth z for camera rays whose direction has z component 1.
        """
        rays = np.ascontiguousarray(np.reshape(rays, (-1, 6)), dtype=np.float32)
        out = self._scene.cast_rays(self._o3d.core.Tensor(rays))
        return out["t_hit"].numpy().astype(np.float64)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(M, 3) points -> (M,) unsigned distance to the nearest triangle (for checks)."""
        pts = np.ascontiguousarray(np.reshape(points, (-1, 3)), dtype=np.float32)
        return self._scene.compute_distance(self._o3d.core.Tensor(pts)).numpy().astype(np.float64)


def caster_for(scene) -> RayCaster:
    """The (cached) RayCaster of a ``Scene3D``."""
    caster = scene.cache.get("caster")
    if caster is None:
        caster = scene.cache["caster"] = RayCaster(scene.vertices, scene.triangles)
    return caster
