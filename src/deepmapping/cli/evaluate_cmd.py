"""`deepmapping evaluate RUN_DIR`: metrics of a finished run against ground truth."""

from __future__ import annotations

import json
from pathlib import Path

from deepmapping.api import evaluate_poses, evaluate_relations
from deepmapping.config import load_config
from deepmapping.errors import InputError
from deepmapping.io.depth import DepthOptions
from deepmapping.io.loaders import load_scans
from deepmapping.io.poses import read_poses_npy
from deepmapping.io.poses3d import read_poses_3d
from deepmapping.output.run_dir import write_json


def run_evaluate(run_dir: Path, gt: Path | None = None) -> dict:
    info_path = run_dir / "run.json"
    if not info_path.is_file():
        raise InputError(f"{run_dir}: not a run folder (no run.json)")
    try:
        info = json.loads(info_path.read_text())
    except (OSError, json.JSONDecodeError):
        raise InputError(f"{info_path}: corrupt run description") from None
    if not (run_dir / "poses.npy").is_file():
        raise InputError(f"{run_dir}: run has no poses.npy (unfinished or interrupted?)")

    depth = DepthOptions.from_dict(info["depth"]) if info.get("depth") else None  # the frames the run had
    scans = load_scans(info["data"], fmt=info.get("format"), gt_path=gt or info.get("gt"),
                       keyframes=info.get("keyframes"), non_keyframes=info.get("non_keyframes"), depth=depth)
    relations = scans.gt_poses is None and scans.sequence is not None and scans.sequence.relations_path
    if scans.gt_poses is None and not relations:
        raise InputError(f"{info['data']}: no ground truth known; pass --gt FILE")
    if scans.is_3d:
        poses = read_poses_3d(run_dir / "poses.npy")
    else:
        poses = read_poses_npy(run_dir / "poses.npy")
    if poses.shape != (scans.num_scans, *scans.pose_shape()):
        raise InputError(f"{run_dir / 'poses.npy'}: {poses.shape[0]} poses for {scans.num_scans} scans")
    cfg = load_config("default", run_dir / "config.yaml") if (run_dir / "config.yaml").exists() else load_config()
    if relations:
        metrics = evaluate_relations(scans, poses)
    else:
        metrics = evaluate_poses(scans, poses, cfg.eval.success_threshold)
    metrics |= {"method": info.get("method", "?"), "runtime_s": info.get("runtime_s")}
    write_json(run_dir / "metrics.json", metrics)
    return metrics
