"""Thin helpers around Open3D for the classic 3D baselines (incremental ICP, multiway [12]).

Open3D is imported lazily, inside functions, so ``import deepmapping`` stays light and works
without it; :func:`require_open3d` turns a missing or broken install into a one-line
:class:`~deepmapping.errors.ConfigError`.
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np

from deepmapping.errors import ConfigError

__all__ = ["require_open3d", "quiet_open3d", "to_pcd"]

_INSTALL_HINT = (
    "pip install open3d-cpu (its wheel needs the system library libusb-1.0-0: apt-get install libusb-1.0-0)"
)


def require_open3d(purpose: str = "the 3D ICP / multiway registration baselines"):
    """Import and return the ``open3d`` module, or raise a one-line ConfigError saying how to get it.

    OSError covers a wheel that is installed but cannot load a shared library (e.g. libusb).
    """
    try:
        import open3d as o3d
    except (ImportError, OSError) as exc:
        reason = " ".join(str(exc).split())
        raise ConfigError(f"Open3D is needed for {purpose}: {_INSTALL_HINT} [{reason}]") from exc
    return o3d


@contextmanager
def quiet_open3d():
    """Within the block, Open3D prints errors only (no ICP / pose-graph chatter); restored afterwards."""
    o3d = require_open3d()
    previous = o3d.utility.get_verbosity_level()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    try:
        yield o3d
    finally:
        o3d.utility.set_verbosity_level(previous)


def to_pcd(points, voxel_size: float | None = None, normals_radius: float | None = None):
    """One scan (N, 3), in its sensor frame -> legacy ``open3d.geometry.PointCloud``.

    ``voxel_size`` > 0: voxel-grid downsampling (one averaged point per occupied voxel).
    ``normals_radius`` > 0: normals from a PCA of the neighbours within that radius (at most
    30), flipped to face the sensor, i.e. the origin of the scan's frame.
    """
    o3d = require_open3d()
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {pts.shape}")
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.ascontiguousarray(pts))
    if voxel_size:
        pcd = pcd.voxel_down_sample(float(voxel_size))
    if normals_radius:
        param = o3d.geometry.KDTreeSearchParamHybrid(radius=float(normals_radius), max_nn=30)
        pcd.estimate_normals(search_param=param)
        pcd.orient_normals_towards_camera_location(np.zeros(3))
    return pcd
