"""The run folder of a 3D registration: poses (npy, KITTI, TUM), registered cloud, M-Net
occupancy (voxel grid + marching-cubes mesh), pictures, metrics."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from deepmapping.api import Result
from deepmapping.data import ScanSet
from deepmapping.geometry import se3
from deepmapping.io.atomic import make_folder, write_json
from deepmapping.io.poses3d import write_kitti_poses, write_poses_npy_3d, write_tum_poses
from deepmapping.io.threedtk import is_3dtk_folder, write_frames, write_pose
from deepmapping.output import plots, plots3d
from deepmapping.output.export3d import (
    occupancy_grid,
    occupancy_mesh,
    write_mesh_ply,
    write_occupancy_grid,
    write_registered_cloud,
)
from deepmapping.output.run_files import write_config, write_history_csv
from deepmapping.solver.resolution import export_voxel


def write_poses_3d(out: Path, poses: np.ndarray) -> None:
    write_poses_npy_3d(out / "poses.npy", poses)
    write_kitti_poses(out / "poses_kitti.txt", poses)
    write_tum_poses(out / "poses_tum.txt", poses)


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


def write_run_3d(out: Path, scans: ScanSet, result: Result, data_info: dict, plots: bool = True) -> list[Path]:
    make_folder(out)
    write_poses_3d(out, result.poses)
    write_config(out, result.config)
    write_registered_cloud(out / "map.ply", scans.points, scans.valid, result.poses)
    write_registered_cloud(out / "map.pcd", scans.points, scans.valid, result.poses)
    _write_3dtk_frames(out, scans, result.poses)
    if result.metrics is not None:
        write_json(out / "metrics.json", result.metrics)
    if result.history.get("iteration"):
        write_history_csv(out / "history.csv", result.history)
    grid = write_occupancy(out, scans, result, result.config.eval.voxel_size) if result.occupancy is not None else None
    write_json(out / "run.json", {"method": result.method, "runtime_s": result.runtime_s,
                                  "num_scans": scans.num_scans, "unit": scans.unit,
                                  "unit_scale": scans.unit_scale, **data_info,
                                  "rollbacks": result.history.get("rollbacks", []),
                                  "stop_reason": result.history.get("stop_reason", ""),
                                  "map_resolution": result.map_resolution, "occupancy_grid": grid})
    if plots:
        _write_pictures(out, scans, result)
    return sorted(p for p in out.iterdir() if p.is_file() and not p.name.startswith("."))


def _write_3dtk_frames(out: Path, scans: ScanSet, poses: np.ndarray) -> None:
    """3DTK input: also slam6D-style ``frames/scanNNN.frames`` (one line, the final pose)."""
    if not is_3dtk_folder(Path(scans.source)):
        return
    make_folder(out / "frames")
    for name, pose in zip(scans.names, poses):
        write_frames(out / "frames" / f"{name}.frames", pose[None])
        write_pose(out / "frames" / f"{name}.pose", pose)


def _write_pictures(out: Path, scans: ScanSet, result: Result) -> None:
    title = result.method
    if result.metrics:
        title += f" — ATE {result.metrics['ate']:.1f} {scans.unit}"
    plots3d.plot_cloud_3d(out / "map.png", scans.points, scans.valid, result.poses, scans.gt_poses, title=title,
                          unit_scale=scans.unit_scale, unit=scans.unit)
    if result.history.get("iteration"):
        plots.plot_curves(out / "curves.png", dict(result.history, unit=scans.unit))
