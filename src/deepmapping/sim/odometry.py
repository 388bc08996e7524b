"""Wheel odometry for a known trajectory: a corrected log becomes a raw log whose reference is known.

The Freiburg benchmark ships corrected logs (poses from a SLAM system) of sites whose raw logs are
not in ``../shared`` (belgioioso, edmonton, fhw, freiburg-101). Their scans with odometry drawn
from this model are logs nobody tuned on, scored against the corrected poses
(``deepmapping simulate OUT --kind odometry --log CORRECTED``, ``deepmapping experiment carmen``).

The model's defaults were measured on the three raw logs of ``../shared`` against their corrected
logs, keyframe to keyframe (intel, fr079, mit-csail): a scale error of the distance driven of
+1.2 %, -6.3 % and -2.2 %; a heading drift of -3.3, -0.8 and -0.1 deg per metre; each turn off by
0.26-0.39 of its angle (standard deviation). Per log one scale error and one drift are drawn, per
step the rest.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deepmapping.geometry import se2
from deepmapping.io.carmen import read_carmen, write_with_poses
from deepmapping.io.relations import relations_from_corrected, write_relations

__all__ = ["OdometryNoise", "simulate_odometry", "path_timestamps", "simulated_log"]


@dataclass(frozen=True)
class OdometryNoise:
    """Standard deviations of the odometry's errors."""

    scale: float = 0.03  # of the distance driven, one draw per log (a wheel radius off)
    drift_deg_per_m: float = 1.5  # heading drift, one draw per log (unequal wheels, a wheel base off)
    step: float = 0.05  # of each step's length
    lateral: float = 0.02  # sideways slip, as a fraction of the step's length
    turn: float = 0.25  # of each step's turn
    heading_deg_per_m: float = 0.3  # heading noise of each step, per metre of it


def simulate_odometry(poses: np.ndarray, seed: int = 0, noise: OdometryNoise = OdometryNoise()) -> np.ndarray:
    """Odometry (S, 3) for the true poses (S, 3) [x, y, theta]: it starts at the first pose and adds
    up each true step with the errors of ``noise``; the same seed gives the same odometry."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3:
        raise ValueError(f"poses must be (S, 3), got {poses.shape}")
    rng = np.random.default_rng(seed)
    scale = 1.0 + rng.normal(0.0, noise.scale)
    drift = rng.normal(0.0, np.radians(noise.drift_deg_per_m))
    steps = se2.relative(poses[:-1], poses[1:])
    length = np.hypot(steps[:, 0], steps[:, 1])
    k = len(steps)
    measured = steps.copy()
    measured[:, :2] *= (scale * (1.0 + rng.normal(0.0, noise.step, k)))[:, None]
    measured[:, 1] += rng.normal(0.0, noise.lateral, k) * length
    turn_sd = noise.turn * np.abs(steps[:, 2]) + np.radians(noise.heading_deg_per_m) * length
    measured[:, 2] += drift * length + rng.normal(0.0, 1.0, k) * turn_sd
    out = np.empty_like(poses)
    out[0] = poses[0]
    for i in range(k):
        out[i + 1] = se2.compose(out[i], measured[i])
    return out


def path_timestamps(poses: np.ndarray, speed: float = 0.5) -> np.ndarray:
    """Timestamps (S,) of a robot driving along ``poses`` at ``speed`` m/s (plus 10 ms a scan, so
    that none repeat): for a log whose own timestamps cannot tell its scans apart (belgioioso's
    are printed to six digits)."""
    poses = np.asarray(poses, dtype=np.float64)
    return np.concatenate([[0.0], np.cumsum(_step_lengths(poses))]) / speed + 0.01 * np.arange(len(poses))


def _step_lengths(poses: np.ndarray) -> np.ndarray:
    return np.hypot(*np.diff(poses[:, :2], axis=0).T)


def simulated_log(corrected: str | Path, folder: str | Path, seed: int = 0,
                  noise: OdometryNoise = OdometryNoise()) -> tuple[Path, Path, dict]:
    """Write ``<site>.clf`` (the corrected log's scans, their poses replaced by ``simulate_odometry``;
    timestamps from ``path_timestamps`` where the log's own repeat) and ``<site>.relations``
    (derived from the corrected poses: ``evaluation.relations.derive_relations``) to ``folder``;
    returns both paths and a summary (scans, path length, the odometry's error at the end)."""
    corrected, folder = Path(corrected), Path(folder)
    site = corrected.name.split(".")[0].removesuffix("-corrected")
    log = read_carmen(corrected)
    odometry = simulate_odometry(log.poses, seed, noise)
    stamps = None
    if len(set(log.stamps)) < log.num_scans:
        stamps = [f"{t:.3f}" for t in path_timestamps(log.poses)]
    folder.mkdir(parents=True, exist_ok=True)
    log_path, relations_path = folder / f"{site}.clf", folder / f"{site}.relations"
    write_with_poses(corrected, log_path, odometry, stamps)
    write_relations(relations_path, relations_from_corrected(corrected, log_path))
    summary = {"scans": log.num_scans, "path_m": float(_step_lengths(log.poses).sum()),
               "end_error_m": float(np.hypot(*(odometry[-1, :2] - log.poses[-1, :2]))),
               "own_timestamps": stamps is None}
    return log_path, relations_path, summary
