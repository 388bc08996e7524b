"""Unorganized clouds of different sizes -> the padded (K, N, 3) arrays of a ScanSet."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from deepmapping.errors import InputError


def check_max_points(folder: Path, max_points: int | None) -> None:
    if max_points is not None and max_points < 1:
        raise InputError(f"{folder}: max_points must be >= 1, got {max_points}")


def subsample(xyz: np.ndarray, max_points: int | None, rng: np.random.Generator) -> np.ndarray:
    """At most ``max_points`` random points (kept in their original order); None keeps all."""
    if max_points is not None and len(xyz) > max_points:
        return xyz[np.sort(rng.choice(len(xyz), max_points, replace=False))]
    return xyz


def pad_clouds(clouds: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Stack clouds (N_k, 3) into points (K, N, 3) float32 and valid (K, N); padding is invalid zeros."""
    k, n = len(clouds), max(len(c) for c in clouds)
    points, valid = np.zeros((k, n, 3), np.float32), np.zeros((k, n), bool)
    for i, c in enumerate(clouds):
        points[i, : len(c)], valid[i, : len(c)] = c, True
    return points, valid
