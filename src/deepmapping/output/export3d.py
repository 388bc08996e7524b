"""3D outputs of a run: the M-Net's occupancy on a voxel grid, its marching-cubes surface, and
the registered point cloud (every scan moved by its L-Net pose, coloured by scan).

The M-Net f_m maps a global point to its occupancy probability (§3.2); sampled at voxel
centres it gives a grid, and its level set ``f_m = 0.5`` is the estimated surface. Every
writer is atomic: a reader never sees a half-written file.
"""

from __future__ import annotations

import io
import math
import os
from typing import IO, Callable

import numpy as np

from deepmapping.geometry import se3
from deepmapping.io.atomic import atomic_write
from deepmapping.io.pcd import write_pcd
from deepmapping.io.ply import write_ply

__all__ = ["occupancy_grid", "write_occupancy_grid", "read_occupancy_grid", "occupancy_mesh",
           "write_mesh_ply", "scan_colors", "registered_cloud", "write_registered_cloud"]


def _numpy(values) -> np.ndarray:
    if hasattr(values, "detach"):  # a torch tensor
        values = values.detach().cpu().numpy()
    return np.asarray(values, dtype=np.float32).reshape(-1)


def occupancy_grid(occupancy_fn: Callable, lo, hi, resolution: float, chunk: int = 1 << 18,
                   max_voxels: int = 64_000_000):
    """Occupancy probabilities at the voxel centres of the box [lo, hi].

    ``occupancy_fn(xyz (M, 3) float32) -> (M,)`` is called on at most ``chunk`` points at a
    time. Returns ``(grid (nx, ny, nz) float32, origin (3,), voxel)``: grid[i, j, k] is the
    occupancy at ``origin + voxel * (i, j, k)``, origin = lo + voxel / 2.
    """
    lo, hi, voxel = np.asarray(lo, np.float64), np.asarray(hi, np.float64), float(resolution)
    if lo.shape != (3,) or hi.shape != (3,) or not (hi > lo).all():
        raise ValueError(f"need lo < hi, both (3,), got {lo} and {hi}")
    if not (voxel > 0 and math.isfinite(voxel)):
        raise ValueError(f"resolution must be positive, got {resolution}")
    shape = tuple(max(int(math.ceil(s / voxel - 1e-9)), 1) for s in hi - lo)
    if math.prod(shape) > max_voxels:
        raise ValueError(f"occupancy grid too large ({shape[0]}x{shape[1]}x{shape[2]}); increase resolution")
    origin = lo + voxel / 2
    total = math.prod(shape)
    out = np.empty(total, np.float32)
    for start in range(0, total, chunk):
        ijk = np.stack(np.unravel_index(np.arange(start, min(start + chunk, total)), shape), axis=1)
        xyz = (origin + voxel * ijk).astype(np.float32)
        vals = _numpy(occupancy_fn(xyz))
        if vals.shape != (len(xyz),):
            raise ValueError(f"occupancy_fn returned {vals.shape[0]} values for {len(xyz)} points")
        out[start : start + len(xyz)] = vals
    return out.reshape(shape), origin, voxel


def write_occupancy_grid(path: str | os.PathLike, grid, origin, voxel: float) -> None:
    """Save ``grid`` (float32), ``origin`` (3,) and ``voxel`` to a compressed .npz, atomically."""
    buf = io.BytesIO()
    np.savez_compressed(buf, grid=np.asarray(grid, np.float32), origin=np.asarray(origin, np.float64),
                        voxel=np.float64(voxel))
    atomic_write(path, lambda f: f.write(buf.getvalue()))


def read_occupancy_grid(path: str | os.PathLike):
    """(grid, origin, voxel) of a file written by ``write_occupancy_grid``."""
    with np.load(path) as z:
        return z["grid"], z["origin"], float(z["voxel"])


def occupancy_mesh(grid, origin, voxel: float, level: float = 0.5):
    """Marching-cubes surface ``occupancy = level`` of a grid: (vertices (V, 3) float64 in world
    coordinates, triangles (T, 3) int64) wound counter-clockwise seen from lower occupancy
    (free space), so that viewers shade the outside of the occupied regions.
    Empty arrays when the grid does not cross ``level`` (or is thinner than 2 voxels)."""
    grid = np.asarray(grid, np.float32)
    empty = (np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    if grid.ndim != 3 or min(grid.shape) < 2 or not (grid.min() < level < grid.max()):
        return empty
    from skimage.measure import marching_cubes

    verts, faces, _, _ = marching_cubes(grid, level=level, spacing=(voxel,) * 3, gradient_direction="ascent")
    return verts.astype(np.float64) + np.asarray(origin, np.float64), faces.astype(np.int64)


def write_mesh_ply(path: str | os.PathLike, vertices, triangles) -> None:
    """Binary little-endian PLY: float x y z vertices, uchar/int ``vertex_indices`` faces."""
    v, t = np.asarray(vertices, np.float32).reshape(-1, 3), np.asarray(triangles, np.int64).reshape(-1, 3)
    if len(t) and (t.min() < 0 or t.max() >= len(v)):
        raise ValueError(f"triangle indices must be in [0, {len(v)})")
    faces = np.zeros(len(t), np.dtype([("n", "u1"), ("i", "<i4", (3,))]))
    faces["n"], faces["i"] = 3, t
    header = ("ply\nformat binary_little_endian 1.0\ncomment written by deepmapping\n"
              f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
              f"element face {len(t)}\nproperty list uchar int vertex_indices\nend_header\n")

    def _write(f: IO[bytes]) -> None:
        f.write(header.encode("ascii"))
        f.write(v.astype("<f4").tobytes())
        f.write(faces.tobytes())

    atomic_write(path, _write)


def scan_colors(k: int) -> np.ndarray:
    """(k, 3) uint8 colours of scans 0..k-1 from a qualitative colormap (tab20, cycled)."""
    import matplotlib

    table = np.asarray(matplotlib.colormaps["tab20"].colors)
    table = np.concatenate([table[0::2], table[1::2]])  # the 10 strong colours first
    return np.round(table[np.arange(k) % len(table)] * 255).astype(np.uint8)


def registered_cloud(points, valid, poses):
    """Valid points (K, N, 3) moved by their poses (K, 4, 4): (pts (M, 3) float64, scan_index (M,))."""
    pts, val = np.asarray(points, np.float64), np.asarray(valid, bool)
    poses = np.asarray(poses, np.float64)
    if pts.ndim != 3 or pts.shape[2] != 3 or val.shape != pts.shape[:2] or poses.shape != (len(pts), 4, 4):
        raise ValueError(f"need points (K, N, 3), valid (K, N), poses (K, 4, 4); got "
                         f"{pts.shape}, {val.shape}, {poses.shape}")
    glob = se3.transform_points(poses, pts)
    index = np.broadcast_to(np.arange(len(pts))[:, None], val.shape)
    return glob[val], index[val]


def write_registered_cloud(path: str | os.PathLike, points, valid, poses) -> None:
    """The registered cloud: binary PLY with one colour per scan (``scan_colors``), or binary PCD
    (x y z) when ``path`` ends in .pcd."""
    pts, index = registered_cloud(points, valid, poses)
    if str(path).lower().endswith(".pcd"):
        write_pcd(path, pts)
        return

    write_ply(path, pts, scan_colors(len(np.asarray(points)))[index])
