"""Loop closures for long 2D sequences: incremental scan matching + pose-graph optimization.

DeepMapping alone does not close loops of metres (its loss basin is a fraction of a metre),
and its authors' follow-up, DeepMapping2 (CVPR 2023), brings in loop closures and pairwise
registrations. This is that ingredient, in the classic incremental form: keyframes are added
in order; each is matched by ICP to a submap of its ``sequential_submap`` predecessors
(point-to-line ICP by default, started from the odometry motion, which also acts as a prior
so that matches in featureless corridors do not slide) and to a local
submap around up to ``max_candidates`` earlier keyframes near its current estimate (at least
``min_gap`` keyframes back); a match is kept when at least ``min_overlap`` of the scan's
points fall within ``inlier_distance`` of the submap, the matched walls fix both directions of
the translation (``min_constraint``) and the match puts no more than ``max_free_conflict`` of
either visit's returns where the other's beams passed (the contradiction DeepMapping's loss
penalizes) and it moves the keyframe no further than drift along the pose graph between the
two allows (``max_drift``: repeated rooms); a kept closure is refined over the points both visits
see from the same side (``refine_closures``: not the two faces of one wall); each kept loop
closure that the poses do not already satisfy triggers a pose-graph optimization
(:mod:`deepmapping.methods.pose_graph_2d`, whose Cauchy kernel down-weights a wrong one that got
through), so drift is removed before the next keyframe looks for its neighbours. With
``recognize_places``, a keyframe that closed no loop also looks for its place among all earlier
keyframes, wherever the estimate puts them (``_recognize``: a descriptor, a match at any heading, a
bound on the turn it asks for, and three neighbouring keyframes that agree). Lengths follow
the scans' ranges (``scale``, :func:`data_scale`). The result warm-starts DeepMapping.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from deepmapping.geometry import se2
from deepmapping.geometry.distance_field import DistanceField2D
from deepmapping.geometry.normals import pca_normals
from deepmapping.methods.icp import icp_2d
from deepmapping.methods.pose_graph_2d import Edge, optimize_pose_graph

__all__ = ["close_loops", "correlative_search", "data_scale", "global_match", "place_descriptor"]

# the median return range the lengths of close_loops are given for (metres: the indoor CARMEN logs
# intel, fr079 and mit-csail, 1.96-2.08 m)
REFERENCE_RANGE = 2.0
# point-to-line residuals' standard deviation against the odometry prior (metres, at scale 1)
POINT_SIGMA = 0.03
# with odometry, a sequential match further from it than ODOMETRY_GATE of its standard deviations
# (odometry_sigma) is kept only where it puts FAR_MARGIN more of the scan on the submap than the
# best match nearer the odometry (a wheel slip: the near ones do not fit)
ODOMETRY_GATE = 6.0
FAR_MARGIN = 0.15
# a sequential match fits when it puts this much of the scan on the submap; where none does, the
# odometry motion itself is a candidate too, and so is the best pose of a correlative search within
# SEARCH_DEGREES and SEARCH_SHIFT x radius of it where that fits FAR_MARGIN better than the odometry
# (on simulated odometry, ICP from turns 12-34 deg off converged nowhere)
FITS = 0.5
SEARCH_DEGREES = 45.0
SEARCH_SHIFT = 0.125
# where the sequential matches fit but disagree with each other by more than AGREE_DEGREES (or three
# inlier distances), the search runs too, and its pose joins them where it fits CLEAR_MARGIN better
# than the best of them (simulated odometry: ICP from a turn 28 deg off matched 4.4 m away at 0.51,
# the true motion fits 0.79; a corridor slid 1.4 m at 0.58 against 0.72)
AGREE_DEGREES = 3.0
CLEAR_MARGIN = 0.05
# place recognition (``recognize_places``): a keyframe that closed no loop near its estimate is
# compared, by a descriptor of its recent scans (histograms of return ranges and of distances between
# returns, both blind to heading), with every earlier keyframe; the RECOGNIZE_CANDIDATES most alike
# are matched wherever they are (a correlative search over every heading and RECOGNIZE_SHIFT x radius,
# then ICP), and a match that passes the closures' tests waits until RECOGNIZE_CONFIRM of them, from
# keyframes at most RECOGNIZE_WINDOW apart, say the same thing of where the old place is
RECOGNIZE_CANDIDATES = 2
RECOGNIZE_SHIFT = 0.25
RECOGNIZE_CONFIRM = 3
RECOGNIZE_WINDOW = 10
RECOGNIZE_EVERY = 2  # keyframes: a revisit lasts several; matching every other one halves the time
# ... and where it turns the keyframe by no more than RECOGNIZE_TURN_DRIFT of the least turning of any
# path between the two through the pose graph, plus RECOGNIZE_MIN_TURN deg: heading drifts with
# turning (simulated odometry: 23 deg lost over turns in place of 360 deg in all), while a look-alike
# place elsewhere (a square ring's other side) needs the turn between the two places
RECOGNIZE_TURN_DRIFT = 0.15
RECOGNIZE_MIN_TURN = 5.0
# ... and where the map they bend contradicts itself no more than before: of the pairs of keyframes
# near each other (within the closures' radius, at least min_gap apart) with one among those it moves
# (at most ADOPT_SAMPLE of them, evenly), the pairs whose scans see each other's returns in free space
# (both ways, over max_free_conflict) may grow by ADOPT_NEW_CONFLICTS of the pairs after, no more
# (simulated odometry: the true places took such pairs from 15 % to 8 %; a real campus folded by a
# look-alike group, 245 m away in the estimate, from 13 % to 21 %: 511 -> 1182 pairs)
ADOPT_SAMPLE = 150
ADOPT_NEW_CONFLICTS = 0.05
RANGE_BINS = np.linspace(0.0, 6.0, 25)  # at scale 1 (metres)
PAIR_BINS = np.linspace(0.0, 8.0, 33)


def data_scale(points, valid) -> float:
    """How much larger than the indoor logs' the scans' ranges are: their median return range over
    ``REFERENCE_RANGE`` (``loop.scale`` "auto"; points (K, N, 2), valid (K, N))."""
    ranges = np.hypot(*np.asarray(points)[np.asarray(valid, dtype=bool)].T)
    return float(np.median(ranges)) / REFERENCE_RANGE if len(ranges) else 1.0


def keyframe_submap(points, valid, poses, center, half_width, origins=False):
    """Keyframes center-half_width..center+half_width merged into keyframe ``center``'s frame (and,
    with ``origins``, the position in that frame of the sensor that saw each point)."""
    lo, hi = max(center - half_width, 0), min(center + half_width + 1, len(points))
    rel = {m: se2.relative(poses[center], poses[m]) for m in range(lo, hi)}
    merged = np.concatenate([se2.transform_points(rel[m], points[m][valid[m]]) for m in rel])
    if not origins:
        return merged
    return merged, np.concatenate([np.repeat(rel[m][None, :2], np.count_nonzero(valid[m]), axis=0) for m in rel])


def _overlap(src, tgt_tree, pose, distance):
    d, _ = tgt_tree.query(se2.transform_points(pose, src), distance_upper_bound=distance)
    return float(np.isfinite(d).mean())


def close_loops(points, valid, init_poses, *, min_gap: int = 30, radius: float = 4.0, max_candidates: int = 3,
                min_overlap: float = 0.7, inlier_distance: float = 0.1, submap_half_width: int = 2,
                sequential_submap: int = 5, sequential_method: str = "plane",
                odometry_sigma: tuple[float, float] | None = (0.1, 5.0), min_constraint: float = 0.2,
                max_free_conflict: float = 0.05, max_drift: float = 0.2, refine_closures: bool = True,
                constant_velocity: bool = False, recognize_places: bool = False, scale: float = 1.0,
                edge_sigma: float = 0.05, progress: Callable[[int, int], None] | None = None) -> tuple[np.ndarray, list[Edge]]:
    """Poses (K, 3) after loop closing, and the pose-graph edges (sequential and loop closures).

    points (K, N, 2) and valid (K, N) in metres; init_poses (K, 3): odometry (or any guess),
    whose relative motions start the sequential matches; ``odometry_sigma`` = (metres, degrees):
    with point-to-line matching, the odometry motion is also a measurement with these standard
    deviations, so a match cannot slide along a featureless corridor (None: ICP alone).
    ``min_constraint``: a loop closure is kept only where the matched geometry fixes both
    directions of the translation (see ``_constraint``); corridors alias along themselves.
    ``max_free_conflict``: ... and where it contradicts the free space seen (``_closure_conflict``;
    1 = no such test). ``max_drift``: a loop closure may move the keyframe by at most this fraction
    of the shortest path between the two keyframes through the pose graph (at least 3 x
    ``inlier_distance``, at most ``radius``): a place that looks like another (a repeated room)
    matches as well as the true one, but further from where the graph puts the keyframe than
    drift along that path can explain. ``refine_closures``: each kept closure is refined by
    point-to-line ICP within ``inlier_distance`` over the pairs whose sensors see the surface from
    the same side (a wall seen from both rooms pulls a match by its thickness towards its other
    face). ``constant_velocity`` (scans without odometry): each sequential match starts from the
    previous keyframe's motion instead of ``init_poses``' motions, and ``odometry_sigma`` holds it there (none
    for the second keyframe); a straight corridor then keeps the robot's pace, where from the identity
    the match slides (the paper's simulated trajectories: 7 of 75 over 1 px from the truth, 5 with it;
    but a 4096-scan one 2.15 -> 9.98 px: off by default, ``loop.constant_velocity``).
    ``recognize_places``: a keyframe that closed no loop also looks for the place among all earlier
    keyframes, however far the estimate puts them (drift of metres after turns in place), see
    ``_recognize``; such closures are kept only where RECOGNIZE_CONFIRM neighbouring keyframes agree.
    ``scale`` multiplies every length (``radius``, ``inlier_distance``, the odometry's
    metres, ``edge_sigma``, the pose graph's translation standard deviation, and the point-to-line
    sigma against the odometry prior), for scans whose ranges are not those of the indoor logs the
    defaults were tuned on (``data_scale``).
    """
    radius, inlier_distance, edge_sigma = radius * scale, inlier_distance * scale, edge_sigma * scale
    if odometry_sigma is not None:
        odometry_sigma = (odometry_sigma[0] * scale, odometry_sigma[1])
    pts = np.asarray(points, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    init = np.asarray(init_poses, dtype=np.float64)
    k = len(pts)
    poses = init[:1].copy()
    edges: list[Edge] = []
    rel = None  # the last sequential match
    descriptors, pending = [], []  # place recognition: each keyframe's descriptor, unconfirmed matches
    for n in range(1, k):
        guess, prior = se2.relative(init[n - 1], init[n]), odometry_sigma
        if constant_velocity:
            guess, prior = (rel, prior) if rel is not None else (np.zeros(3), None)
        rel = _sequential(pts, valid, poses, n, guess, sequential_submap, sequential_method, prior,
                          radius, inlier_distance, POINT_SIGMA * scale)
        edges.append(Edge(n - 1, n, rel, sigma_t=edge_sigma))
        poses = np.vstack([poses, se2.compose(poses[-1], rel)])
        candidates = _candidates(poses, n, min_gap, radius, max_candidates)
        # most keyframes have no candidate: no need to list the held edges for them
        path = _graph_distances(_held(edges, poses, 3 * inlier_distance), n, candidates, radius / max_drift) \
            if candidates else {}
        closing = [_match(pts, valid, poses, j, n, submap_half_width,
                          min(radius, max(3 * inlier_distance, max_drift * path[j])), min_overlap, inlier_distance,
                          min_constraint, max_free_conflict, edge_sigma, radius, refine_closures)
                   for j in candidates]
        closing = [e for e in closing if e is not None]
        edges += closing
        if any(_disagrees(poses, e, inlier_distance / 2) for e in closing):
            poses = optimize_pose_graph(poses, edges)
        if recognize_places:
            if n == 1:
                descriptors.append(place_descriptor(_recent(pts, valid, poses, 0, sequential_submap), scale))
            descriptors.append(place_descriptor(_recent(pts, valid, poses, n, sequential_submap), scale))
            if not closing and n >= min_gap and n % RECOGNIZE_EVERY == 0:
                confirmed = _recognize(pts, valid, poses, edges, n, descriptors, pending, min_gap, submap_half_width,
                                       min_overlap, inlier_distance, min_constraint, max_free_conflict, edge_sigma,
                                       radius)
                if confirmed:
                    poses, edges = _adopt(pts, valid, poses, edges, confirmed, inlier_distance, min_gap, radius,
                                          max_free_conflict)
        if progress is not None:
            progress(n, k - 1)
    return optimize_pose_graph(poses, edges), edges


def _graph_distances(edges, n, targets, limit, turns=False) -> dict:
    """The length of the shortest path from keyframe n to each of ``targets`` through the pose graph
    (edge length = its translation; a loop closure is a short cut), at most ``limit``: how far
    drift can have carried n from each of them. With ``turns``, an edge's length is its rotation
    (radians): how far heading drift can have turned n."""
    if not targets:
        return {}
    ij = np.array([(e.i, e.j) for e in edges])
    z = np.array([e.z for e in edges])
    w = np.maximum(np.abs(se2.wrap_angle(z[:, 2])) if turns else np.hypot(z[:, 0], z[:, 1]), 1e-12)  # 0: no edge
    graph = coo_matrix((w, (ij[:, 0], ij[:, 1])), shape=(n + 1, n + 1)).tocsr()
    dist = dijkstra(graph, directed=False, indices=n, limit=limit)
    return {j: float(min(dist[j], limit)) for j in targets}


def _held(edges, poses, distance) -> list:
    """The sequential edges and the loop closures the poses satisfy within ``distance`` (translation):
    a wrong closure the pose graph's kernel overrules is no short cut for drift."""
    return [e for e, k in zip(edges, _satisfied(edges, poses, distance)) if k]


