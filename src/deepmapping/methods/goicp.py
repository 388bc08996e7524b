"""Go-ICP in 2D: globally optimal pairwise registration by nested branch and bound, ICP inside.

Go-ICP (Yang, Li, Campbell & Jia, TPAMI 2016; the paper's baseline [49]) minimises the
(optionally trimmed) sum of squared closest-point distances E(R, t) over the whole domain
of rotations and translations. An outer branch and bound splits the rotations, an inner one
splits the translations; a cube's lower bound subtracts the uncertainty radii of the cube
(how far a point can move inside it) from each closest-point distance, its upper bound is E
at the cube's centre. Whenever the search finds a better pose, ICP refines it (the local
search that makes Go-ICP fast), and the better of the two becomes the current optimum. The
search stops when no cube can beat the optimum by more than ``mse_threshold`` per point
(epsilon-optimality), or when its time budget is spent (then the best pose so far).

This is the same algorithm on SE(2): rotations are one interval ``[-pi, pi]`` (uncertainty
radius ``2 |x| sin(delta / 2)`` for a half-width ``delta``), translations a square
(radius ``sqrt(2) sigma`` for a half-side ``sigma``); distances come from a distance
transform of the target (:class:`~deepmapping.geometry.distance_field.DistanceField2D`, its
discretisation error subtracted in the lower bounds), as in Go-ICP. Points are normalised
into the unit disc (Go-ICP normalises into ``[-1, 1]^3``), and its default search domain
(all rotations, translations in ``[-1, 1]^2``) and ``MSEThresh`` semantics are kept.

Why our own implementation: the PyPI package ``py-goicp`` (0.0.4, 2020, the authors' C++
wrapped with Cython) ships no wheel; its sdist only builds with pinned old build tools
(setuptools < 70 for pkg_resources, Cython < 3, autowrap < 0.23, no build isolation), it
is 3-D only (it would search all of SO(3) for planar scans), builds a 3-D distance
transform per pair (33 s at its default 300^3 cells on this machine) and prints to stdout
from C++. The 2-D search here is the same algorithm at a fraction of the cost.
"""

from __future__ import annotations

import heapq
import time

import numpy as np

from deepmapping.geometry import se2
from deepmapping.geometry.distance_field import DistanceField2D, clean_points_2d
from deepmapping.methods.icp import icp_2d

__all__ = ["goicp_2d", "incremental_goicp"]


def _exact_sse(pose, src, tgt, n_in: int) -> float:
    from scipy.spatial import cKDTree

    d, _ = cKDTree(tgt).query(se2.transform_points(pose, src))
    return float(np.sort(d * d)[:n_in].sum())


