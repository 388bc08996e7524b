"""Cold start by curriculum: scans enter the map one chunk at a time (§3.4, the SLAM setting).

No initial poses and no classical registration. Each new scan is placed by the paper's own
loss: the lowest (0.1 x eq. 4 + lambda x Chamfer) of random hypotheses near its predecessor
(+ eq. 4's free-space labels read from the two scans themselves, seen_free, where weighted), then refined
by gradient steps of that loss together with the M-Net. When every scan is placed, the
placements become the warm start (§3.5) of ordinary training: T_i = T_place,i ∘ f_theta(S_i).
See docs/method.md ("Cold start").
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Callable

import numpy as np
import torch

from deepmapping.errors import ConfigError
from deepmapping.geometry import se2
from deepmapping.solver import distributed
from deepmapping.solver.geometry import planar_matrix, transform, translation
from deepmapping.solver.loss import chamfer

if TYPE_CHECKING:
    from deepmapping.solver.trainer import Trainer


def supported(model) -> bool:
    """2D scans, or 3D scans with planar (3-DoF, AVD-like) poses: the curriculum places by x, y, heading."""
    return not model.is_3d or model.lnet.out.out_features == 3


def enabled(cfg, model, ordered: bool) -> bool:
    """Whether this run places its scans by the curriculum first (``curriculum.enabled``)."""
    # "auto": every cold start of an ordered sequence the curriculum supports (2D scans, planar 3D
    # poses); 6-DoF poses start from the identity (docs/method.md, "Cold start on depth images")
    on = cfg.curriculum.enabled == "on" or (
        cfg.curriculum.enabled == "auto" and cfg.warm_start.method == "none" and ordered and supported(model))
    if on and not supported(model):
        raise ConfigError("curriculum: the cold-start curriculum is implemented for 2D scans and planar "
                          "(3-DoF) 3D poses only, not 6-DoF")
    if on and not cfg.lnet.zero_init_output:
        raise ConfigError("curriculum: needs lnet.zero_init_output = true (the L-Net starts at the placements)")
    return on


# -- placements as planar poses ---------------------------------------------------------------
# The curriculum reasons in planar poses [a, b, heading] (geometry.se2). 2D: the scans' own [x, y,
# theta]. 3D (AVD-like, y vertical): [z, x, theta about y], the order in which a turn about y is
# a counter-clockwise se2 rotation; the placements themselves are the model's free planar
# corrections (model.make_direct), converted here.


def _se2_of(m: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) planar matrices -> (..., 3) [z, x, theta]."""
    return torch.stack([m[..., 2, 3], m[..., 0, 3], torch.atan2(m[..., 0, 2], m[..., 0, 0])], dim=-1)


def _matrix_of(p: torch.Tensor) -> torch.Tensor:
    """(H, 3) [z, x, theta] -> (H, 4, 4) (planar_matrix takes [x, z, theta])."""
    return planar_matrix(p[:, [1, 0, 2]])


def placement(model, j: int) -> np.ndarray:
    """Where scan j is placed now, as a planar pose (3,)."""
    if not model.is_3d:
        return model.direct_poses[j].detach().double().cpu().numpy()
    with torch.no_grad():
        return _se2_of(model.poses(torch.tensor([j], device=model.scans.device))[0].double()).cpu().numpy()


def placements(model, n: int) -> np.ndarray:
    """Where scans 0..n-1 are placed now, as planar poses (n, 3)."""
    if not model.is_3d:
        return model.direct_poses[:n].detach().double().cpu().numpy()
    with torch.no_grad():
        return _se2_of(model.poses(torch.arange(n, device=model.scans.device)).double()).cpu().numpy()


def last_motion(model, j: int) -> np.ndarray:
    """The motion from scan j-2's placement to scan j-1's (zero before two scans are placed): the
    constant-velocity guess that moves scan j's second search centre on from its predecessor."""
    return se2.relative(placement(model, j - 2), placement(model, j - 1)) if j >= 2 else np.zeros(3)


