"""The optimisation loop: "training" the networks is the registration (eq. 2)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from deepmapping.config import Config, unresolved_auto
from deepmapping.errors import ConfigError, Interrupted, TrainingError
from deepmapping.solver import checkpoint as ckpt
from deepmapping.solver import curriculum, distributed
from deepmapping.solver.geometry import rotate, transform
from deepmapping.solver.loss import chamfer_loss, occupancy_bce, odometry_factor, place_pairs, scan_normals
from deepmapping.solver.model import DeepMappingModel
from deepmapping.solver.resolution import point_spacing, resolve_step
from deepmapping.solver.sampling import free_space_fractions, free_space_points, near_hit_fractions, select_beams


def _positions(poses: np.ndarray) -> np.ndarray:
    return poses[:, :3, 3] if poses.ndim == 3 else poses[:, :2]


ROLLBACK_LR_FACTOR = 0.5  # each rollback after a NaN/inf step multiplies every learning rate by this
MAX_ROLLBACKS = 4  # per run; one more non-finite step is a TrainingError


class NonFinite(Exception):
    """A step's loss is NaN/inf, or a NaN/inf gradient made the weights so: the work since the
    last boundary is undone (``Trainer.guarded``)."""


@dataclass
class TrainState:
    epoch: int = 0
    step: int = 0
    elapsed_s: float = 0.0
    placed: int = 0  # cold-start curriculum: scans placed so far
    curriculum_steps: int = 0  # steps taken by the curriculum (before the learning-rate schedule)
    reviewed: list = field(default_factory=list)  # cold-start curriculum: scans placed again by its review
    history: dict = field(default_factory=lambda: {k: [] for k in ckpt.HISTORY_KEYS})
    lr_scale: float = 1.0  # x every learning rate: ROLLBACK_LR_FACTOR per rollback
    rollbacks: list = field(default_factory=list)  # one dict per rollback (epoch, step, what, lr_scale)
    early_stop_ref: np.ndarray | None = None  # poses at the last log, for optim.early_stop_tol
    epoch_losses: list = field(default_factory=list)  # the last 2 x optim.stop_window epochs' mean losses
    stop_reason: str = ""  # why training ended before optim.epochs ("" = it ran them all)
    places: np.ndarray | None = None  # optim.batch_order "place": Trainer._places as last computed
    places_epoch: int = -1  # ... at the start of this epoch


def loss_plateau(losses: list, window: int, min_improvement: float) -> bool:
    """The stopping rule: whether the mean of the last ``window`` epoch losses is lower than the
    mean of the ``window`` before them by less than ``min_improvement`` x that earlier mean."""
    if len(losses) < 2 * window:
        return False
    before, last = float(np.mean(losses[-2 * window: -window])), float(np.mean(losses[-window:]))
    return before - last < min_improvement * abs(before)


def epoch_batches(num_scans: int, batch: int, rng: np.random.Generator, order: str = "contiguous") -> list[np.ndarray]:
    """Contiguous blocks of scans (temporal neighbours stay together for the Chamfer term),
    cut at a random offset each epoch so every neighbour pair is seen, in random order;
    ``order`` "random": blocks of a random permutation (each sorted); "auto" (api.register resolves it
    first) is contiguous."""
    batch = min(batch, num_scans)
    if order == "random":
        perm = rng.permutation(num_scans)
        return [np.sort(perm[a:a + batch]) for a in range(0, num_scans, batch)]
    offset = int(rng.integers(0, batch))
    cuts = [0] + list(range(offset or batch, num_scans, batch)) + [num_scans]
    blocks = [np.arange(a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]
    return [blocks[i] for i in rng.permutation(len(blocks))]


def place_batches(places: np.ndarray, batch: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Scans grouped by place (``places`` (K, F): where each scan is and what it sees): anchors in
    random order, each batch an anchor with the ``batch`` - 1 scans nearest to it that no batch of
    this epoch holds yet; every scan once an epoch, as with contiguous blocks."""
    k = len(places)
    batch = min(batch, k)
    free = np.ones(k, dtype=bool)
    out = []
    for a in rng.permutation(k):
        if not free[a]:
            continue
        free[a] = False
        cand = np.flatnonzero(free)
        near = cand[np.argsort(np.linalg.norm(places[cand] - places[a], axis=1), kind="stable")[: batch - 1]]
        free[near] = False
        out.append(np.sort(np.concatenate([[a], near])))
    return out