class _Search:
    """State of one Go-ICP search (normalised units)."""

    def __init__(self, xs, ys, trim_fraction, mse_threshold, translation_range, dt_size, batch, deadline):
        self.xs = xs
        self.norms = np.linalg.norm(xs, axis=1)
        self.n_in = max(1, xs.shape[0] - int(np.floor(trim_fraction * xs.shape[0])))
        self.eps = mse_threshold * self.n_in
        self.tau = translation_range
        self.field = DistanceField2D(ys, half_extent=1.0 + np.sqrt(2.0) * translation_range + 0.05, size=dt_size)
        self.batch = batch
        self.deadline = deadline
        self.nodes = 0
        self.timed_out = False

    def out_of_time(self) -> bool:
        if self.deadline is not None and time.perf_counter() > self.deadline:
            self.timed_out = True
        return self.timed_out

    def sse(self, e: np.ndarray) -> np.ndarray:
        """Trimmed sum of squares over the last axis: the n_in smallest of each row."""
        sq = e * e
        if self.n_in >= sq.shape[-1]:
            return sq.sum(-1)
        return np.partition(sq, self.n_in - 1, axis=-1)[..., : self.n_in].sum(-1)

    def error(self, pose) -> float:
        """E at a pose [tx, ty, theta] (normalised units)."""
        moved = se2.transform_points(np.asarray(pose, dtype=np.float64), self.xs)
        return float(self.sse(self.field.lookup(moved)))

    def inner(self, pts: np.ndarray, gamma_r: np.ndarray | None, cap: float,
              max_batches: int | None = None) -> tuple[float, np.ndarray | None]:
        """Translation branch and bound for rotated points ``pts``.

        gamma_r None: the best E over translations (an upper bound for this rotation);
        else the best of the relaxed error max(e - gamma_r - slack, 0) (a lower bound for the
        rotation interval). Only values below ``cap`` count; returns (value, translation).
        ``max_batches``: stop after that many expansions (the upper-bound search only).
        """
        slack = self.field.slack
        sub = (0.0 if gamma_r is None else gamma_r + slack)
        best, best_t = cap, None
        heap = [(0.0, 0, 0.0, 0.0, self.tau)]
        count = 1
        offsets = np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]], dtype=np.float64) * 0.5
        batches = 0
        while heap:
            if self.out_of_time() or (max_batches is not None and batches >= max_batches):
                break
            batches += 1
            parents = []
            while heap and len(parents) < self.batch:
                lb, _, cx, cy, half = heapq.heappop(heap)
                if lb >= best - self.eps:
                    heap = []
                    break
                parents.append((cx, cy, half))
            if not parents:
                break
            par = np.asarray(parents)
            centers = (par[:, None, :2] + offsets[None] * par[:, None, 2:3]).reshape(-1, 2)
            halves = np.repeat(par[:, 2] * 0.5, 4)
            self.nodes += centers.shape[0]
            e = self.field.lookup(pts[None, :, :] + centers[:, None, :])  # (C, N)
            ub = self.sse(np.maximum(e - sub, 0.0))
            lb = self.sse(np.maximum(e - sub - (0.0 if gamma_r is not None else slack)
                                     - np.sqrt(2.0) * halves[:, None], 0.0))
            i = int(np.argmin(ub))
            if ub[i] < best:
                best, best_t = float(ub[i]), centers[i].copy()
            for j in np.flatnonzero(lb < best):
                heapq.heappush(heap, (float(lb[j]), count, centers[j, 0], centers[j, 1], halves[j]))
                count += 1
        return best, best_t