def triggered(model, j: int, cfg, median_range: float) -> tuple[bool, bool]:
    """Whether scan j gets (the wide search, the free-space check): both for the second scan (no
    motion known yet); for later ones, each when the median shift or turn between the placements
    of scans 0..j-1 exceeds its trigger (``wide_trigger``, ``free_space_trigger``) x the rounds'
    spread (``max_shift`` x ``median_range``, ``max_turn_deg``): slow sequences skip them."""
    if j < 2:
        return j == 1 and cfg.wide_hypotheses > 0, j == 1
    p = placements(model, j)  # once: both triggers read the same motions
    m = se2.relative(p[:-1], p[1:])
    shift, turn = float(np.median(np.hypot(m[:, 0], m[:, 1]))), float(np.median(np.abs(m[:, 2])))

    def above(trigger: float) -> bool:
        return shift > trigger * (cfg.max_shift * median_range) or turn > trigger * math.radians(cfg.max_turn_deg)

    return cfg.wide_hypotheses > 0 and above(cfg.wide_trigger), above(cfg.free_space_trigger)


def wide_size(cfg, full: bool) -> tuple[int, float, float, int, int]:
    """The wide search's (hypotheses, shift in median ranges, turn in degrees, keep, refine): the
    full size where the free-space check runs too (``full``: the larger motions), the small one
    (``small_wide_*``) elsewhere, unless ``small_wide_hypotheses`` is 0."""
    if full or cfg.small_wide_hypotheses == 0:
        return cfg.wide_hypotheses, cfg.wide_shift, cfg.wide_turn_deg, cfg.wide_keep, cfg.wide_refine
    return (cfg.small_wide_hypotheses, cfg.small_wide_shift, cfg.small_wide_turn_deg, cfg.small_wide_keep,
            cfg.small_wide_refine)


def candidate_poses(model, cands) -> torch.Tensor:
    """Planar poses (H, 3) -> what ``transform`` takes: (H, 3) in 2D, (H, 4, 4) in 3D."""
    t = torch.as_tensor(cands, dtype=model.scans.dtype, device=model.scans.device)
    return _matrix_of(t) if model.is_3d else t


@torch.no_grad()
def set_placement(model, idx: range, pose: np.ndarray) -> None:
    """Place the scans ``idx`` at the planar pose ``pose`` (3,)."""
    dp = model.direct_poses
    if len(idx) == 0:
        return
    target = torch.as_tensor(pose, dtype=dp.dtype, device=dp.device)
    if not model.is_3d:
        dp[idx.start: idx.stop] = target
        return
    # 3D: T = T_init @ Tr(p) @ P(v) @ Tr(-p) = G  =>  P(v) = Tr(-p) @ T_init^-1 @ G @ Tr(p)
    sel = torch.arange(idx.start, idx.stop, device=dp.device)
    g = _matrix_of(target[None]).expand(len(sel), 4, 4)
    m = torch.linalg.inv(model.init_poses[sel]) @ g
    if model.pivot is not None:
        p = model.pivot[sel]
        m = translation(-p) @ m @ translation(p)
    dp[idx.start: idx.stop] = _se2_of(m)[:, [1, 0, 2]]  # corrections are [x, z, theta]


