"""Multiway registration, the baseline [12] of §4.2 and supp. C (Choi, Zhou & Koltun 2015, as in Open3D).

Each scan is a pose-graph node. Pairs of scans are registered by coarse-then-fine
point-to-plane ICP; the result and its information matrix form an edge: an *odometry* edge
(consecutive scans, certain) or a *loop-closure* edge (any other pair, uncertain, so the
line process of the global optimization may prune it). Node poses start from the chained
odometry (or from ``init``) and are refined by Levenberg-Marquardt pose-graph optimization.
Default scales as in :mod:`deepmapping.methods.icp3d`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from deepmapping.errors import ConfigError
from deepmapping.geometry import se3
from deepmapping.methods.icp3d import check_clouds, check_init, default_scales, plausible, prepare_clouds, register_pair
from deepmapping.methods.open3d_utils import quiet_open3d

__all__ = ["multiway_registration", "build_pose_graph", "edge_pairs"]


def edge_pairs(k: int, edges: str = "all") -> list[tuple[int, int]]:
    """Scan pairs (i, j), i < j, to register: every pair ("all") or ``j - i <= N`` ("window:N")."""
    if edges == "all":
        window = k
    elif isinstance(edges, str) and edges.startswith("window:") and edges[7:].isdigit() and int(edges[7:]) >= 1:
        window = int(edges[7:])
    else:
        raise ConfigError(f"edges must be 'all' or 'window:N' with N >= 1, got {edges!r}")
    return [(i, j) for i in range(k) for j in range(i + 1, min(i + window, k - 1) + 1)]


def build_pose_graph(clouds, init=None, voxel_size=None, max_correspondence_distance=None,
                     edges: str = "all", progress: Callable[[int, int], None] | None = None):
    """The pose graph before optimization; returns (open3d PoseGraph, Scales).

    Node k holds the pose of scan k (sensor to world); the edge (i, j) holds T_ij, the pose of
    scan i in scan j's frame, as found by ICP from the guess of the initial node poses.
    Implausible pairwise results (see ``plausible``) are not trusted.
    """
    clouds = check_clouds(clouds)
    k = len(clouds)
    init = check_init(init, k)
    pairs = edge_pairs(k, edges)
    scales = default_scales(clouds, voxel_size, max_correspondence_distance)
    pcds = prepare_clouds(clouds, scales)
    with quiet_open3d() as o3d:
        reg = o3d.pipelines.registration
        poses = se3.identity((k,)) if init is None else init.copy()
        results = {}
        # Odometry pairs first: their chain gives the initial node poses (when no init).
        ordered = sorted(pairs, key=lambda p: (p[1] - p[0] != 1, p))
        for done, (i, j) in enumerate(ordered, start=1):
            # without init, scan j of an odometry pair is not placed yet: start it where scan i is
            # (as incremental ICP does), not at the origin (that guess was scan i's whole pose)
            guess = np.eye(4) if init is None and j == i + 1 else se3.relative(poses[j], poses[i])
            res = register_pair(pcds[i], pcds[j], guess, scales)
            failed = not plausible(res, guess, scales, pcds[i].get_center())
            results[i, j] = (guess if failed else res.transformation), failed
            if init is None and j == i + 1:
                poses[j] = poses[i] @ np.linalg.inv(results[i, j][0])
            if progress is not None:
                progress(done, len(pairs))
        graph = reg.PoseGraph()
        for pose in poses:
            graph.nodes.append(reg.PoseGraphNode(pose))
        for (i, j), (transform, failed) in sorted(results.items()):
            odometry = j == i + 1
            if failed and not odometry:
                continue
            info = reg.get_information_matrix_from_point_clouds(pcds[i], pcds[j], scales.fine, transform)
            graph.edges.append(reg.PoseGraphEdge(i, j, transform, info, uncertain=failed or not odometry))
    return graph, scales


def multiway_registration(
    clouds,
    init: np.ndarray | None = None,
    voxel_size: float | None = None,
    max_correspondence_distance: float | None = None,
    edges: str = "all",
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """Multiway registration [12] of K scans (each (N_i, 3) in its sensor frame) -> poses (K, 4, 4).

    ``edges``: "all" (every pair) or "window:N" (pairs at most N scans apart). ``progress(done,
    total)`` after each pairwise registration. The optimization keeps node 0 fixed
    (reference node) with the fine correspondence distance and an edge-prune threshold of
    0.25; the result is re-anchored so that pose 0 = ``init[0]`` or the identity.
    """
    graph, scales = build_pose_graph(clouds, init, voxel_size, max_correspondence_distance, edges, progress)
    with quiet_open3d() as o3d:
        reg = o3d.pipelines.registration
        option = reg.GlobalOptimizationOption(max_correspondence_distance=scales.fine,
                                              edge_prune_threshold=0.25, reference_node=0)
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                reg.GlobalOptimizationConvergenceCriteria(), option)
    poses = np.stack([np.asarray(node.pose, dtype=np.float64) for node in graph.nodes])
    anchor = np.eye(4) if init is None else np.asarray(init, dtype=np.float64)[0]
    return se3.compose(anchor @ se3.inverse(poses[0]), poses)