def goicp_2d(
    source,
    target,
    *,
    trim_fraction: float = 0.0,
    mse_threshold: float = 1e-4,
    translation_range: float = 1.0,
    init=(0.0, 0.0, 0.0),
    dt_size: int = 1024,
    time_budget_s: float | None = None,
    icp_iterations: int = 50,
    initial_intervals: int = 8,
    batch: int = 32,
    ub_batches: int | None = 8,
) -> tuple[np.ndarray, dict]:
    """Register ``source`` (N, 2) onto ``target`` (M, 2) globally: returns (pose (3,), info).

    The pose T satisfies target ≈ T(source) (as :func:`deepmapping.methods.icp.icp_2d`).
    Both clouds are scaled by one factor so that every point lies in the unit disc; the
    search covers all rotations and translations in ``[-translation_range,
    translation_range]^2`` of those normalised units. ``trim_fraction``: share of the
    largest residuals left out of E (partial overlap). ``mse_threshold``: the optimality
    gap per point (normalised units squared). ``init``: ICP starts here first (Go-ICP starts
    from the identity). ``time_budget_s``: stop then with the best pose found (None = run to
    epsilon-optimality). info: optimal (gap closed), mse (of the returned pose, normalised
    units), nodes (translation cubes evaluated), icp_runs, time_s.

    ``ub_batches``: effort of the search for a better pose at a rotation (expansions of
    ``batch`` translation cubes; None = to optimality, as Go-ICP). ICP then starts from the
    best cube found when it beats the optimum or when the rotation interval cannot be
    pruned. Only the lower bounds prove optimality, so the cheaper upper-bound search keeps
    the guarantee; solving it exactly spent whole budgets on one wrong rotation.
    """
    t0 = time.perf_counter()
    src = clean_points_2d(source, "source")
    tgt = clean_points_2d(target, "target")
    scale = float(max(np.linalg.norm(src, axis=1).max(), np.linalg.norm(tgt, axis=1).max())) or 1.0
    deadline = None if time_budget_s is None else t0 + float(time_budget_s)
    s = _Search(src / scale, tgt / scale, trim_fraction, mse_threshold, translation_range, dt_size, batch, deadline)

    def normalise(pose):
        return np.array([pose[0] / scale, pose[1] / scale, pose[2]])

    icp_runs = 0

    def refine(pose_n: np.ndarray) -> tuple[float, np.ndarray]:
        nonlocal icp_runs
        icp_runs += 1
        start = np.array([pose_n[0] * scale, pose_n[1] * scale, pose_n[2]])
        pose, _ = icp_2d(src, tgt, init=start, method="point", max_iterations=icp_iterations)
        return s.error(normalise(pose)), normalise(pose)

    init_n = normalise(np.asarray(init, dtype=np.float64).reshape(3))
    opt, best = s.error(init_n), init_n
    e_icp, p_icp = refine(init_n)
    if e_icp < opt:
        opt, best = e_icp, p_icp

    def gamma(half: float) -> np.ndarray:
        return 2.0 * s.norms * np.sin(min(half / 2.0, np.pi / 2.0))

    heap: list = []
    count = 0

    def visit(theta: float, half: float) -> None:
        nonlocal opt, best, count
        pts = se2.transform_points(np.array([0.0, 0.0, theta]), s.xs)
        ub, t = s.inner(pts, None, np.inf if ub_batches is not None else opt, ub_batches)
        candidate = None if t is None else np.array([t[0], t[1], se2.wrap_angle(theta)])
        if candidate is not None and ub < opt:
            opt, best = ub, candidate
            e_r, p_r = refine(candidate)
            if e_r < opt:
                opt, best = e_r, p_r
            candidate = None
        lb, _ = s.inner(pts, gamma(half), opt)
        if lb < opt - s.eps:
            if candidate is not None:  # a rotation that may hold a better pose: ICP from its best cube
                e_r, p_r = refine(candidate)
                if e_r < opt:
                    opt, best = e_r, p_r
            if lb < opt - s.eps:
                heapq.heappush(heap, (lb, count, theta, half))
                count += 1

    width = 2.0 * np.pi / initial_intervals
    for k in range(initial_intervals):
        if s.out_of_time():
            break
        visit(-np.pi + (k + 0.5) * width, width / 2.0)
    while heap and not s.out_of_time():
        lb, _, theta, half = heapq.heappop(heap)
        if lb >= opt - s.eps:
            heap = []
            break
        for sign in (-1.0, 1.0):
            visit(theta + sign * half / 2.0, half / 2.0)
    # the distance transform's error can rank a cube's centre above the ICP pose next to it:
    # the final pose is the better, by exact closest-point distances, of the best and its ICP
    pose = np.array([best[0] * scale, best[1] * scale, se2.wrap_angle(best[2])])
    polished, _ = icp_2d(src, tgt, init=pose, method="point", max_iterations=icp_iterations)
    if _exact_sse(polished, src, tgt, s.n_in) <= _exact_sse(pose, src, tgt, s.n_in):
        pose = polished
    info = {"optimal": not s.timed_out, "mse": opt / s.n_in, "nodes": s.nodes, "icp_runs": icp_runs,
            "time_s": time.perf_counter() - t0}
    return pose, info


def incremental_goicp(points, valid, *, time_budget_s: float | None = None, progress=None,
                      **kwargs) -> tuple[np.ndarray, dict]:
    """Go-ICP of each scan onto its predecessor, relative motions chained (pose 0 = identity).

    points (K, N, 2), valid (K, N); ``time_budget_s`` is for the whole sequence, shared
    by the K - 1 pairs (time a pair leaves unused goes to the later ones); other keyword
    arguments go to :func:`goicp_2d`. Each pair starts its ICP from the previous relative
    motion (constant velocity, as incremental ICP).
    Returns (poses (K, 3), info: pairs solved to optimality, mean time per pair).
    """
    pts = np.asarray(points, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    k = pts.shape[0]
    rels = np.zeros((max(k - 1, 0), 3))
    prev = np.zeros(3)
    optimal, times = 0, []
    t0 = time.perf_counter()
    for i in range(1, k):
        budget = None
        if time_budget_s is not None:  # what earlier pairs left unused goes to the later ones
            budget = max(0.0, time_budget_s - (time.perf_counter() - t0)) / (k - i)
        rel, info = goicp_2d(pts[i][valid[i]], pts[i - 1][valid[i - 1]], init=prev, time_budget_s=budget, **kwargs)
        rels[i - 1] = prev = rel
        optimal += int(info["optimal"])
        times.append(info["time_s"])
        if progress is not None:
            progress(i, k)
    return se2.chain(rels), {"pairs_optimal": optimal, "pairs": max(k - 1, 0),
                             "mean_pair_s": float(np.mean(times)) if times else 0.0}