def selection_points(model, valid: torch.Tensor, j: int, cap: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Scan j's points and validity for ranking hypotheses: all beams, or (dense scans, e.g. depth
    images) ``cap`` of its valid points, drawn once per scan."""
    scan, v = model.scans[j], valid[j]
    if scan.shape[0] <= cap:
        return scan, v
    ok = torch.nonzero(v).flatten()
    g = torch.Generator().manual_seed(j)
    pick = ok[torch.randperm(len(ok), generator=g)[:cap].to(ok.device)]
    return scan[pick], v[pick]


# -- one new scan ------------------------------------------------------------------------------


def truncated_chamfer(x: torch.Tensor, xv: torch.Tensor, y: torch.Tensor, yv: torch.Tensor, r: float) -> torch.Tensor:
    """Eq. 5 with each nearest-neighbour distance capped at ``r``, divided by ``r`` -> (P,) in [0, 2].
    Parts of two partially overlapping views that the other does not see cost a constant instead
    of pulling the views together (depth images with a 60 deg field of view)."""
    d = torch.cdist(x, y)
    if not bool(yv.all()):
        d = d.masked_fill(~yv[:, None, :], math.inf)
    if not bool(xv.all()):
        d = d.masked_fill(~xv[:, :, None], math.inf)
    wx, wy = xv.to(x.dtype), yv.to(x.dtype)
    ax = (d.min(2).values.clamp(max=r) * wx).sum(1) / wx.sum(1).clamp(min=1)
    ay = (d.min(1).values.clamp(max=r) * wy).sum(1) / wy.sum(1).clamp(min=1)
    return (ax + ay) / r


def fit_pinhole(scans: torch.Tensor, valid: torch.Tensor, grid_shape: tuple[int, int]) -> tuple[float, ...] | None:
    """(fx, cx, fy, cy) of organized depth images (pixel j = (j // W, j % W), z forward), fitted
    by least squares to u = fx x / z + cx, v = fy y / z + cy over the valid points; None when the
    images are not a pinhole's (an RMS residual above 0.5 pixel) or have too few points."""
    h, w = grid_shape
    p = scans.detach().double().cpu().numpy().reshape(-1, h * w, 3)
    ok = valid.cpu().numpy().reshape(-1, h * w) & (p[..., 2] > 1e-9)
    j = np.broadcast_to(np.arange(h * w), ok.shape)[ok]
    if len(j) < 3:
        return None
    out = []
    for coord, pixel in ((p[..., 0][ok] / p[..., 2][ok], j % w), (p[..., 1][ok] / p[..., 2][ok], j // w)):
        a = np.stack([coord, np.ones_like(coord)], 1)
        fit = np.linalg.lstsq(a, pixel.astype(np.float64), rcond=None)[0]
        if np.sqrt(np.mean((a @ fit - pixel) ** 2)) > 0.5:
            return None
        out.extend(fit)
    return tuple(float(x) for x in out)


def fit_polar(scans: torch.Tensor, valid: torch.Tensor) -> tuple[float, float] | None:
    """(start, increment) of organized 2D scans (beam j at bearing start + j x increment, radians),
    fitted to the valid beams' bearings; None when the beams are not in bearing order (an RMS
    residual above half an increment) or there are too few of them."""
    p = scans.detach().double().cpu().numpy()
    ok = valid.cpu().numpy() & (np.hypot(p[..., 0], p[..., 1]) > 1e-9)
    s, j = np.nonzero(ok)  # row-major: beams in order within each scan
    if len(j) < 3:
        return None
    bearing = np.arctan2(p[s, j, 1], p[s, j, 0])
    same = s[1:] == s[:-1]
    steps = (se2.wrap_angle(np.diff(bearing)) / np.maximum(np.diff(j), 1))[same]
    if len(steps) == 0 or abs(float(np.median(steps))) < 1e-9:
        return None
    inc = float(np.median(steps))
    start = float(np.angle(np.exp(1j * (bearing - inc * j)).mean()))
    resid = se2.wrap_angle(bearing - inc * j - start)
    if np.sqrt(np.mean(resid ** 2)) > 0.5 * abs(inc):
        return None
    return start, inc


def free_depth(depth: torch.Tensor, valid: torch.Tensor, grid_shape: tuple[int, ...]) -> torch.Tensor:
    """(N,) how far each pixel's (2D: beam's) ray is surely free: the nearest depth among it and its
    neighbours (8 in an image, 2 along a scan), 0 where any of them has no return (at depth edges a
    point projected to the next pixel is not taken for free space)."""
    img = torch.where(valid, depth, torch.zeros_like(depth)).reshape(1, 1, *grid_shape)
    pool = torch.nn.functional.max_pool2d if len(grid_shape) == 2 else torch.nn.functional.max_pool1d
    return (-pool(-img, 3, stride=1, padding=1)).flatten().clamp(min=0)


def _excess(depth: torch.Tensor, idx: torch.Tensor, dist: torch.Tensor, seen: torch.Tensor, pv: torch.Tensor,
            tol: float, ramp: float = 1.0) -> torch.Tensor:
    """(H,) mean over the valid points of how far each lies in front of the seen surface: 0 within
    ``tol``, rising to 1 at (1 + ``ramp``) x ``tol``; points not ``seen`` (outside the view) cost 0."""
    excess = ((depth[idx] - dist) / tol - 1).clamp(0, ramp) / ramp * (seen & pv[None, :])
    return excess.sum(1) / pv.to(dist.dtype).sum().clamp(min=1)


def seen_free(pts: torch.Tensor, pv: torch.Tensor, cams: torch.Tensor, depth: torch.Tensor, intr: tuple,
              grid_shape: tuple[int, int], tol: float, ramp: float = 1.0) -> torch.Tensor:
    """Eq. 4's free-space labels taken exactly from one depth image: the mean over points ``pts``
    (H, P, 3) global (validity ``pv`` (P,)) of how far each lies in front of the surface that the
    camera ``cams`` (H, 4, 4) saw along its pixel (``depth`` (N,), from free_depth): 0 within
    ``tol``, rising to 1 at (1 + ``ramp``) x ``tol`` in front; points behind that surface or outside
    the image cost 0."""
    fx, cx, fy, cy = intr
    h, w = grid_shape
    rot, t = cams[:, :3, :3], cams[:, :3, 3]
    q = (pts - t[:, None, :]) @ rot  # global -> camera frame (R^T (p - t), row-wise)
    z = q[..., 2]
    zs = z.clamp(min=1e-6)
    u = torch.round(fx * q[..., 0] / zs + cx)
    v = torch.round(fy * q[..., 1] / zs + cy)
    inside = (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    idx = (v.clamp(0, h - 1) * w + u.clamp(0, w - 1)).long()
    return _excess(depth, idx, z, inside, pv, tol, ramp)


def seen_free_2d(pts: torch.Tensor, pv: torch.Tensor, poses: torch.Tensor, ranges: torch.Tensor,
                 polar: tuple[float, float], tol: float, ramp: float = 1.0) -> torch.Tensor:
    """seen_free for 2D scans: points ``pts`` (H, P, 2) global against the ranges (N,) (from
    free_depth) of one scan taken from ``poses`` (H, 3) [x, y, theta], its beams at the bearings
    ``polar`` (fit_polar) gives; points at a bearing no beam covers cost 0."""
    start, inc = polar
    n = ranges.shape[0]
    c, s = torch.cos(poses[:, 2])[:, None], torch.sin(poses[:, 2])[:, None]
    d = pts - poses[:, None, :2]
    qx, qy = c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]  # global -> sensor frame
    turn = round(2 * math.pi / abs(inc))  # beams per full turn
    k = torch.round(torch.remainder(math.copysign(1.0, inc) * (torch.atan2(qy, qx) - start), 2 * math.pi)
                    / abs(inc)).long() % turn
    return _excess(ranges, k.clamp(max=n - 1), torch.hypot(qx, qy), k < n, pv, tol, ramp)


def candidate_losses(model, pts: tuple, j: int, candidates: torch.Tensor, prev: tuple | None,
                     chamfer_weight: float, bce_weight: float = 1.0, free_samples: int = 4,
                     truncate: float | None = None) -> torch.Tensor:
    """The loss of scan ``j`` (``pts`` = its points and validity) placed at each of ``candidates``
    (H, 3) or (H, 4, 4): eq. 4 under the current M-Net (every given beam, stratified free-space
    samples at fixed fractions) + lambda x Chamfer (eq. 5) to ``prev`` (the predecessor's points
    in the global frame and validity; None for the first scan), or lambda x the truncated
    Chamfer distance when ``truncate`` (the cap, in the points' units) is given."""
    h = candidates.shape[0]
    scan, vj = pts[0][None].expand(h, -1, -1), pts[1][None].expand(h, -1)
    occ = transform(candidates, scan)  # (H, N, D)
    use_chamfer = chamfer_weight > 0 and prev is not None
    if bce_weight > 0 or not use_chamfer:
        t = (torch.arange(free_samples, device=scan.device, dtype=scan.dtype) + 0.5) / free_samples
        free = transform(candidates, scan[:, :, None, :] * t[None, None, :, None])  # (H, N, S, D)
        nll_occ = torch.nn.functional.softplus(-model.mnet(occ))  # BCE against 1
        nll_free = torch.nn.functional.softplus(model.mnet(free)).mean(-1)  # BCE against 0
        w = vj.to(scan.dtype)
        bce = bce_weight * ((nll_occ + nll_free) * w).sum(1) / w.sum(1).clamp(min=1)
    else:  # Chamfer only: the M-Net is not evaluated (the wide search's first screen on depth images)
        bce = torch.zeros(h, dtype=scan.dtype, device=scan.device)
    if not use_chamfer:
        return bce
    y, yv = prev[0][None].expand(h, -1, -1), prev[1][None].expand(h, -1)
    ch = truncated_chamfer(occ, vj, y, yv, truncate) if truncate else chamfer(occ, vj, y, yv)
    return bce + chamfer_weight * ch


def free_space_check(trainer: Trainer, j: int, prev: np.ndarray, prev_glob: tuple,
                     median_range: float) -> Callable | None:
    """With ``curriculum.free_space_weight`` > 0: a function (poses as ``transform`` takes them (H, ...),
    the new scan's points and validity) -> (H,) that charges the new scan's points lying in front of
    what the placed predecessor saw (depth images: seen_free; 2D scans: seen_free_2d), and the
    predecessor's points in front of what the new scan sees; None otherwise, and for scans whose
    sensor no model fits (fit_pinhole, fit_polar)."""
    cfg, model = trainer.cfg.curriculum, trainer.model
    grid = model.lnet.grid_shape if model.is_3d else (model.scans.shape[1],)
    if cfg.free_space_weight == 0 or grid is None:
        return None
    if trainer.sensor is None:
        fit = fit_pinhole(model.scans, trainer.valid, grid) if model.is_3d else fit_polar(model.scans, trainer.valid)
        trainer.sensor = fit or ()
    if not trainer.sensor:
        return None
    prev_cam = candidate_poses(model, prev[None])
    tol = cfg.free_space_tolerance * median_range

    def depth(k: int) -> torch.Tensor:  # along the optical axis (depth images), or the range (2D)
        return model.scans[k][:, 2] if model.is_3d else model.scans[k].norm(dim=1)

    prev_free = free_depth(depth(j - 1), trainer.valid[j - 1], grid)
    new_free = free_depth(depth(j), trainer.valid[j], grid)

    def seen(pts: torch.Tensor, pv: torch.Tensor, cams: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
        if model.is_3d:
            return seen_free(pts, pv, cams, free, trainer.sensor, grid, tol, cfg.free_space_ramp)
        return seen_free_2d(pts, pv, cams, free, trainer.sensor, tol, cfg.free_space_ramp)

    def check(cams: torch.Tensor, on: tuple) -> torch.Tensor:
        h = len(cams)
        placed = transform(cams, on[0][None].expand(h, -1, -1))
        there = seen(placed, on[1], prev_cam.expand(h, *prev_cam.shape[1:]), prev_free)
        back = seen(prev_glob[0][None].expand(h, -1, -1), prev_glob[1], cams, new_free)
        return cfg.free_space_weight * (there + back)

    return check


def halves(h: int) -> tuple[int, int, np.ndarray]:
    """``h`` hypotheses in two halves around two centres: (h, the first half's size, a mask that
    is False at each half's first hypothesis, left at its centre: neither turned nor shifted)."""
    half = (h + 1) // 2
    keep = np.ones(h, bool)
    keep[[0, half % h]] = False
    return h, half, keep


def ranking_scale(trainer: Trainer, pts: tuple) -> tuple[float, float, float | None]:
    """For ranking a scan's hypotheses (``pts``: its points and validity): its median range, the
    Chamfer term's weight and its cap (``select_truncate`` x the median range; None: uncapped)."""
    cfg = trainer.cfg.curriculum
    median_range = float(pts[0][pts[1]].norm(dim=1).median())
    if cfg.select_truncate > 0:
        return median_range, cfg.select_chamfer_weight, cfg.select_truncate * median_range
    return median_range, trainer.cfg.loss.chamfer_weight, None


@torch.no_grad()
def place_new_scan(trainer: Trainer, j: int) -> None:
    """Initial placement of scan j: the lowest-loss of several random hypotheses.

    Round 1: half of the hypotheses around the predecessor moved on by the last motion
    (constant velocity), half around the predecessor itself (no motion: a wrong last motion is
    not repeated); each turned by up to ``max_turn_deg`` and shifted by up to ``max_shift`` x
    the scan's median range (the first of each half neither turned nor shifted). Each further
    round draws around the best so far with half the spread; the best so far stays a candidate.
    """
    cfg, model = trainer.cfg.curriculum, trainer.model
    if j == 0:
        return
    prev = placement(model, j - 1)
    motion = last_motion(model, j)
    rng = np.random.default_rng([trainer.cfg.seed, j])
    h, half, keep = halves(cfg.hypotheses)
    centres = np.where(np.arange(h)[:, None] < half, se2.compose(prev, motion), prev)
    pts = selection_points(model, trainer.valid, j, cfg.select_points)
    prev_pts, prev_valid = selection_points(model, trainer.valid, j - 1, cfg.select_points)
    prev_glob = (transform(candidate_poses(model, prev[None]), prev_pts[None])[0], prev_valid)
    median_range, ch_weight, truncate = ranking_scale(trainer, pts)
    shift = cfg.max_shift * median_range

    wide, check_free = triggered(model, j, cfg, median_range)  # slow sequences skip both
    free_check = free_space_check(trainer, j, prev, prev_glob, median_range) if check_free else None

    def score(c, on=pts, bce_weight=cfg.select_bce_weight) -> torch.Tensor:
        cams = candidate_poses(model, c)
        loss = candidate_losses(model, on, j, cams, prev_glob, ch_weight, bce_weight, truncate=truncate)
        if free_check is not None:
            loss = loss + free_check(cams, on)
        if check_free and cfg.turn_prior > 0 and not model.is_3d:
            loss = loss + cfg.turn_prior * (1 - torch.cos(cams[:, 2] - float(prev[2]))) / 2
        return loss

    wide_bce = cfg.select_bce_weight if cfg.wide_bce_weight is None else cfg.wide_bce_weight

    def wide_score(c, on=pts) -> torch.Tensor:  # the wide search's ranking: its screen and refinement
        return score(c, on, wide_bce)

    turn = math.radians(cfg.max_turn_deg)
    seeds = None
    if wide:
        few = selection_points(model, trainer.valid, j, cfg.wide_points)
        hyp, reach, wide_turn, wide_keep, wide_refine = wide_size(cfg, check_free)
        seeds = wide_search(lambda c: wide_score(c, few), centres[[0, half % h]], hyp, reach * median_range,
                            math.radians(wide_turn), wide_keep,
                            np.random.default_rng([trainer.cfg.seed, j, 1]),  # the rounds draw as without it
                            points=len(few[0]))
    best = search_rounds(score, centres, keep, shift, turn, cfg, rng, model.scans.dtype)
    if seeds is not None:  # the wide search's seeds, refined apart, replace the rounds' best if lower (prefer_wide)
        far = refine(wide_score, seeds, distributed.split_scores(wide_score, seeds), wide_refine, cfg.refine_steps, cfg.refine_lr,
                     model.scans.dtype)
        best = prefer_wide(best, far, score(np.stack([best, far])), cfg.wide_margin, cfg.wide_heading_only)
    set_placement(model, range(j, model.scans.shape[0]), best)  # unplaced scans wait there too


def search_rounds(score: Callable, centres: np.ndarray, keep: np.ndarray, shift: float, turn: float, cfg,
                  rng: np.random.Generator, dtype) -> np.ndarray:
    """The rounds of ``place_new_scan``: hypotheses around ``centres`` (H, 3) shifted by up to ``shift``
    and turned by up to ``turn`` (not those where ``keep`` is False), ``cfg.rounds`` rounds each
    around the best so far with half the spread; then the ``refine_top`` lowest refined
    (``refine``). Returns the lowest-``score`` pose (3,)."""
    h = len(centres)
    best, best_loss = None, math.inf
    seen_c, seen_l = [], []
    for _ in range(cfg.rounds):
        r = np.sqrt(rng.uniform(0, 1, h)) * shift * keep
        a = rng.uniform(0, 2 * np.pi, h)
        delta = np.stack([r * np.cos(a), r * np.sin(a), rng.uniform(-1, 1, h) * turn * keep], 1)
        cands = se2.compose(centres, delta)
        if best is not None:
            cands[0] = best
        losses = distributed.split_scores(score, cands)  # several workers: each scores its share
        seen_c.append(cands)
        seen_l.append(losses)
        i = int(torch.argmin(losses))
        if float(losses[i]) <= best_loss:
            best, best_loss = cands[i], float(losses[i])
        centres, keep = np.broadcast_to(best, (h, 3)), np.arange(h) > 0
        shift, turn = shift / 2, turn / 2
    if cfg.refine_top > 0:
        best = refine(score, np.concatenate(seen_c), torch.cat(seen_l), cfg.refine_top, cfg.refine_steps,
                      cfg.refine_lr, dtype)
    return best


def prefer_wide(best: np.ndarray, far: np.ndarray, losses: torch.Tensor, margin: float,
                heading_only: bool) -> np.ndarray:
    """The rounds' choice ``best`` or the wide search's ``far`` (losses: theirs, in that order):
    ``far`` only if its loss is lower by more than ``margin`` x the rounds' (a motion prior: the
    nearer motion unless the farther one is clearly better); with ``heading_only``, ``far``'s
    heading at ``best``'s position (depth images: the truncated Chamfer distance finds the heading
    after a move, but after a turn in place it slides the view along what both see)."""
    lb, lf = float(losses[0]), float(losses[1])
    if not lf < lb - margin * abs(lb):
        return best
    return np.array([best[0], best[1], far[2]]) if heading_only else far


WIDE_BLOCK_POINTS = 1 << 17  # hypotheses x points scored at once: bounded memory for dense scans


def wide_search(score: Callable, centres: np.ndarray, h: int, radius: float, turn: float, keep: int,
                rng: np.random.Generator, points: int = 1) -> np.ndarray:
    """The ``keep`` lowest-loss of ``h`` hypotheses drawn uniformly within ``radius`` of the
    ``centres`` (a random one each) and turned uniformly within +- ``turn``: candidates from
    farther than the rounds reach, refined and compared with the rounds' choice by the caller."""
    c = centres[rng.integers(0, len(centres), h)]
    r, a = np.sqrt(rng.uniform(0, 1, h)) * radius, rng.uniform(0, 2 * np.pi, h)
    cands = se2.compose(c, np.stack([r * np.cos(a), r * np.sin(a), rng.uniform(-1, 1, h) * turn], 1))
    block = max(1, WIDE_BLOCK_POINTS // points)
    losses = torch.cat([distributed.split_scores(score, cands[i: i + block]) for i in range(0, h, block)])
    return cands[torch.argsort(losses)[:keep].cpu().numpy()]


def refine(score: Callable, cands: np.ndarray, losses: torch.Tensor, top: int, steps: int, lr: float,
           dtype) -> np.ndarray:
    """The ``top`` lowest-loss hypotheses, each moved by ``steps`` Adam steps of the same loss
    (the M-Net held), then ranked again: a hypothesis near the right basin gets to its bottom
    before the ranking, one that only looked good at its starting point does not win. The
    unrefined hypotheses stay in the final ranking, so refining never picks a higher loss."""
    order = torch.argsort(losses)[:top].cpu().numpy()
    order = order[distributed.part(len(order))]  # several workers: each refines its share
    both = torch.zeros((0, *cands.shape[1:]), dtype=dtype)
    final = torch.zeros(0, dtype=dtype)
    if len(order):
        p = torch.tensor(cands[order], dtype=dtype, requires_grad=True)
        opt = torch.optim.Adam([p], lr=lr)
        with torch.enable_grad():
            for _ in range(steps):
                (g,) = torch.autograd.grad(score(p).sum(), [p])
                p.grad = g
                opt.step()
        both = torch.cat([p.detach(), torch.as_tensor(cands[order], dtype=dtype)])  # a step that made it worse loses
        final = score(both)
    if distributed.active():
        both = torch.cat(distributed.gather(both.cpu()))
        final = torch.cat([f.to(torch.float64) for f in distributed.gather(final.detach().cpu())])
    return both[int(torch.argmin(final))].double().cpu().numpy()


def stage_batch(n: int, cfg, rng: np.random.Generator) -> np.ndarray:
    """The newest ``window`` placed scans (temporal neighbours together) and ``revisit`` random earlier ones."""
    start = max(0, n - cfg.window)
    earlier = rng.choice(start, size=min(cfg.revisit, start), replace=False) if start else np.zeros(0, np.int64)
    return np.sort(np.concatenate([earlier, np.arange(start, n)])).astype(np.int64)


# -- the whole curriculum ----------------------------------------------------------------------


def run(trainer: Trainer, checkpoint_path=None, on_log: Callable | None = None,
        on_place: Callable[[int, int], None] | None = None) -> None:
    """Place every scan (from ``trainer.state.placed`` on, so that a resumed run continues),
    then hand the placements over to ordinary training. Each stage is one ``trainer.guarded``
    body: a NaN/inf step sends it back to the stage's start with a lower learning rate."""
    model, st, cfg = trainer.model, trainer.state, trainer.cfg.curriculum
    k = model.scans.shape[0]
    if model.direct_poses is None:  # placements: free poses while the L-Net is held at zero output
        model.make_direct()
        trainer.reset_optimizer()
        trainer.boundary()
    n, stage = st.placed, st.placed // cfg.chunk  # a resumed run logs at the same stages
    while n < k:
        n, sums = trainer.guarded(lambda start=n: _stage(trainer, start))
        st.curriculum_steps = st.step
        stage += 1
        if on_place:
            on_place(n, k)
        if stage % cfg.log_every == 0 or n == k:
            trainer.log_now(*(sums / max(cfg.steps, 1)), on_log)
        if n < k:  # a checkpoint says "all placed" only once the placements are handed over
            st.placed = n
            trainer.boundary(checkpoint_path)
    st.reviewed = review_placements(trainer)
    distributed.broadcast_(model.direct_poses, model.init_poses)
    hand_over(trainer)
    st.placed = k
    trainer.boundary(checkpoint_path, force=True)


def _stage(trainer: Trainer, start: int) -> tuple[int, np.ndarray]:
    """Place scans ``start``.. (one chunk), then ``steps`` steps on the placed ones; returns
    (number placed, summed (loss, bce, chamfer) of the steps)."""
    model, cfg = trainer.model, trainer.cfg.curriculum
    k = model.scans.shape[0]
    new = range(start, min(start + cfg.chunk, k))
    for j in new:
        place_new_scan(trainer, j)
    distributed.broadcast_(model.direct_poses, model.init_poses)  # several workers: worker 0's placements
    n = new[-1] + 1
    rng = np.random.default_rng([trainer.cfg.seed, n])
    sums = np.zeros(3)
    for _ in range(cfg.steps if n > 1 else 0):
        sums += trainer.step(stage_batch(n, cfg, rng), lr=cfg.lr)
    set_placement(model, range(n, k), placement(model, n - 1))  # unplaced scans wait at the newest
    return n, sums


@torch.no_grad()
def review_placements(trainer: Trainer) -> list[int]:
    """Once every scan is placed: a scan that sits apart from both temporal neighbours while they
    agree with each other (the smaller of its Chamfer distances to them over ``review_ratio`` x
    theirs to each other; the ``review_max`` highest ratios, each checked again just before, as
    moving one changes its neighbours') is placed again by the rounds of ``place_new_scan`` around
    where it is and between the neighbours, ranked by the same loss with the Chamfer term to both
    neighbours. A new placement is taken only if its loss is lower by more than ``review_margin`` x
    the current one. Returns the scans moved."""
    cfg, model = trainer.cfg.curriculum, trainer.model
    k = model.scans.shape[0]
    if cfg.review_ratio <= 0 or k < 3:
        return []
    p = placements(model, k)
    pts = [selection_points(model, trainer.valid, i, cfg.select_points) for i in range(k)]
    glob = transform(candidate_poses(model, p), torch.stack([x for x, _ in pts]))
    valid = torch.stack([v for _, v in pts])

    def ratio(i: torch.Tensor) -> torch.Tensor:  # scans i (1..k-2)
        near = torch.minimum(chamfer(glob[i - 1], valid[i - 1], glob[i], valid[i]),
                             chamfer(glob[i], valid[i], glob[i + 1], valid[i + 1]))
        return near / chamfer(glob[i - 1], valid[i - 1], glob[i + 1], valid[i + 1]).clamp(min=1e-12)

    inner = torch.arange(1, k - 1, device=glob.device)
    order = inner[torch.argsort(ratio(inner), descending=True)[: cfg.review_max]].tolist()
    rng = np.random.default_rng([trainer.cfg.seed, k, 2])
    h, half, keep = halves(cfg.hypotheses)
    moved = []
    for i in order:
        if float(ratio(torch.tensor([i], device=glob.device))[0]) <= cfg.review_ratio:
            continue
        median_range, ch_weight, truncate = ranking_scale(trainer, pts[i])

        def score(c, i=i, truncate=truncate, ch_weight=ch_weight) -> torch.Tensor:
            cams = candidate_poses(model, c)
            before = candidate_losses(model, pts[i], i, cams, (glob[i - 1], valid[i - 1]), ch_weight,
                                      cfg.select_bce_weight, truncate=truncate)
            return before + candidate_losses(model, pts[i], i, cams, (glob[i + 1], valid[i + 1]), ch_weight, 0.0,
                                             truncate=truncate)

        between = se2.compose(p[i - 1], se2.relative(p[i - 1], p[i + 1]) / 2)
        centres = np.where(np.arange(h)[:, None] < half, p[i], between)
        best = search_rounds(score, centres, keep, cfg.max_shift * median_range, math.radians(cfg.max_turn_deg),
                             cfg, rng, model.scans.dtype)
        now, new = score(np.stack([p[i], best])).tolist()
        if new < now - cfg.review_margin * abs(now):
            set_placement(model, range(i, i + 1), best)
            p[i] = best
            glob[i] = transform(candidate_poses(model, best[None]), pts[i][0][None])[0]
            moved.append(i)
    return moved


def hand_over(trainer: Trainer) -> None:
    """Placements -> warm start: DeepMapping composes the L-Net with them (its features are
    standardized again with the placed poses as input); direct optimization keeps optimizing them."""
    model = trainer.model
    if trainer.cfg.method != "direct":
        with torch.no_grad():
            model.init_poses.copy_(model.all_poses())
        model.direct_poses = None
        if trainer.cfg.lnet.feature_norm:
            model.calibrate_lnet()
    trainer.reset_optimizer()
