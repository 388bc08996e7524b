"""DeepMapping loss: L_cls (eq. 4) + lambda * L_ch (eq. 5-7), and an optional odometry factor."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree

from deepmapping.geometry.normals import pca_normals
from deepmapping.solver.geometry import relative

# queries x targets per pair from which the nearest neighbours come from a k-d tree (SciPy) instead
# of the full distance matrix: 3D scans (256 x 4800 on 80x60 depth images: 10x faster); the 2D
# sizes (256 x 256 beams, 361 x 361 on CARMEN logs) keep the matrix, so their runs are unchanged
KDTREE_MIN_PAIRS = 1 << 18


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    m = mask.to(x.dtype)
    return (x * m).sum() / m.sum().clamp(min=1)


def occupancy_bce(occ_logits: torch.Tensor, occ_mask: torch.Tensor,
                  free_logits: torch.Tensor, free_mask: torch.Tensor) -> torch.Tensor:
    """Eq. 4 with logits: mean BCE of occupied samples against 1 plus free samples against 0.

    Masks drop samples of invalid beams (no return) from both means.
    """
    occ = F.binary_cross_entropy_with_logits(occ_logits, torch.ones_like(occ_logits), reduction="none")
    free = F.binary_cross_entropy_with_logits(free_logits, torch.zeros_like(free_logits), reduction="none")
    return masked_mean(occ, occ_mask) + masked_mean(free, free_mask)


def nearest_distance(q: torch.Tensor, qv: torch.Tensor, t: torch.Tensor, tv: torch.Tensor,
                     tn: torch.Tensor | None = None, truncate: float | None = None,
                     target: torch.Tensor | None = None, trees: dict | None = None) -> torch.Tensor:
    """Mean over valid queries q (P, n, D) of the distance to the nearest valid t (P, m, D) -> (P,);
    with t's unit normals tn (P, m, D): the distance along the nearest point's normal (point to plane).
    ``target`` (P,), ``trees``: which cloud each t is, and its k-d trees so far (as nearest_index).

    The neighbour is searched without gradient and the distance to it re-evaluated with
    gradient (same value and gradient as the minimum, 5x faster).
    """
    nn_idx = nearest_index(q, t, tv, target, trees)
    gather = nn_idx[..., None].expand(-1, -1, t.shape[2])
    diff = q - t.gather(1, gather)
    point = (diff.pow(2).sum(-1) + 1e-12).sqrt()
    dist = point if tn is None else ((diff * tn.gather(1, gather)).sum(-1).pow(2) + 1e-12).sqrt()
    if truncate is not None:  # a query without a neighbour within ``truncate`` counts ``truncate``, no gradient
        dist = torch.where(point.detach() <= truncate, dist, dist.new_full((), truncate))
    return (dist * qv).sum(1) / qv.sum(1).clamp(min=1)


def nearest_index(q: torch.Tensor, t: torch.Tensor, tv: torch.Tensor, target: torch.Tensor | None = None,
                  trees: dict | None = None) -> torch.Tensor:
    """Index (P, n) of the nearest valid point of t (P, m, D) to each query of q (P, n, D), no gradient.

    On the CPU and from ``KDTREE_MIN_PAIRS`` distances a pair on, a k-d tree of each target's valid
    points; else the full distance matrix. Both give the exact nearest neighbour (up to rounding
    on near ties). ``target`` (P,): which cloud each t is; pairs with the same target share its
    tree (a batch's every pair: one tree a scan, not one a pair; the same neighbours); ``trees``:
    the trees built so far by target (a dict this call adds to: chamfer's two directions share it).
    """
    with torch.no_grad():
        if q.device.type != "cpu" or q.shape[1] * t.shape[1] < KDTREE_MIN_PAIRS:
            return torch.cdist(q, t).masked_fill(~tv[:, None, :], float("inf")).argmin(dim=2)
        qn, tn, tvn = q.detach().numpy(), t.detach().numpy(), tv.numpy()
        index = np.zeros(q.shape[:2], dtype=np.int64)
        names = range(q.shape[0]) if target is None else target.tolist()
        trees = {} if trees is None or target is None else trees
        for p, name in enumerate(names):  # non-finite points (a diverged step) get any index: their distance stays NaN
            if name not in trees:
                keep = np.flatnonzero(tvn[p] & np.isfinite(tn[p]).all(1))
                trees[name] = (keep, cKDTree(tn[p, keep]) if keep.size else None)
            keep, tree = trees[name]
            if keep.size:  # no valid target: any index (the pair's term is dropped by chamfer's ``has``)
                queries = np.where(np.isfinite(qn[p]), qn[p], 0.0)
                index[p] = keep[tree.query(queries, k=1)[1]]
        return torch.from_numpy(index)


def chamfer(x: torch.Tensor, xv: torch.Tensor, y: torch.Tensor, yv: torch.Tensor,
            xq: torch.Tensor | None = None, xqv: torch.Tensor | None = None,
            yq: torch.Tensor | None = None, yqv: torch.Tensor | None = None,
            xn: torch.Tensor | None = None, yn: torch.Tensor | None = None,
            truncate: float | None = None, x_id: torch.Tensor | None = None,
            y_id: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 5 for P pairs at once: x (P, N, D), y (P, M, D) with validity masks -> (P,).

    Two-way mean Euclidean distance to the nearest point of the other cloud; invalid points
    neither count nor serve as neighbours. Optional query subsets xq of x and yq of y (the
    beams sampled this step) estimate each mean from fewer points, against the full clouds.
    With both clouds' unit normals xn, yn: each distance along the nearest point's normal.
    x_id, y_id (P,): which cloud each x and y is (pairs sharing a cloud share its k-d tree, in
    both directions).
    """
    xq, xqv = (x, xv) if xq is None else (xq, xqv)
    yq, yqv = (y, yv) if yq is None else (yq, yqv)
    has = (xv.any(1) & yv.any(1)).to(x.dtype)
    trees = {} if x_id is not None and y_id is not None else None
    return (nearest_distance(xq, xqv, y, yv, yn, truncate, y_id, trees)
            + nearest_distance(yq, yqv, x, xv, xn, truncate, x_id, trees)) * has


def temporal_pairs(indices: torch.Tensor, window: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions (a, b) in a batch whose scans are temporal neighbours: 0 < i_b - i_a <= window."""
    diff = indices[None, :] - indices[:, None]
    a, b = torch.nonzero((diff > 0) & (diff <= window), as_tuple=True)
    return a, b


def place_pairs(places: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions (a < b) in a batch of each scan and its ``k`` nearest others by place (``places``
    (B, F), as trainer.place_batches), each pair once."""
    d = np.linalg.norm(places[:, None] - places[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    near = np.argsort(d, axis=1, kind="stable")[:, : min(k, len(places) - 1)]
    a = np.repeat(np.arange(len(places)), near.shape[1])
    pairs = np.unique(np.sort(np.stack([a, near.ravel()], 1), axis=1), axis=0)
    return pairs[:, 0], pairs[:, 1]


def chamfer_loss(glob: torch.Tensor, valid: torch.Tensor, indices: torch.Tensor, window: int,
                 queries: torch.Tensor | None = None, queries_valid: torch.Tensor | None = None,
                 first_below: int | None = None, normals: torch.Tensor | None = None,
                 truncate: float | None = None, extra_pairs: tuple | None = None) -> torch.Tensor:
    """Eq. 7 averaged over the neighbour pairs present in the batch (0 when there are none).

    glob (B, N, D): whole scans in the global frame; queries (B, n, D): optional subsets of them
    whose distances to the neighbour's whole scan estimate the two means of eq. 5; normals (B, N, D):
    the scans' unit normals in the global frame, for point-to-plane distances.
    ``first_below``: only the pairs whose earlier scan is at a position below it (a worker's own scans).
    ``extra_pairs``: positions (a, b) to pair as well as the temporal neighbours (place_pairs).
    """
    a, b = temporal_pairs(indices, window)
    if extra_pairs is not None:
        extra = torch.as_tensor(np.stack(extra_pairs, 1), dtype=a.dtype, device=a.device)
        both = torch.cat([torch.stack([a, b], 1), extra])
        both = torch.unique(both, dim=0)
        a, b = both[:, 0], both[:, 1]
    if first_below is not None:
        keep = a < first_below
        a, b = a[keep], b[keep]
    if a.numel() == 0:
        return glob.new_zeros(())
    q = (None,) * 4 if queries is None else (queries[a], queries_valid[a], queries[b], queries_valid[b])
    n = (None, None) if normals is None else (normals[a], normals[b])
    return chamfer(glob[a], valid[a], glob[b], valid[b], *q, *n, truncate=truncate, x_id=a, y_id=b).mean()


def scan_normals(scans: np.ndarray, valid: np.ndarray, k: int = 16) -> np.ndarray:
    """Unit normals (K, N, D) of scans (K, N, D), 2D or 3D: each valid point's direction of least
    spread among its k nearest valid points of the same scan (PCA); 0 at invalid points."""
    normals = np.zeros_like(scans)
    for i in range(scans.shape[0]):
        keep = np.flatnonzero(valid[i])
        if keep.size < 3:
            continue
        normals[i, keep] = pca_normals(scans[i, keep], k)
    return normals


def odometry_factor(poses: torch.Tensor, prior: torch.Tensor, indices: torch.Tensor,
                    sigma_t: float, sigma_r_rad: float, first_below: int | None = None) -> torch.Tensor:
    """The odometry factor: each temporal neighbour pair (i, i+1) of the batch, the relative motion
    D = T_i^-1 T_{i+1} of ``poses`` (B, 4, 4) against that of ``prior`` (the warm start, D0):
    E = D0^-1 D, |t_E|^2 / sigma_t^2 + theta_E^2 / sigma_r^2 averaged over the pairs (theta^2 from
    |R_E - I|_F^2 / 2, smooth at 0); 0 when the batch has no pair. ``first_below`` as in chamfer_loss."""
    a, b = temporal_pairs(indices, 1)
    if first_below is not None:
        keep = a < first_below
        a, b = a[keep], b[keep]
    if a.numel() == 0:
        return poses.new_zeros(())
    err = relative(relative(prior[a], prior[b]), relative(poses[a], poses[b]))
    eye = torch.eye(3, dtype=poses.dtype, device=poses.device)
    trans = (err[:, :3, 3] ** 2).sum(-1) / sigma_t ** 2
    rot = ((err[:, :3, :3] - eye) ** 2).sum((-1, -2)) / 2.0 / sigma_r_rad ** 2
    return (trans + rot).mean()
