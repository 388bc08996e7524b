"""Everything a run writes into its folder, each file written atomically: one writer for 2D and 3D,
the steps that differ by dimension in ``Extras2D`` / ``run_dir3d.Extras3D``.

poses.npy, poses_kitti.txt, poses_tum.txt (2D also poses.txt, and all_scans_* for keyframed logs),
map.ply / map.pcd, map.png, curves.png, history.csv, config.yaml, run.json and (when ground truth is
known) metrics.json; 2D: occupancy.png; 3D: occupancy.npz and occupancy_mesh.ply (the M-Net's map),
frames/ for 3DTK input. The checkpoint (checkpoint.pt) is written by the trainer while it runs.
"""

from __future__ import annotations

from datetime import datetime
from pathlib import Path

import numpy as np

from deepmapping.api import Result
from deepmapping.data import ScanSet
from deepmapping.geometry import se2
from deepmapping.geometry.alignment import align_poses_2d
from deepmapping.io.atomic import make_folder, write_json, write_text
from deepmapping.io.pcd import write_pcd
from deepmapping.io.ply import write_ply
from deepmapping.io.poses import write_pose_text, write_poses_npy
from deepmapping.io.poses3d import write_kitti_poses, write_tum_poses
from deepmapping.methods.keyframes import place_all_scans
from deepmapping.output import plots
from deepmapping.output.run_dir3d import Extras3D
from deepmapping.output.run_files import write_config, write_history_csv


def default_run_dir(method: str, root: str | Path = "runs") -> Path:
    """runs/YYYYmmdd-HHMMSS_<method> (a fresh timestamped folder per run)."""
    return Path(root) / f"{datetime.now():%Y%m%d-%H%M%S}_{method}"


def write_run(out: Path, scans: ScanSet, result: Result, data_info: dict, plots: bool = True) -> list[Path]:
    """Write every output of a finished run; returns the files written."""
    extras = Extras3D if scans.is_3d else Extras2D
    make_folder(out)
    extras.write_poses(out, scans, result.poses)
    write_config(out, result.config)
    extras.write_map(out, scans, result.poses)
    if result.metrics is not None:
        write_json(out / "metrics.json", result.metrics)
    if result.history.get("iteration"):
        write_history_csv(out / "history.csv", result.history)
    more = extras.write_more(out, scans, result)
    write_json(out / "run.json", {"method": result.method, "runtime_s": result.runtime_s,
                                  "num_scans": scans.num_scans, "unit": scans.unit,
                                  "unit_scale": scans.unit_scale, **data_info,
                                  "rollbacks": result.history.get("rollbacks", []),
                                  "stop_reason": result.history.get("stop_reason", ""),
                                  "reviewed": result.history.get("reviewed", []),
                                  "odometry_sigma": result.history.get("odometry_sigma"), **more})
    if plots:
        extras.write_pictures(out, scans, result)
        _write_curves(out, scans, result)
    return sorted(p for p in out.iterdir() if p.is_file() and not p.name.startswith("."))


def _write_curves(out: Path, scans: ScanSet, result: Result) -> None:
    if result.history.get("iteration"):
        plots.plot_curves(out / "curves.png", dict(result.history, unit=scans.unit))


class Extras2D:
    """What a 2D run writes beyond the common files."""

    @staticmethod
    def write_poses(out: Path, scans: ScanSet, poses: np.ndarray) -> None:
        """poses.npy / poses.txt ([x, y, θ]), KITTI and TUM files (full precision) of the registered
        scans; for a keyframed log also of every input scan (``all_scans_*``, non-keyframes placed
        by odometry from their nearest keyframe), with the log's own timestamps, and the keyframe
        indices."""
        write_poses_npy(out / "poses.npy", poses)
        write_pose_text(out / "poses.txt", poses)
        write_kitti_poses(out / "poses_kitti.txt", se2.to_se3(poses))
        seq = scans.sequence
        write_tum_poses(out / "poses_tum.txt", se2.to_se3(poses), None if seq is None else list(scans.names))
        if seq is None:
            return
        every = place_all_scans(seq, poses)
        write_poses_npy(out / "all_scans_poses.npy", every)
        write_pose_text(out / "all_scans_poses.txt", every)
        write_kitti_poses(out / "all_scans_kitti.txt", se2.to_se3(every))
        write_tum_poses(out / "all_scans_tum.txt", se2.to_se3(every), seq.stamps)
        write_text(out / "keyframes.txt", "".join(f"{k}\n" for k in seq.keyframes))

    @staticmethod
    def write_map(out: Path, scans: ScanSet, poses: np.ndarray) -> None:
        """The registered points (z = 0), coloured by scan."""
        import matplotlib

        glob = se2.transform_points(poses, scans.points[..., :2].astype(np.float64))
        scan_id = np.broadcast_to(np.arange(scans.num_scans)[:, None], scans.valid.shape)
        xy, ids = glob[scans.valid], scan_id[scans.valid]
        colors = (matplotlib.colormaps["turbo"](ids / max(scans.num_scans - 1, 1))[:, :3] * 255).astype(np.uint8)
        cloud = np.column_stack([xy, np.zeros(len(xy))])
        write_ply(out / "map.ply", cloud, colors)
        write_pcd(out / "map.pcd", cloud)

    @staticmethod
    def write_more(out: Path, scans: ScanSet, result: Result) -> dict:
        return {}

    @staticmethod
    def write_pictures(out: Path, scans: ScanSet, result: Result) -> None:
        unit, scale = scans.unit, scans.unit_scale
        flip = unit == "px"  # image frame: y grows downwards, as in the simulator's pictures
        # show the estimate in the ground-truth frame when known (the estimate's frame is arbitrary)
        poses = result.poses if scans.gt_poses is None else align_poses_2d(result.poses, scans.gt_poses)
        title = f"{result.method}"
        if result.metrics and "ate" in result.metrics:
            title += f" — ATE {result.metrics['ate']:.2f} {unit}"
        plots.plot_map(out / "map.png", scans.points, scans.valid, poses, scans.gt_poses, title=title,
                       unit=unit, unit_scale=scale, invert_y=flip)
        if result.occupancy is not None:
            plots.plot_occupancy(out / "occupancy.png", result.occupancy, scans.points, scans.valid, result.poses,
                                 unit=unit, unit_scale=scale, title=f"M-Net occupancy ({result.method})",
                                 invert_y=flip)
