"""2D pose-graph optimization: sequential and loop-closure edges, robust least squares (SciPy).

An edge (i, j, z) says "pose j seen from pose i is z" (z = relative(T_i, T_j), [dx, dy, dθ]).
Residuals are whitened by the edge's standard deviations (sigma_t metres, sigma_r radians)
and a Cauchy loss down-weights edges that disagree with the rest (a wrong loop closure).
The first pose is held fixed. scipy.optimize.least_squares with the Jacobian's sparsity
pattern keeps it fast on thousands of poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix

from deepmapping.geometry import se2

__all__ = ["Edge", "optimize_pose_graph"]


@dataclass
class Edge:
    i: int
    j: int
    z: np.ndarray  # (3,) relative(T_i, T_j)
    sigma_t: float = 0.05
    sigma_r: float = np.radians(1.0)


def _residuals(x, fixed, ii, jj, z, w):
    poses = np.vstack([fixed, x.reshape(-1, 3)])
    rel = se2.relative(poses[ii], poses[jj])
    r = rel - z
    r[:, 2] = se2.wrap_angle(r[:, 2])
    return (r * w).ravel()


def _sparsity(ii, jj, k):
    """The Jacobian's pattern: edge e's three residuals depend on the three parameters of each of
    its two poses (pose 0 is fixed, not a parameter)."""
    three = np.arange(3)
    blocks = [np.broadcast_arrays((3 * e)[:, None, None] + three[:, None], (3 * (node[e] - 1))[:, None, None] + three)
              for node in (np.asarray(ii), np.asarray(jj)) for e in [np.flatnonzero(node > 0)]]
    rows = np.concatenate([r.ravel() for r, _ in blocks])
    cols = np.concatenate([c.ravel() for _, c in blocks])
    m = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(3 * len(ii), 3 * (k - 1))).tocsr()
    m.data[:] = 1  # an edge from a pose to itself would count twice
    return m


def optimize_pose_graph(poses: np.ndarray, edges: list[Edge], robust_scale: float = 3.0,
                        max_nfev: int = 50) -> np.ndarray:
    """Poses (K, 3) that best agree with the edges (pose 0 kept where it is)."""
    poses = np.asarray(poses, dtype=np.float64)
    if not edges or len(poses) < 2:
        return poses.copy()
    ii = np.array([e.i for e in edges])
    jj = np.array([e.j for e in edges])
    z = np.array([e.z for e in edges], dtype=np.float64)
    w = np.array([[1 / e.sigma_t, 1 / e.sigma_t, 1 / e.sigma_r] for e in edges])
    fixed = poses[:1]
    sol = least_squares(_residuals, poses[1:].ravel(), args=(fixed, ii, jj, z, w), method="trf",
                        jac_sparsity=_sparsity(ii, jj, len(poses)), loss="cauchy", f_scale=robust_scale,
                        x_scale="jac", max_nfev=max_nfev)
    out = np.vstack([fixed, sol.x.reshape(-1, 3)])
    out[:, 2] = se2.wrap_angle(out[:, 2])
    return out