class Trainer:
    def __init__(self, cfg: Config, model: DeepMappingModel, valid: torch.Tensor, ordered: bool,
                 evaluate: Callable[[np.ndarray], float | None] | None = None,
                 odometry_sigma: tuple[float, float] | None = None):
        if distributed.active() and cfg.optim.batch_parts > 1:
            raise ConfigError("optim.batch_parts > 1 is for one process: several workers already share each batch")
        self.cfg, self.model, self.valid = cfg, model, valid
        # the odometry factor (loss.odometry_sigma as resolved for this run, sigma_t in normalized units; degrees)
        self.odometry_sigma = odometry_sigma if ordered and model.is_3d else None
        self.sensor: tuple | None = None  # curriculum cache: the fitted pinhole or polar beams; () = none fits
        self.use_chamfer = ordered and cfg.loss.chamfer_weight > 0
        # loss.chamfer_metric "plane": each scan's normals in its own frame, turned with its pose each step
        self.normals = None
        if self.use_chamfer and cfg.loss.chamfer_metric == "plane":
            self.normals = torch.from_numpy(scan_normals(model.scans.cpu().numpy(), valid.cpu().numpy())).to(
                model.scans.device)
        self.truncate = None
        if self.use_chamfer and cfg.loss.chamfer_truncate is not None:
            self.truncate = cfg.loss.chamfer_truncate * point_spacing(model.scans.cpu().numpy(), valid.cpu().numpy())
        # loss.beams_per_scan "auto" made a number (self.cfg stays as given: the checkpoint's settings)
        self.beams_per_scan = resolve_step(cfg, valid.shape[1], model.lnet.grid_shape).loss.beams_per_scan
        self.evaluate = evaluate
        self.device = valid.device
        # each worker its own beam samples (worker 0, or one process: the seed itself)
        self.gen = torch.Generator(device=self.device).manual_seed(
            (cfg.seed + distributed.rank() * distributed.RANK_SEED_STRIDE) % 2**64)
        self._step_loss: tuple[tuple, torch.nn.Module] | None = None  # (what it was built for, the loss module)
        self.use_curriculum = curriculum.enabled(cfg, model, ordered)
        self.reset_optimizer()
        k = valid.shape[0]
        # valid beams each scan gives eq. 4 per step (select_beams takes valid ones first): workers' weights
        beams = self.beams_per_scan or valid.shape[1]
        weighted = distributed.active() or cfg.optim.batch_parts > 1  # a batch in weighted parts
        self.samples_per_scan = valid.sum(1).clamp(max=beams).cpu().numpy() if weighted else None
        self.steps_per_epoch = len(epoch_batches(k, cfg.optim.batch_size, np.random.default_rng(0)))
        self.total_steps = cfg.optim.epochs * self.steps_per_epoch
        self.state = TrainState()
        self.extra: dict = {}  # saved with every checkpoint (e.g. the warm start and the frame)
        self._t_start = time.perf_counter()
        self._last_ckpt = time.perf_counter()
        self._good: dict | None = None  # the last consistent state (ckpt.capture), see boundary()
        self._epoch_warmup = False  # whether the last epoch was M-Net warm-up (see _after_epoch)
        self.curriculum_s = 0.0  # wall time of the cold-start curriculum in this process

    def reset_optimizer(self) -> None:
        """A fresh Adam over what produces the poses (L-Net or free poses) and the M-Net."""
        self.opt = torch.optim.Adam(self.model.param_groups(), lr=self.cfg.optim.lr)

    # -- one step -----------------------------------------------------------------------
    def lr_at(self, step: int) -> float:
        lo = self.cfg.optim.lr_final_factor
        frac = min(max(step - self.state.curriculum_steps, 0) / max(self.total_steps, 1), 1.0)
        return self.cfg.optim.lr * (lo + (1 - lo) * 0.5 * (1 + math.cos(math.pi * frac)))

    def mnet_warmup_now(self) -> bool:
        """Whether this step trains the M-Net only, the poses held (``optim.mnet_warmup_epochs``
        epochs and ``optim.mnet_warmup_steps`` steps of ordinary training, whichever is longer)."""
        o = self.cfg.optim
        if self.use_curriculum_now():  # the curriculum's placements always move with the M-Net
            return False
        epochs = unresolved_auto(o.mnet_warmup_epochs, "optim.mnet_warmup_epochs")  # api.register resolves "auto" first
        return self.state.epoch < epochs or self.state.step - self.state.curriculum_steps < o.mnet_warmup_steps

    def loss(self, idx: torch.Tensor, own: int | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(eq. 4, eq. 7, the odometry factor) on the scans ``idx``; ``own``: only the first ``own`` of
        them count in eq. 4 and as a pair's earlier scan in eq. 7 and the factor (a worker's part of a
        batch; the rest are its neighbours). Terms that are off are 0."""
        cfg = self.cfg.loss
        scans, valid = self.model.scans[idx], self.valid[idx]
        if self.mnet_warmup_now():
            with torch.no_grad():  # M-Net warm-up: poses held, no L-Net backward
                poses = self.model.poses(idx)
        else:
            poses = self.model.poses(idx)
        pts, pv = select_beams(scans, valid, self.beams_per_scan, self.gen)
        occ_global = transform(poses, pts)
        def mine(x: torch.Tensor) -> torch.Tensor:  # no slice at all in one process: the same graph as ever
            return x if own is None else x[:own]

        t = free_space_fractions(mine(pv).shape, cfg.free_samples, cfg.free_sampling, self.gen, self.device)
        near = unresolved_auto(cfg.near_hit_samples, "loss.near_hit_samples")  # api.register resolves "auto" first
        if near:
            t = torch.cat([t, near_hit_fractions(mine(pts), near, cfg.near_hit_distance, self.gen)], -1)
        free_global = transform(mine(poses), free_space_points(mine(pts), t))
        occ_logits = self.model.mnet(mine(occ_global))  # (B, M)
        free_logits = self.model.mnet(free_global)  # (B, M, S)
        bce = occupancy_bce(occ_logits, mine(pv), free_logits, mine(pv)[..., None].expand_as(free_logits))
        odo = bce.new_zeros(())
        if self.odometry_sigma is not None and poses.requires_grad:  # not while the poses are held
            sigma_t, sigma_r = self.odometry_sigma
            odo = odometry_factor(poses, self.model.init_poses[idx], idx, sigma_t, math.radians(sigma_r), own)
        if not self.use_chamfer:
            return bce, bce.new_zeros(()), odo
        # the beams sampled for eq. 4 are also the Chamfer queries (all beams in the paper profile)
        normals = None if self.normals is None else rotate(poses, self.normals[idx])
        extra = None
        if cfg.chamfer_place_neighbours:
            extra = place_pairs(self._places()[idx.cpu().numpy()], cfg.chamfer_place_neighbours)
        return bce, chamfer_loss(transform(poses, scans), valid, idx, cfg.chamfer_window, occ_global, pv, own,
                                 normals=normals, truncate=self.truncate, extra_pairs=extra), odo

    def step(self, idx: np.ndarray, lr: float | None = None) -> tuple[float, float, float]:
        """One optimizer step on the scans ``idx``; ``lr``: a constant rate instead of the schedule."""
        lr = (self.lr_at(self.state.step) if lr is None else lr) * self.state.lr_scale
        warmup = self.mnet_warmup_now()
        for g in self.opt.param_groups:
            g["lr"] = 0.0 if (warmup and g["name"] == "poses") else lr * g["lr_factor"]
        # several workers: each takes a part of the batch (and the neighbours its Chamfer pairs need),
        # its terms weighted so that their mean over the workers is the batch's loss; then
        # DistributedDataParallel averages the gradients. optim.batch_parts in one process: the same
        # parts one after the other, their weighted gradients summed
        # (the odometry factor's pairs are neighbours too: weighted as the Chamfer pairs, exact for window 1)
        window = max(self.cfg.loss.chamfer_window if self.use_chamfer else 0, int(self.odometry_sigma is not None))
        self.opt.zero_grad(set_to_none=True)
        if self.cfg.optim.batch_parts > 1:  # one process (refused with workers in __init__): the batch in parts
            sums = torch.zeros(3, device=self.device)
            for i in range(self.cfg.optim.batch_parts):
                part = distributed.split(idx, window, self.samples_per_scan, i, self.cfg.optim.batch_parts)
                if part[2] > 0 or part[3] > 0:
                    sums += self._backward(*part)
            total, bce, ch = sums
        else:
            total, bce, ch = self._backward(*distributed.share(idx, window, self.samples_per_scan))
        self.opt.step()
        loss, bce, ch = distributed.mean(torch.stack([total, bce, ch])).tolist()
        if not math.isfinite(loss):  # the step is undone by the rollback (guarded) that follows
            raise NonFinite(f"loss is {loss}")
        self.state.step += 1
        return loss, bce, ch

    def _backward(self, mine: np.ndarray, own: int | None, w_bce: float, w_ch: float) -> torch.Tensor:
        """The gradients of the scans ``mine`` (the first ``own`` of them theirs, weighted ``w_bce``,
        ``w_ch``: distributed.split) added to the parameters'; (total, eq. 4, eq. 7) as weighted."""
        bce, ch, odo = self.loss_module()(torch.as_tensor(mine, device=self.device), own)
        if own is not None:  # weighted only in parts (workers, batch_parts): one process keeps its graph and last bits
            bce, ch, odo = w_bce * bce, w_ch * ch, w_ch * odo
        total = bce + self.cfg.loss.chamfer_weight * ch if self.use_chamfer else bce
        if self.odometry_sigma is not None:
            total = total + odo
        total.backward()
        return torch.stack([total, bce, ch]).detach()

    def loss_module(self) -> torch.nn.Module:
        """``loss`` as a module over the model ((idx, own) -> (bce, chamfer)); with several workers
        in DistributedDataParallel, built again when the parameters or their use change (placements,
        hand-over, the end of the M-Net warm-up)."""
        # the L-Net gets no gradient in the M-Net warm-up and while poses are optimized directly
        unused = self.mnet_warmup_now() or self.model.direct_poses is not None
        key = (unused, *(id(p) for g in self.model.param_groups() for p in g["params"]))
        if self._step_loss is None or self._step_loss[0] != key:
            self._step_loss = (key, distributed.wrap(_StepLoss(self.model, self.loss), self.device, unused=unused))
        return self._step_loss[1]

    def _check_weights(self) -> None:
        """NonFinite when a weight or pose is NaN/inf: a finite loss with a NaN/inf gradient
        leaves them so (the next step's loss then shows it; this catches the last step's)."""
        sums = [p.detach().sum() for g in self.opt.param_groups for p in g["params"]]
        if sums and not bool(torch.isfinite(torch.stack(sums).sum())):
            raise NonFinite("weights became NaN/inf (a NaN/inf gradient)")

    def use_curriculum_now(self) -> bool:
        return self.use_curriculum and self.state.placed < self.valid.shape[0]

    def log_now(self, loss: float, bce: float, ch: float, on_log=None) -> np.ndarray:
        self.state.elapsed_s = time.perf_counter() - self._t_start
        return self._log(self.state.step, loss, bce, ch, self.state.elapsed_s, on_log)

    # -- consistent states: checkpoints, rollbacks -----------------------------------------
    def boundary(self, path=None, force: bool = False) -> None:
        """Here the state is consistent (an epoch or a curriculum stage and its log are complete):
        keep a copy in memory, the point a NaN/inf step rolls back to and Ctrl-C saves, and
        write it to the checkpoint ``path`` when one is due (every optim.checkpoint_every_s)."""
        self._good = ckpt.capture(self)
        if path and (force or time.perf_counter() - self._last_ckpt > self.cfg.optim.checkpoint_every_s):
            self._write_good(path)

    def _write_good(self, path) -> None:
        if not distributed.is_main():  # one file for the workers' one state
            return
        self.state.elapsed_s = time.perf_counter() - self._t_start
        ckpt.write(path, dict(self._good, elapsed_s=self.state.elapsed_s))
        self._last_ckpt = time.perf_counter()

    def guarded(self, body: Callable):
        """``body()`` (an epoch, a curriculum stage) from the last boundary; when one of its steps
        goes NaN/inf: back to that boundary, every learning rate x ROLLBACK_LR_FACTOR, and again
        (at most MAX_ROLLBACKS times per run, then TrainingError)."""
        while True:
            try:
                out = body()
                self._check_weights()
                return out
            except NonFinite as exc:
                self._roll_back(str(exc))

    def _roll_back(self, what: str) -> None:
        st = self.state
        if len(st.rollbacks) >= MAX_ROLLBACKS:
            raise TrainingError(
                f"training diverged: the {what} at epoch {st.epoch} (step {st.step}) after {MAX_ROLLBACKS} "
                f"rollbacks that each multiplied the learning rates by {ROLLBACK_LR_FACTOR} (now "
                f"{st.lr_scale:g} x the set ones); lower optim.lr (and curriculum.lr) and run again")
        event = {"epoch": st.epoch, "step": st.step, "what": what, "lr_scale": st.lr_scale * ROLLBACK_LR_FACTOR}
        rollbacks = st.rollbacks + [event]
        ckpt.restore(self, self._good)
        st.rollbacks, st.lr_scale = rollbacks, event["lr_scale"]

    # -- the loop -----------------------------------------------------------------------
    def run(self, checkpoint_path=None, on_log: Callable[[dict], None] | None = None,
            on_epoch: Callable[[int, int, float], None] | None = None,
            on_place: Callable[[int, int], None] | None = None) -> TrainState:
        cfg, st = self.cfg.optim, self.state
        self._t_start = time.perf_counter() - st.elapsed_s
        self._last_ckpt = time.perf_counter()
        if st.epoch == 0 and not st.history["iteration"]:
            self._log(0, float("nan"), float("nan"), float("nan"), 0.0, on_log)
        self.boundary()
        try:
            if self.use_curriculum_now():
                t = time.perf_counter()
                curriculum.run(self, checkpoint_path, on_log, on_place)
                self.curriculum_s = time.perf_counter() - t
            if cfg.early_stop_tol and st.early_stop_ref is None:  # training's start (a resumed run has it)
                st.early_stop_ref = self.model.all_poses().cpu().numpy()
                self.boundary()
            while st.epoch < cfg.epochs:
                mean = self.guarded(self._epoch)
                st.epoch += 1
                last = self._after_epoch(mean, on_log)
                self.boundary(checkpoint_path, force=last)
                if on_epoch:
                    on_epoch(st.epoch, cfg.epochs, mean[0])
                if last:
                    break
        except KeyboardInterrupt:  # save the last consistent state: resuming repeats what followed it
            if checkpoint_path:
                self._write_good(checkpoint_path)
            raise Interrupted(checkpoint_path) from None
        return st

    def _epoch(self) -> np.ndarray:
        """One pass over the scans; the mean (loss, bce, chamfer) of its steps (the caller counts it)."""
        self._anneal_mnet()
        rng = np.random.default_rng([self.cfg.seed, self.state.epoch])
        sums = np.zeros(3)
        if self.cfg.optim.batch_order == "place" or self.cfg.loss.chamfer_place_neighbours:
            places = self._places()
        if self.cfg.optim.batch_order == "place":
            batches = place_batches(places, self.cfg.optim.batch_size, rng)
        else:
            batches = epoch_batches(self.valid.shape[0], self.cfg.optim.batch_size, rng, self.cfg.optim.batch_order)
        self._epoch_warmup = self.mnet_warmup_now()  # its loss is not the stopping rule's
        for idx in batches:
            sums += self.step(idx)
        return sums / len(batches)

    def _places(self) -> np.ndarray:
        """Each scan's sensor position and the centre of its points, in the global frame, from the
        poses of the model at the start of an epoch, every optim.eval_every epochs (kept in the checkpoint)."""
        st = self.state
        if st.places is None or (st.epoch % self.cfg.optim.eval_every == 0 and st.places_epoch != st.epoch):
            v = self.valid.to(self.model.scans.dtype)[..., None]
            centre = (self.model.scans * v).sum(1, keepdim=True) / v.sum(1, keepdim=True).clamp(min=1)
            poses = self.model.all_poses()
            sensor = transform(poses, torch.zeros_like(centre))
            st.places = torch.cat([sensor, transform(poses, centre)], -1)[:, 0].cpu().numpy()
            st.places_epoch = st.epoch
        return st.places

    def _after_epoch(self, mean: np.ndarray, on_log) -> bool:
        """Log when due; whether training ends here (last epoch, time budget, early stop)."""
        cfg, st = self.cfg.optim, self.state
        st.elapsed_s = time.perf_counter() - self._t_start
        out_of_time = distributed.any_true(cfg.max_time_s is not None and st.elapsed_s >= cfg.max_time_s, self.device)
        # since the M-Net warm-up, only as many as the stopping rule reads (bounded in every checkpoint)
        st.epoch_losses = [] if self._epoch_warmup else (st.epoch_losses + [float(mean[0])])[-2 * cfg.stop_window:]
        plateau = cfg.stop_min_improvement is not None and loss_plateau(
            st.epoch_losses, cfg.stop_window, cfg.stop_min_improvement)
        last = st.epoch >= cfg.epochs or out_of_time or plateau
        if out_of_time and st.epoch < cfg.epochs:
            st.stop_reason = f"time budget optim.max_time_s = {cfg.max_time_s:g} s"
        elif plateau and st.epoch < cfg.epochs:
            st.stop_reason = (f"the loss improved by less than {100 * cfg.stop_min_improvement:g} % over "
                              f"{cfg.stop_window} epochs (optim.stop_min_improvement)")
        if st.epoch % cfg.eval_every == 0 or last:
            poses = self._log(st.step, *mean, st.elapsed_s, on_log)
            if st.early_stop_ref is not None:
                moved = np.abs(_positions(poses) - _positions(st.early_stop_ref)).max()
                st.early_stop_ref = poses
                if distributed.any_true(moved < cfg.early_stop_tol, self.device) and not last:
                    st.stop_reason = f"the poses moved less than optim.early_stop_tol = {cfg.early_stop_tol:g}"
                    last = True
        return last

    def _anneal_mnet(self) -> None:
        frac = self.cfg.mnet.coarse_to_fine
        enc = getattr(self.model.mnet, "encoding", None)
        if frac > 0 and hasattr(enc, "set_progress"):
            enc.set_progress(self.state.epoch / (frac * self.cfg.optim.epochs))

    def _log(self, step, loss, bce, ch, elapsed, on_log) -> np.ndarray:
        poses = self.model.all_poses().cpu().numpy().astype(np.float64)
        ate = self.evaluate(poses) if self.evaluate else None
        h = self.state.history
        for key, val in zip(ckpt.HISTORY_KEYS, (step, self.state.epoch, elapsed, loss, bce, ch, ate)):
            h[key].append(None if val is None else float(val))
        if on_log:
            on_log({k: h[k][-1] for k in ckpt.HISTORY_KEYS} | {"total_epochs": self.cfg.optim.epochs})
        return poses


class _StepLoss(torch.nn.Module):
    """The model with one step's loss as its forward (what DistributedDataParallel wraps)."""

    def __init__(self, model: DeepMappingModel, loss: Callable):
        super().__init__()
        self.model, self._loss = model, loss

    def forward(self, idx: torch.Tensor, own: int | None = None):
        return self._loss(idx, own)
