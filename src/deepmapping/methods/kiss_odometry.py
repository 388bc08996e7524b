"""KISS-ICP (Vizzo et al., RA-L 2023) as a warm start for LiDAR sequences: the odometry LiDAR
users already run (PyPI ``kiss-icp``), frame to local map, adaptive threshold, constant
velocity. Used as a library; its defaults except two that follow our data:

- ``data.max_range`` = the largest range of the sequence (its default, 100 m, sets the voxel
  of a 30 m simulator scan to 1 m); KISS-ICP's own rule then gives voxel = max_range / 100;
- no deskewing: our clouds carry no per-point timestamps;
- one thread: its parallel reductions may add in another order from run to run, and a run
  must be reproducible (``threads`` > 1 asks for more).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from deepmapping.errors import ConfigError
from deepmapping.methods.icp3d import check_clouds, check_init

__all__ = ["kiss_icp_poses", "kiss_config"]


def kiss_config(clouds: list[np.ndarray], voxel_size: float | None = None, threads: int = 1):
    """KISS-ICP's config for these clouds (sensor frames): max range from the data, no deskew."""
    try:
        from kiss_icp.config import KISSConfig
    except ImportError as exc:  # a dependency of the package; only a broken install lacks it
        raise ConfigError(f"warm start kiss-icp: cannot import kiss_icp ({exc}); pip install kiss-icp") from None
    max_range = float(max(np.linalg.norm(c, axis=1).max() for c in clouds)) * 1.01
    cfg = KISSConfig()
    cfg.data.max_range, cfg.data.min_range, cfg.data.deskew = max_range, 0.0, False
    cfg.mapping.voxel_size = float(voxel_size) if voxel_size else max_range / 100.0
    cfg.registration.max_num_threads = int(threads)
    return cfg


def kiss_icp_poses(clouds, init: np.ndarray | None = None, voxel_size: float | None = None, threads: int = 1,
                   progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """Sensor-to-world poses (K, 4, 4) of an ordered sequence of clouds ((N_i, 3), sensor
    frames) by KISS-ICP odometry, pose 0 = ``init[0]`` (or the identity); the rest of ``init``
    is not used (KISS-ICP predicts each frame by constant velocity)."""
    from kiss_icp.kiss_icp import KissICP

    clouds = check_clouds(clouds)
    k = len(clouds)
    start = np.eye(4) if init is None else check_init(init, k)[0]
    odom = KissICP(kiss_config(clouds, voxel_size, threads))
    poses = np.empty((k, 4, 4))
    for i, c in enumerate(clouds):
        odom.register_frame(np.ascontiguousarray(c, dtype=np.float64), np.zeros(len(c)))
        poses[i] = start @ odom.last_pose
        if progress is not None and i:
            progress(i, k - 1)
    return poses
