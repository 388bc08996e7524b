"""What a 3D run writes beyond the common files (output.run_dir.write_run): poses as 4x4
matrices, the registered cloud, the M-Net's occupancy (voxel grid + marching-cubes mesh), slam6D
frames for 3DTK input, pictures."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from deepmapping.api import Result
from deepmapping.data import ScanSet
from deepmapping.geometry import se3
from deepmapping.io.atomic import make_folder
from deepmapping.io.poses3d import write_kitti_poses, write_poses_npy_3d, write_tum_poses
from deepmapping.io.threedtk import is_3dtk_folder, write_frames, write_pose
from deepmapping.output import plots3d
from deepmapping.output.export3d import (
    occupancy_grid,
    occupancy_mesh,
    write_mesh_ply,
    write_occupancy_grid,
    write_registered_cloud,
)
from deepmapping.solver.resolution import export_voxel


def write_occupancy(out: Path, scans: ScanSet, result: Result, voxel: float | None) -> dict:
    """The M-Net's map as a voxel grid of occupancy probabilities and its 0.5 level set as a mesh;
    returns the grid's voxel and shape. Default voxel: half the M-Net's finest period (64-128
    cells along the longest side, solver.resolution.export_voxel)."""
    glob = se3.transform_points(result.poses, scans.points)[scans.valid]
    lo, hi = glob.min(0), glob.max(0)
    voxel = voxel or export_voxel(float((hi - lo).max()), (result.map_resolution or {}).get("finest_period"))
    grid, origin, voxel = occupancy_grid(result.occupancy, lo, hi, voxel)
    write_occupancy_grid(out / "occupancy.npz", grid, origin, voxel)
    verts, tris = occupancy_mesh(grid, origin, voxel, level=0.5)
    write_mesh_ply(out / "occupancy_mesh.ply", verts, tris)
    return {"voxel": float(voxel), "cells": list(grid.shape), "megabytes": grid.size * 4 / 2**20}


class Extras3D:
    """What a 3D run writes beyond the common files."""

    @staticmethod
    def write_poses(out: Path, scans: ScanSet, poses: np.ndarray) -> None:
        write_poses_npy_3d(out / "poses.npy", poses)
        write_kitti_poses(out / "poses_kitti.txt", poses)
        write_tum_poses(out / "poses_tum.txt", poses)

    @staticmethod
    def write_map(out: Path, scans: ScanSet, poses: np.ndarray) -> None:
        write_registered_cloud(out / "map.ply", scans.points, scans.valid, poses)
        write_registered_cloud(out / "map.pcd", scans.points, scans.valid, poses)

    @staticmethod
    def write_more(out: Path, scans: ScanSet, result: Result) -> dict:
        """3DTK input: slam6D-style ``frames/scanNNN.frames`` (one line, the final pose) and ``.pose``;
        the M-Net's occupancy grid and mesh. Returns what run.json says of the map's resolution."""
        if is_3dtk_folder(Path(scans.source)):
            make_folder(out / "frames")
            for name, pose in zip(scans.names, result.poses):
                write_frames(out / "frames" / f"{name}.frames", pose[None])
                write_pose(out / "frames" / f"{name}.pose", pose)
        grid = None
        if result.occupancy is not None:
            grid = write_occupancy(out, scans, result, result.config.eval.voxel_size)
        return {"map_resolution": result.map_resolution, "occupancy_grid": grid}

    @staticmethod
    def write_pictures(out: Path, scans: ScanSet, result: Result) -> None:
        title = result.method
        if result.metrics:
            title += f" — ATE {result.metrics['ate']:.1f} {scans.unit}"
        plots3d.plot_cloud_3d(out / "map.png", scans.points, scans.valid, result.poses, scans.gt_poses, title=title,
                              unit_scale=scans.unit_scale, unit=scans.unit)