def _satisfied(edges, poses, distance) -> np.ndarray:
    """Per edge: a sequential edge, or a loop closure the poses satisfy within ``distance`` (translation)."""
    if not edges:
        return np.zeros(0, dtype=bool)
    ij = np.array([(e.i, e.j) for e in edges])
    z = np.array([e.z[:2] for e in edges])
    r = se2.relative(poses[ij[:, 0]], poses[ij[:, 1]])[:, :2] - z
    return (ij[:, 1] - ij[:, 0] == 1) | (np.hypot(r[:, 0], r[:, 1]) <= distance)


def _disagrees(poses, edge, distance) -> bool:
    """A loop closure the current poses do not already satisfy (by more than ``distance``, or 1
    degree): only then is the pose graph optimized again before the next keyframe (a trajectory
    that keeps revisiting places closes thousands of loops, most of them already in place; the
    last optimization takes every edge)."""
    r = se2.relative(poses[edge.i], poses[edge.j]) - edge.z
    return bool(np.hypot(r[0], r[1]) > distance or abs(se2.wrap_angle(r[2])) > np.radians(1.0))


def place_descriptor(points, scale) -> np.ndarray:
    """A keyframe's place as heading-blind histograms (each summing to 1): of its returns' ranges and
    of the distances between returns (a subsample of 200), ``points`` (N, 2) in the keyframe's frame,
    lengths over ``scale``. Two visits of a place from about the same spot have alike histograms
    wherever drift has put them."""
    r = np.hypot(*points.T) / scale
    sub = points[:: max(len(points) // 200, 1)] / scale
    d = np.hypot(*(sub[:, None] - sub[None]).reshape(-1, 2).T)
    h = [np.histogram(r, RANGE_BINS)[0], np.histogram(d[d > 0], PAIR_BINS)[0]]
    return np.concatenate([x / max(x.sum(), 1) for x in h])


def _recognize(pts, valid, poses, edges, n, descriptors, pending, min_gap, half_width, min_overlap, inlier_distance,
               min_constraint, max_free_conflict, edge_sigma, radius) -> list:
    """Loop closures for keyframe n from place recognition: the RECOGNIZE_CANDIDATES earlier keyframes
    (at least ``min_gap`` back) whose descriptors are nearest n's are matched globally
    (``global_match``) and tested as any closure (overlap, constraint, free space) and for the turn it
    asks of the keyframe (``_turn_allowed``); a match that passes
    joins ``pending`` and is returned, with those that confirm it, once RECOGNIZE_CONFIRM matches of
    keyframes within RECOGNIZE_WINDOW of each other agree on where the old place lies (a single look-alike
    room is not enough: on simulated odometry, a corridor matched 180 deg about at 0.75-0.83 overlap)."""
    old = np.arange(n - min_gap + 1)
    desc = np.asarray(descriptors)
    nearest = old[np.argsort(np.abs(desc[old] - desc[n]).sum(axis=1), kind="stable")[:RECOGNIZE_CANDIDATES]]
    pending[:] = [e for e in pending if n - e.j <= RECOGNIZE_WINDOW]
    src = pts[n][valid[n]]
    for j in nearest:
        target, origins = keyframe_submap(pts, valid, poses, int(j), half_width, origins=True)
        rel = _verified(pts, valid, poses, int(j), n, src, target, origins,
                        global_match(src, target, RECOGNIZE_SHIFT * radius, inlier_distance), half_width,
                        min_overlap, inlier_distance, min_constraint, max_free_conflict, refine=True)
        if rel is None or not _turn_allowed(poses, edges, int(j), n, rel, inlier_distance):
            continue
        edge = Edge(int(j), n, rel, sigma_t=edge_sigma)
        agree = [e for e in pending if _same_place(poses, e, edge, 3 * inlier_distance)]
        if len({e.j for e in agree} | {n}) >= RECOGNIZE_CONFIRM:  # from as many keyframes
            pending[:] = [e for e in pending if e not in agree]
            return agree + [edge]
        pending.append(edge)
    return []


def _adopt(pts, valid, poses, edges, confirmed, inlier_distance, min_gap, radius, max_free_conflict):
    """(poses, edges) with the ``confirmed`` place-recognition closures, or as they were where the map
    cannot take them: a recognized place can be metres from where the graph had it, so the graph is
    solved by least squares first, over the edges the poses hold (within 3 x ``inlier_distance``) and the new ones (the
    robust kernel would hardly feel so large a residual, and an overruled closure should not pull), then
    over every edge with the kernel; the closures are kept only where the poses then satisfy them and
    every loop closure they satisfied before (a look-alike place that fooled the other tests bends the
    map against the loops already closed), and where the part of the map they move contradicts the rest
    no more than it did (``_map_conflicts``; a bent part that carries no closure to break still folds
    walls into corridors)."""
    distance = 3 * inlier_distance
    before = _satisfied(edges, poses, distance)
    held = [e for e, k in zip(edges, before) if k] + confirmed
    trial = optimize_pose_graph(optimize_pose_graph(poses, held, robust_scale=1e6), edges + confirmed)
    after = _satisfied(edges + confirmed, trial, distance)
    if not after[len(edges):].all() or (before & ~after[: len(edges)]).any():
        return poses, edges
    moved = np.flatnonzero(np.hypot(*(trial[:, :2] - poses[:, :2]).T) > distance)
    moved = moved[np.linspace(0, len(moved) - 1, min(len(moved), ADOPT_SAMPLE)).astype(int)] if len(moved) else moved
    was, _ = _map_conflicts(pts, valid, poses, moved, min_gap, radius, 2 * inlier_distance, max_free_conflict)
    now, pairs = _map_conflicts(pts, valid, trial, moved, min_gap, radius, 2 * inlier_distance, max_free_conflict)
    if now > was + ADOPT_NEW_CONFLICTS * pairs:
        return poses, edges
    return trial, edges + confirmed


def _map_conflicts(pts, valid, poses, keyframes, min_gap, radius, margin, max_free_conflict) -> tuple[int, int]:
    """How many pairs of a keyframe in ``keyframes`` and another within ``radius`` of it (at least
    ``min_gap`` apart in time) see each other's returns in their free space (both ways, over
    ``max_free_conflict``; ``free_space_conflict`` with ``margin``), and how many such pairs there are:
    how much the map contradicts itself where ``keyframes`` lie."""
    tree, chosen = cKDTree(poses[:, :2]), set(int(m) for m in keyframes)
    conflicts = pairs = 0
    for m in sorted(chosen):
        for q in tree.query_ball_point(poses[m, :2], radius):
            if abs(q - m) < min_gap or (q in chosen and q < m):  # each pair once
                continue
            seen = [free_space_conflict(pts[a][valid[a]], se2.transform_points(se2.relative(poses[a], poses[b]),
                                                                                pts[b][valid[b]]), margin)
                    for a, b in ((m, q), (q, m))]
            pairs += 1
            conflicts += min(seen) > max_free_conflict
    return conflicts, pairs


def _turn_allowed(poses, edges, j, n, rel, inlier_distance) -> bool:
    """Whether a recognized place (keyframe n at ``rel`` from j) turns n by no more than heading drift
    can explain: RECOGNIZE_TURN_DRIFT of the least total turn of a path from j to n through the pose
    graph's held edges, plus RECOGNIZE_MIN_TURN degrees."""
    turn = abs(se2.wrap_angle(se2.relative(poses[n], se2.compose(poses[j], rel))[2]))
    path = _graph_distances(_held(edges, poses, 3 * inlier_distance), n, [j], 2 * np.pi * len(poses), turns=True)[j]
    return bool(turn <= RECOGNIZE_TURN_DRIFT * path + np.radians(RECOGNIZE_MIN_TURN))


def _same_place(poses, a, b, distance) -> bool:
    """Whether two place-recognition closures (old keyframe i, new keyframe j) agree: keyframe b.j seen
    from a.j through the new keyframes' own poses and through the old place (a.z, the old keyframes'
    poses, b.z) is the same within ``distance`` and 2 deg, and the two old keyframes are near in time."""
    if abs(a.i - b.i) > 2 * RECOGNIZE_WINDOW:
        return False
    direct = se2.relative(poses[a.j], poses[b.j])
    via = se2.compose(se2.compose(se2.inverse(a.z), se2.relative(poses[a.i], poses[b.i])), b.z)
    r = direct - via
    return bool(np.hypot(r[0], r[1]) <= distance and abs(se2.wrap_angle(r[2])) <= np.radians(2.0))


def global_match(src, target, shift, inlier_distance) -> np.ndarray:
    """The pose of ``src`` on ``target`` (both (N, 2)) at any heading and within ``shift`` of the
    target's origin: a coarse correlative search (4-degree steps, three inlier distances, at most 60
    points), a fine one around its best (1 degree, one inlier distance), then point-to-point ICP."""
    coarse = _coarse_search(src[:: max(len(src) // 60, 1)], target, shift, 3 * inlier_distance, 4.0)
    fine = correlative_search(src, target, coarse, 4.0, 3 * inlier_distance, inlier_distance)
    return icp_2d(src, target, init=fine, method="point", max_correspondence_distance=3 * inlier_distance,
                  trim=None)[0]


def _coarse_search(src, target, shift, tolerance, step_degrees) -> np.ndarray:
    """``correlative_search`` about the origin at every heading, cheaper: the shifts are whole cells of
    the target's grid (``tolerance`` / 2), so each heading's points are put in cells once and every
    shift is an integer offset of those cells into a mask of the cells within ``tolerance`` of the
    target (outside the grid: none)."""
    cell = tolerance / 2
    lo = target.min(axis=0) - tolerance
    size = int(np.ceil(np.max(target.max(axis=0) + tolerance - lo) / cell)) + 1
    field = DistanceField2D(target, half_extent=size * cell / 2, size=size, center=lo + size * cell / 2)
    reach = int(np.floor(shift / cell + 1e-9))
    pad = reach + 1
    mask = np.zeros((size + 2 * pad, size + 2 * pad), dtype=bool)
    mask[pad:-pad, pad:-pad] = field.grid <= np.float64(tolerance * (1 + 1e-6))
    steps = np.arange(-reach, reach + 1)
    offsets = np.stack(np.meshgrid(steps, steps, indexing="ij"), axis=-1).reshape(-1, 1, 2)
    best, pose = -1.0, np.zeros(3)
    for angle in np.radians(np.arange(-180.0, 180.0, step_degrees)):
        cells = np.floor((se2.transform_points(np.array([0.0, 0.0, angle]), src) - lo) / cell).astype(np.int64)
        cells = np.clip(cells, -pad, size + pad - 1) + pad  # outside the grid: in the empty border or beyond
        idx = np.clip(cells + offsets, 0, size + 2 * pad - 1)
        score = mask[idx[..., 1], idx[..., 0]].mean(axis=1)
        k = int(np.argmax(score))
        if score[k] > best:
            best, pose = float(score[k]), np.array([*(offsets[k, 0] * cell), angle])
    return pose


def _sequential(pts, valid, poses, n, guess, submap, method, odometry_sigma, radius, inlier_distance, point_sigma):
    """The motion from keyframe n-1 to n, one of these matches started from the odometry ``guess``:
    (1) point-to-line against the submap of recent keyframes, with the odometry prior;
    (2) point-to-point against the previous scan alone; (3) coarse-to-fine point-to-point against
    the submap (recovers odometry jumps of a metre, e.g. wheel slip); with odometry, where none of
    these puts ``FITS`` of the scan on the submap, also (4) the odometry motion as it is (a scan
    that fits nowhere, e.g. a person in front of the laser) and (5) the best pose of a correlative
    search around it (``correlative_search``: a turn whose odometry is tens of degrees off), as it is
    and refined by ICP, where one of them fits ``FAR_MARGIN`` better than the odometry; where the
    matches fit but disagree with each other (``_disagree_with_each_other``), the search runs too and
    its pose joins them where it also fits ``CLEAR_MARGIN`` better than the best of them.
    The one that puts most of the scan within ``inlier_distance`` of the submap wins, with the
    odometry's say in ``_pick``. Without odometry (``odometry_sigma`` None) the one nearest the
    submap wins instead (``_fit_error``): a match that slides a little along a wall puts as much of
    the scan within ``inlier_distance`` as the right one, and the count cannot tell them apart."""
    src = pts[n][valid[n]]
    target = _recent(pts, valid, poses, n - 1, submap)
    prior = None
    if odometry_sigma is not None and method == "plane":
        prior = (odometry_sigma[0], np.radians(odometry_sigma[1]))
    first, _ = icp_2d(src, target, init=guess, method=method, prior_sigma=prior, point_sigma=point_sigma)
    hypotheses = [first, icp_2d(src, pts[n - 1][valid[n - 1]], init=guess, method="point")[0]]
    coarse, _ = icp_2d(src, target, init=guess, method="point", max_correspondence_distance=radius / 4, trim=None)
    hypotheses.append(icp_2d(src, target, init=coarse, method=method, prior_sigma=None)[0])
    tree = cKDTree(target)
    if odometry_sigma is None:
        normals = pca_normals(target, 6, tree)
        return hypotheses[int(np.argmin([_fit_error(src, tree, normals, h, inlier_distance) for h in hypotheses]))]
    scores = [_overlap(src, tree, h, inlier_distance) for h in hypotheses]
    fits = max(scores) >= FITS
    if not fits or _disagree_with_each_other(hypotheses, inlier_distance):
        odometry_score = _overlap(src, tree, guess, inlier_distance)
        # the best of thousands of poses fits a little better than the odometry even for random points
        # (by 0.02-0.06); the turns the search is for fit 0.27-0.46 better
        bar = odometry_score + FAR_MARGIN
        if fits:
            bar = max(bar, max(scores) + CLEAR_MARGIN)
        else:  # (4): the odometry motion as it is
            hypotheses.append(np.asarray(guess, dtype=np.float64).copy())
            scores.append(odometry_score)
        searched = correlative_search(src, target, guess, SEARCH_DEGREES, SEARCH_SHIFT * radius, inlier_distance)
        found = [searched, icp_2d(src, target, init=searched, method=method)[0]]
        found_scores = [_overlap(src, tree, h, inlier_distance) for h in found]
        if max(found_scores) >= bar:
            hypotheses, scores = hypotheses + found, scores + found_scores
    return _pick(hypotheses, np.array(scores), guess, odometry_sigma)


def _fit_error(src, tree, normals, pose, distance) -> float:
    """The mean squared point-to-line distance from ``src`` at ``pose`` to the submap in ``tree``
    (``normals``: the submap's), each point's capped at ``distance`` (and ``distance`` where its
    nearest submap point is further): a truncated least-squares cost that, unlike ``_overlap``'s
    count, still sees how far within ``distance`` the points lie, and, measured along the normals,
    does not prefer the pose that lays each point on an earlier scan's samples of the same wall."""
    moved = se2.transform_points(pose, src)
    d, j = tree.query(moved, distance_upper_bound=distance)
    ok = np.isfinite(d)
    err = np.full(len(moved), distance)
    err[ok] = np.minimum(np.abs(((moved[ok] - tree.data[j[ok]]) * normals[j[ok]]).sum(axis=1)), distance)
    return float((err ** 2).mean())


def _disagree_with_each_other(hypotheses, inlier_distance) -> bool:
    """Whether two of the sequential matches are more than ``AGREE_DEGREES`` or three inlier distances
    apart: ICP started from the same odometry converged to different poses, so the scan matches more
    than one way and the basin ICP fell into is no evidence."""
    h = np.asarray(hypotheses)
    i, j = np.triu_indices(len(h), 1)
    turn = np.abs(se2.wrap_angle(h[i, 2] - h[j, 2]))
    shift = np.hypot(*(h[i, :2] - h[j, :2]).T)
    return bool(np.any((turn > np.radians(AGREE_DEGREES)) | (shift > 3 * inlier_distance)))


def correlative_search(src, target, center, degrees, shift, inlier_distance, step_degrees=1.0) -> np.ndarray:
    """The pose within ``degrees`` (``step_degrees`` steps) and ``shift`` (steps of ``inlier_distance`` / 2)
    of ``center`` that puts the most of ``src`` within ``inlier_distance`` of ``target``, both (N, 2):
    a correlative scan matcher (Olson 2009) over a grid of the target, for a scan whose ICP matches,
    started from the odometry, fit nowhere (a turn in place whose odometry is 30 deg off)."""
    cell = inlier_distance / 2
    lo = target.min(axis=0) - inlier_distance
    size = int(np.ceil(np.max(target.max(axis=0) + inlier_distance - lo) / cell)) + 1
    field = DistanceField2D(target, half_extent=size * cell / 2, size=size, center=lo + size * cell / 2)
    # the field's distances are multiples of sqrt(integer) cells, stored as float32: a tolerance far
    # below one cell keeps a point exactly inlier_distance away within it
    within = inlier_distance * (1 + 1e-6)
    steps = np.arange(-shift, shift + 1e-9, cell)
    shifts = np.stack(np.meshgrid(steps, steps, indexing="ij"), axis=-1).reshape(-1, 1, 2)
    best, pose = -1.0, np.asarray(center, dtype=np.float64).copy()
    for angle in center[2] + np.radians(np.arange(-degrees, degrees + 1e-9, step_degrees)):
        moved = se2.transform_points(np.array([*center[:2], angle]), src)
        score = field.within(moved + shifts, within).mean(axis=1)
        k = int(np.argmax(score))
        if score[k] > best:
            best, pose = float(score[k]), np.array([*(center[:2] + shifts[k, 0]), angle])
    return pose


def _pick(hypotheses, scores, guess, odometry_sigma):
    """The sequential match to keep: the one that puts most of the scan on the submap (``scores``);
    with odometry, one further than ``ODOMETRY_GATE`` standard deviations from the odometry
    ``guess`` only where it beats the best match nearer the odometry by ``FAR_MARGIN`` (a wheel
    slip: the near ones do not fit; where ``_sequential`` adds it, the odometry is a near one).
    Where none is near, of the matches within ``FAR_MARGIN`` of the best overlap the one fewest
    standard deviations from the odometry wins (a turn in place whose odometry is 36 deg off, matched
    to 0.3 deg with 0.60 overlap, against a match 2.7 m away with 0.63).
    Measured on logs with simulated odometry (docs/logs.md): the most overlap alone had taken a
    symmetric room matched 53 deg from the odometry (0.81 against 0.68 for the right match), or a
    3.4 m / 55 deg jump on a scan that fit nowhere (0.16 against 0.12), and the loops behind them
    never closed."""
    best = int(np.argmax(scores))  # ties: the first
    if odometry_sigma is None:
        return hypotheses[best]
    departure = np.array([(np.hypot(*(h[:2] - guess[:2])) / odometry_sigma[0],
                           abs(se2.wrap_angle(h[2] - guess[2])) / np.radians(odometry_sigma[1])) for h in hypotheses])
    near = np.flatnonzero((departure <= ODOMETRY_GATE).all(axis=1))
    if near.size and scores[best] - scores[near].max() < FAR_MARGIN:
        return hypotheses[int(near[np.argmax(scores[near])])]
    if not near.size:  # of those that fit about as well as the best, the one the odometry explains best
        close = np.flatnonzero(scores >= scores[best] - FAR_MARGIN)
        return hypotheses[int(close[np.argmin(departure[close].max(axis=1))])]
    return hypotheses[best]


def _recent(points, valid, poses, last, count):
    """The ``count`` keyframes up to ``last`` merged in ``last``'s frame (the scan-to-submap target)."""
    parts = [se2.transform_points(se2.relative(poses[last], poses[m]), points[m][valid[m]])
             for m in range(max(last - count + 1, 0), last + 1)]
    return np.concatenate(parts)


def _candidates(poses, n, min_gap, radius, max_candidates):
    if n < min_gap or max_candidates == 0:
        return []
    old = poses[: n - min_gap + 1]
    d = np.hypot(*(old[:, :2] - poses[n, :2]).T)
    order = np.argsort(d)
    picked: list[int] = []
    for j in order[d[order] < radius]:
        if all(abs(j - p) > 2 * min_gap // 3 for p in picked):  # from different visits
            picked.append(int(j))
        if len(picked) == max_candidates:
            break
    return picked


def _match(pts, valid, poses, j, n, half_width, max_shift, min_overlap, inlier_distance, min_constraint,
           max_free_conflict, edge_sigma, radius, refine=False):
    target, origins = keyframe_submap(pts, valid, poses, j, half_width, origins=True)
    src = pts[n][valid[n]]
    guess = se2.relative(poses[j], poses[n])
    coarse, _ = icp_2d(src, target, init=guess, method="point", max_correspondence_distance=radius / 2, trim=None)
    rel, _ = icp_2d(src, target, init=coarse, method="point", max_correspondence_distance=3 * inlier_distance,
                    trim=None)
    if np.hypot(*(rel[:2] - guess[:2])) > max_shift:  # further than the drift between the two allows
        return None
    rel = _verified(pts, valid, poses, j, n, src, target, origins, rel, half_width, min_overlap, inlier_distance,
                    min_constraint, max_free_conflict, refine)
    return None if rel is None else Edge(j, n, rel, sigma_t=edge_sigma)


def _verified(pts, valid, poses, j, n, src, target, origins, rel, half_width, min_overlap, inlier_distance,
              min_constraint, max_free_conflict, refine):
    """A loop closure's pose (keyframe n at ``rel`` from j; ``target``, ``origins``: j's submap) after the
    tests every closure passes (overlap, constraint, free space), refined where ``refine``; None where
    one fails."""
    tree = cKDTree(target)
    if _overlap(src, tree, rel, inlier_distance) < min_overlap:
        return None
    if _constraint(src, target, tree, rel, inlier_distance) < min_constraint:
        return None
    if max_free_conflict < 1 and _closure_conflict(pts, valid, poses, j, n, rel, half_width,
                                                   2 * inlier_distance) > max_free_conflict:
        return None
    if refine:  # the two faces of a wall are not each other: pairs seen from the same side only
        rel, _ = icp_2d(src, target, init=rel, method="plane", max_correspondence_distance=inlier_distance, trim=None,
                        target_origins=origins)
    return rel


def free_space_conflict(scan, hits, margin) -> float:
    """The fraction of ``hits`` (M, 2, in the sensor frame of ``scan``) that lie in the free space
    ``scan`` (N, 2, its valid returns) observed: nearer the sensor, by more than ``margin``, than
    the nearest return in bearing and both its neighbours (so that walls seen at a grazing angle
    do not count). This is the contradiction DeepMapping's loss (eq. 4) penalizes, a point labelled
    occupied where a beam passed, tested on the beams themselves instead of a trained M-Net."""
    if len(hits) == 0 or len(scan) < 3:
        return 0.0
    bearing = np.arctan2(scan[:, 1], scan[:, 0])
    order = np.argsort(bearing)
    bearing, rng = bearing[order], np.hypot(*scan[order].T)
    step = float(np.median(np.diff(bearing)))
    near = np.minimum(np.minimum(rng, np.roll(rng, 1)), np.roll(rng, -1))
    b = np.arctan2(hits[:, 1], hits[:, 0])
    i = np.clip(np.searchsorted(bearing, b), 1, len(bearing) - 1)
    i = np.where(np.abs(b - bearing[i - 1]) < np.abs(b - bearing[i]), i - 1, i)
    inside = np.abs(b - bearing[i]) <= step
    return float(np.mean(inside & (np.hypot(*hits.T) < near[i] - margin)))


def _closure_conflict(pts, valid, poses, j, n, rel, half_width, margin) -> float:
    """How much a loop closure (keyframe n at ``rel`` from j) makes the map contradict itself: the
    smaller of the fraction of j's returns in n's free space and the fraction of n's returns in the
    free space of j's submap keyframes. A wrong placement contradicts both ways; a door closed or a
    person in the way between the visits, one way only."""
    into_n = free_space_conflict(pts[n][valid[n]], se2.transform_points(se2.inverse(rel), pts[j][valid[j]]), margin)
    src = se2.transform_points(rel, pts[n][valid[n]])  # in j's frame
    into_j = max(free_space_conflict(pts[m][valid[m]], se2.transform_points(se2.relative(poses[m], poses[j]), src),
                                     margin)
                 for m in range(max(j - half_width, 0), min(j + half_width + 1, len(pts))))
    return min(into_n, into_j)


def _constraint(src, target, tree, pose, distance) -> float:
    """How well a match fixes the translation: the smaller over the larger eigenvalue of the
    mean n n^T of the target normals at the inliers (0: a straight corridor, which matches
    anywhere along itself; 0.5: directions equally constrained)."""
    d, j = tree.query(se2.transform_points(pose, src), distance_upper_bound=distance)
    ok = np.isfinite(d)
    if ok.sum() < 3:
        return 0.0
    n = pca_normals(target, 6, tree)[j[ok]]
    ev = np.linalg.eigvalsh(n.T @ n / len(n))
    return float(ev[0] / max(ev[1], 1e-12))
