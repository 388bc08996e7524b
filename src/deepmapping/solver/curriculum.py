"""Cold start by curriculum: scans enter the map one chunk at a time (§3.4, the SLAM setting).

No initial poses and no classical registration. Each new scan is placed by the paper's own
loss: the lowest (eq. 4 + lambda x Chamfer) of random hypotheses near its predecessor,
then refined by gradient steps of that
loss together with the M-Net. When every scan is placed, the placements become the warm start
(§3.5) of ordinary training: T_i = T_place,i ∘ f_theta(S_i). See docs/method.md ("Cold start").
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Callable

import numpy as np
import torch

from deepmapping.core import se2
from deepmapping.errors import ConfigError
from deepmapping.solver.geometry import transform
from deepmapping.solver.loss import chamfer

if TYPE_CHECKING:
    from deepmapping.solver.trainer import Trainer


def enabled(cfg, model, ordered: bool) -> bool:
    """Whether this run places its scans by the curriculum first (``curriculum.enabled``)."""
    on = cfg.curriculum.enabled == "on" or (
        cfg.curriculum.enabled == "auto" and cfg.warm_start.method == "none" and ordered and not model.is_3d)
    if on and model.is_3d:
        raise ConfigError("curriculum: the cold-start curriculum is implemented for 2D scans only")
    if on and not cfg.lnet.zero_init_output:
        raise ConfigError("curriculum: needs lnet.zero_init_output = true (the L-Net starts at the placements)")
    return on


# -- one new scan ------------------------------------------------------------------------------


def candidate_losses(model, valid: torch.Tensor, j: int, candidates: torch.Tensor, prev_pose: torch.Tensor,
                     chamfer_weight: float, bce_weight: float = 1.0, free_samples: int = 4) -> torch.Tensor:
    """The loss of scan ``j`` placed at each of ``candidates`` (H, 3): eq. 4 under the current
    M-Net (all its beams, stratified free-space samples at fixed fractions) + lambda x Chamfer
    (eq. 5) to scan j - 1 at ``prev_pose`` (3,)."""
    h = candidates.shape[0]
    scan, vj = model.scans[j][None].expand(h, -1, -1), valid[j][None].expand(h, -1)
    occ = transform(candidates, scan)  # (H, N, 2)
    t = (torch.arange(free_samples, device=scan.device, dtype=scan.dtype) + 0.5) / free_samples
    free = transform(candidates, scan[:, :, None, :] * t[None, None, :, None])  # (H, N, S, 2)
    nll_occ = torch.nn.functional.softplus(-model.mnet(occ))  # BCE against 1
    nll_free = torch.nn.functional.softplus(model.mnet(free)).mean(-1)  # BCE against 0
    w = vj.to(scan.dtype)
    bce = bce_weight * ((nll_occ + nll_free) * w).sum(1) / w.sum(1).clamp(min=1)
    if chamfer_weight <= 0 or j == 0:
        return bce
    prev = transform(prev_pose[None], model.scans[j - 1][None]).expand(h, -1, -1)
    return bce + chamfer_weight * chamfer(occ, vj, prev, valid[j - 1][None].expand(h, -1))


@torch.no_grad()
def place_new_scan(trainer: Trainer, j: int) -> None:
    """Initial placement of scan j: the lowest-loss of several random hypotheses.

    Round 1: half of the hypotheses around the predecessor moved on by the last motion
    (constant velocity), half around the predecessor itself (no motion: a wrong last motion is
    not repeated); each turned by up to ``max_turn_deg`` and shifted by up to ``max_shift`` x
    the scan's median range (the first of each half neither turned nor shifted). Each further
    round draws around the best so far with half the spread; the best so far stays a candidate.
    """
    cfg, poses = trainer.cfg.curriculum, trainer.model.direct_poses
    if j == 0:
        return
    prev = poses[j - 1].double().cpu().numpy()
    motion = se2.relative(poses[j - 2].double().cpu().numpy(), prev) if j >= 2 else np.zeros(3)
    rng = np.random.default_rng([trainer.cfg.seed, j])
    h, half = cfg.hypotheses, (cfg.hypotheses + 1) // 2
    centres = np.where(np.arange(h)[:, None] < half, se2.compose(prev, motion), prev)
    keep = np.ones(h, bool)
    keep[[0, half % h]] = False  # the two plain centres
    scan = trainer.model.scans[j][trainer.valid[j]]
    shift = cfg.max_shift * float(scan.norm(dim=1).median())
    turn = math.radians(cfg.max_turn_deg)
    best, best_loss = None, math.inf
    for _ in range(cfg.rounds):
        r = np.sqrt(rng.uniform(0, 1, h)) * shift * keep
        a = rng.uniform(0, 2 * np.pi, h)
        delta = np.stack([r * np.cos(a), r * np.sin(a), rng.uniform(-1, 1, h) * turn * keep], 1)
        cands = se2.compose(centres, delta)
        if best is not None:
            cands[0] = best
        cands_t = torch.as_tensor(cands, dtype=poses.dtype, device=poses.device)
        losses = candidate_losses(trainer.model, trainer.valid, j, cands_t, poses[j - 1],
                                  trainer.cfg.loss.chamfer_weight, cfg.select_bce_weight)
        i = int(torch.argmin(losses))
        if float(losses[i]) <= best_loss:
            best, best_loss = cands[i], float(losses[i])
        centres, keep = np.broadcast_to(best, (h, 3)), np.arange(h) > 0
        shift, turn = shift / 2, turn / 2
    poses[j:] = torch.as_tensor(best, dtype=poses.dtype, device=poses.device)  # unplaced scans wait there too


def stage_batch(n: int, cfg, rng: np.random.Generator) -> np.ndarray:
    """The newest ``window`` placed scans (temporal neighbours together) and ``revisit`` random earlier ones."""
    start = max(0, n - cfg.window)
    earlier = rng.choice(start, size=min(cfg.revisit, start), replace=False) if start else np.zeros(0, np.int64)
    return np.sort(np.concatenate([earlier, np.arange(start, n)])).astype(np.int64)


# -- the whole curriculum ----------------------------------------------------------------------


def run(trainer: Trainer, checkpoint_path=None, on_log: Callable | None = None,
        on_place: Callable[[int, int], None] | None = None) -> None:
    """Place every scan (from ``trainer.state.placed`` on, so that a resumed run continues),
    then hand the placements over to ordinary training."""
    model, st, cfg = trainer.model, trainer.state, trainer.cfg.curriculum
    k = model.scans.shape[0]
    if model.direct_poses is None:  # placements: free poses while the L-Net is held at zero output
        model.make_direct()
        trainer.reset_optimizer()
    n, stage = st.placed, 0
    while n < k:
        new = range(n, min(n + cfg.chunk, k))
        for j in new:
            place_new_scan(trainer, j)
        n = new[-1] + 1
        rng = np.random.default_rng([trainer.cfg.seed, n])
        sums = np.zeros(3)
        for _ in range(cfg.steps if n > 1 else 0):
            sums += trainer.step(stage_batch(n, cfg, rng), lr=cfg.lr)
        with torch.no_grad():  # scans not placed yet wait at the newest placement
            model.direct_poses[n:] = model.direct_poses[n - 1]
        st.curriculum_steps = st.step
        stage += 1
        if on_place:
            on_place(n, k)
        if stage % cfg.log_every == 0 or n == k:
            trainer.log_now(*(sums / max(cfg.steps, 1)), on_log)
        if n < k:  # a checkpoint says "all placed" only once the placements are handed over
            st.placed = n
            trainer.maybe_checkpoint(checkpoint_path)
    hand_over(trainer)
    st.placed = k
    trainer.maybe_checkpoint(checkpoint_path, force=True)


def hand_over(trainer: Trainer) -> None:
    """Placements -> warm start: DeepMapping composes the L-Net with them (its features are
    standardized again with the placed poses as input); direct optimization keeps optimizing them."""
    model = trainer.model
    if trainer.cfg.method != "direct":
        with torch.no_grad():
            model.init_poses.copy_(model.direct_poses)
        model.direct_poses = None
        if trainer.cfg.lnet.feature_norm:
            model.calibrate_lnet()
    trainer.reset_optimizer()
