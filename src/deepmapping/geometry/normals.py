"""Surface normals of point sets, 2D or 3D (numpy/scipy only)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def pca_normals(points: np.ndarray, k: int = 6, tree: cKDTree | None = None) -> np.ndarray:
    """Unit normals (M, D) from PCA of each point's k nearest neighbours (itself included): the
    direction of least spread. ``tree``: a k-d tree of ``points`` already built."""
    pts = np.asarray(points, dtype=np.float64)
    m = pts.shape[0]
    k = int(min(max(k, 2), m))
    tree = cKDTree(pts) if tree is None else tree
    _, idx = tree.query(pts, k=k)
    nb = pts[idx.reshape(m, k)]  # (M, k, D)
    nb = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("mki,mkj->mij", nb, nb)
    _, vecs = np.linalg.eigh(cov)  # ascending eigenvalues
    return vecs[:, :, 0]
