"""The library entry point: ``register(scans, config) -> Result``.

The CLI, the benchmarks and the tests all call this function.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from deepmapping.config import AUTO_FALLBACKS, Config, load_config, resolve_profile, validate_config
from deepmapping.data import ScanSet, identity_poses
from deepmapping.errors import ConfigError, InputError
from deepmapping.evaluation import ate, evaluate
from deepmapping.evaluation.evo_metrics import evo_metrics
from deepmapping.evaluation.relations import read_relations, score_relations
from deepmapping.io.poses import read_poses
from deepmapping.io.poses3d import read_poses_3d
from deepmapping.methods.keyframes import place_all_scans
from deepmapping.methods.registry import CLASSICAL, run_classical
from deepmapping.solver import resolution
from deepmapping.solver.frame import Frame


@dataclass
class Result:
    method: str
    poses: np.ndarray  # 2D (K, 3) [x, y, theta]; 3D (K, 4, 4); in the units of the input points
    runtime_s: float
    config: Config
    init_poses: np.ndarray | None = None
    metrics: dict | None = None
    # per-log lists (iteration, epoch, time_s, loss, bce, chamfer, ate) and "rollbacks": one dict
    # per NaN/inf step that training rolled back from (epoch, step, what, lr_scale after it);
    # "stop_reason": why training ended before optim.epochs ("" = it ran them all); "reviewed": the
    # scans the cold-start curriculum's review placed again
    history: dict = field(default_factory=dict)
    occupancy: Callable[[np.ndarray], np.ndarray] | None = None  # M-Net: (M, D) -> p(occupied)
    # trained L-Net (DeepMapping only): (points (M, N, D), valid (M, N), init=None) -> poses of new scans
    localize: Callable[..., np.ndarray] | None = None
    # cold-start curriculum: where it placed each scan (the poses the L-Net's corrections compose with)
    placements: np.ndarray | None = None
    # the M-Net's encoding as built (data units): point spacing, finest period, frequencies, bands
    map_resolution: dict | None = None
    # where the time went (s): "warm_start_s", "curriculum_s" (cold start), "training_s"
    timings: dict = field(default_factory=dict)
    # what a classical method reports about its run (Go-ICP: pairs solved to optimality, ...)
    method_info: dict = field(default_factory=dict)


def register(scans: ScanSet, config: Config | None = None, *, checkpoint: str | Path | None = None,
             resume: bool = False, on_log: Callable[[dict], None] | None = None,
             on_epoch: Callable[[int, int, float], None] | None = None,
             on_icp_progress: Callable[[int, int], None] | None = None,
             on_place: Callable[[int, int], None] | None = None) -> Result:
    """Register the scans with ``config.method`` (deepmapping, direct, icp-point, icp-plane,
    icp-planar, multiway, loop-closure, kiss-icp).

    With no config: the "default" profile for 2D scans, "default-3d" for 3D ones ("handheld" for
    6-DoF depth images). A cold start
    (``warm_start.method = "none"``) of an ordered 2D or planar-3D sequence places the scans by the
    curriculum first (``config.curriculum``; ``on_place(placed, total)`` reports its progress).
    """
    scans.validate()
    cfg = config or load_config(resolve_profile("default", scans.is_3d, handheld=scans.handheld))
    check_settings(scans, cfg)
    t0 = time.perf_counter()
    if cfg.method in BASELINES:  # initial guesses from a pose file, or from a 2D log's own odometry
        init = (warm_start_poses(scans, cfg) if cfg.warm_start.method == "file"
                else None if cfg.warm_start.method == "none" else _log_odometry(scans))
        info: dict = {}
        poses = baseline_poses(scans, cfg, cfg.method, init, on_icp_progress, info=info)
        result = _finish(scans, cfg, poses, t0, init=init)
        result.method_info = info
        return result
    cfg = cfg.with_overrides(start_settings(scans, cfg))
    saved = _load_checkpoint(checkpoint, cfg) if resume else None
    if saved is not None:
        init = np.asarray(saved["init_poses_input"])
        t0 -= saved["elapsed_s"]
    else:
        init = warm_start_poses(scans, cfg, on_icp_progress)
    warm_start_s = time.perf_counter() - t0 if saved is None else 0.0
    result = _train(scans, cfg, init, t0, checkpoint, saved, on_log, on_epoch, on_place)
    result.timings = {"warm_start_s": warm_start_s, **result.timings}
    return result


def check_settings(scans: ScanSet, cfg: Config) -> None:
    """ConfigError for settings that do not fit the scans' kind (raised before any work or output)."""
    if cfg.method in ("deepmapping", "direct") and scans.is_3d and cfg.mnet.kind == "grid":
        raise ConfigError("mnet.kind = grid: the grid M-Net is for 2D scans only; 3D scans take fourier "
                          "(default-3d), mlp or resmlp")


BASELINES = CLASSICAL  # the classical methods (methods.registry): baselines and warm starts


def baseline_poses(scans: ScanSet, cfg: Config, method: str, init=None, progress=None,
                   info: dict | None = None) -> np.ndarray:
    """Classic registration by name (methods.registry): incremental ICP (2D: ours; 3D: Open3D),
    loop closure (2D logs), planar ICP, multiway registration or KISS-ICP odometry (3D)."""
    return run_classical(scans, cfg, method, init, progress, info)


def _log_odometry(scans: ScanSet) -> np.ndarray | None:
    """A 2D log's own poses (its odometry), where 2D ICP and loop closure start each pair, as a warm
    start and as a classical method (``--method loop-closure``, ``icp-*``); None (the identity) otherwise."""
    return scans.init_poses if not scans.is_3d and scans.sequence is not None else None


def warm_start_poses(scans: ScanSet, cfg: Config, progress=None) -> np.ndarray:
    """Initial poses (§3.5): identity (cold start), incremental ICP, or a given pose file."""
    ws = cfg.warm_start
    if ws.method == "auto":
        ws = ws.model_copy(update={"method": auto_warm_start(scans)})
    if ws.method == "none":
        return scans.identity_poses()
    if ws.method == "file":
        if scans.is_3d and scans.init_poses is not None:  # the loader read the file (in the scans' frames)
            return np.asarray(scans.init_poses, dtype=np.float64)
        if ws.path is not None:
            init = _read_init(ws.path, scans.is_3d)
            if init.shape != (scans.num_scans, *scans.pose_shape()):
                raise InputError(f"{ws.path}: {init.shape[0]} initial poses for {scans.num_scans} scans (counts differ)")
        elif scans.init_poses is not None:
            init = scans.init_poses
        else:
            raise ConfigError("warm_start.method is 'file' but no initial pose file was given")
        return np.asarray(init, dtype=np.float64)
    return baseline_poses(scans, cfg, ws.method, _log_odometry(scans), progress)


# warm_start "auto" for ordered 2D scans: loop closures from this many scans on (the paper's 128- and
# 256-scan trajectories: loop closure alone 0.07-0.36 px where point-to-plane ICP is 0.56-3.1 px, and
# DeepMapping from it ends lower than from ICP; simulated 1024 and 4096 scans: ICP drifts 9-55 px)
LONG_SEQUENCE = 128
# Settings "auto" that follow the warm start (start_settings), from a loop-closure start (0.1-0.4 px from
# the truth on the paper's trajectories) and from any other:
# - optim.mnet_warmup_epochs: epochs of M-Net-only training. Released at once, the poses follow an M-Net
#   with no map yet (256 scans: 0.20 px -> 3.9 px at epoch 10); from a point-to-plane ICP start (3.3 px)
#   the warm-up hurt (0.76 -> 2.0 px).
# - mnet.kind: a dense multi-resolution grid (finest cell 1.5-2.2 px on the simulated maps) whose loss has
#   its minimum near the truth (256 scans started at the truth: 0.02 px after 250 epochs, Fourier 0.14 px).
# - loss.near_hit_samples: free-space samples within loss.near_hit_distance before each hit. The stratified
#   ones fall near a wall less often on a long beam than on a short one, so every scan is pushed towards
#   its long beams, the open space: the map shrinks by 0.1-0.3 % (paper trajectory 10: 0.07 -> 0.28 px,
#   0.06 px after a similarity alignment). A fixed number at a fixed distance per beam removes the push
#   (0.010 px). From ICP both changes hurt (256 scans with near-hit samples: 0.76 -> 2.96 px).
# - optim.batch_order: batches of scans drawn at random over the whole trajectory, not stretches of
#   consecutive ones, so that each step's M-Net and L-Net see the whole map, not one part of it after the
#   other (simulated 256 scans: 0.030 -> 0.0067 px and 0.109 -> 0.077; 1024: 0.069 -> 0.065 and 0.061 ->
#   0.054; docs/results.md). The Chamfer term then pairs the few temporal neighbours a batch holds:
#   loop closure has already put them together.
# - lnet.lr_factor: with those batches, the L-Net at half the rate it has from any other start ends
#   nearer on the longer trajectories (256 s1 0.077 -> 0.066 px; 1024 0.065 -> 0.057 and 0.054 -> 0.046)
#   and as near on the others; at three times it the poses do not move from their start (1024: 0.085 px).
# Keyframed logs (CARMEN) start from loop closure too, but keep the Fourier M-Net and no near-hit samples:
# on a building the grid's finest cell is 6-15 cm, 1.4-7 point spacings (0.5 on the simulated maps), and
# there the two changes gave intel 0.0184 -> 0.0182 m, fr079 0.0447 -> 0.0454, mit-csail 0.065 -> 0.082.
LOOP_WARMUP_EPOCHS = 25
START_SETTINGS = {
    "loop-closure": {"optim.mnet_warmup_epochs": LOOP_WARMUP_EPOCHS, "mnet.kind": "grid", "loss.near_hit_samples": 4,
                     "optim.batch_order": "random", "lnet.lr_factor": 0.05},
    "log": AUTO_FALLBACKS | {"optim.mnet_warmup_epochs": LOOP_WARMUP_EPOCHS},
    "other": dict(AUTO_FALLBACKS),
}


def auto_warm_start(scans: ScanSet) -> str:
    """warm_start "auto": planar ICP for AVD-like depth images with planar poses (6-DoF ICP from the
    identity fails on their 30 deg turns), point-to-plane ICP for 6-DoF depth images (handheld:
    on 7-Scenes 6-10 mm, point-to-point 11-14 mm, no registration 60 mm, docs/results.md), point
    clouds and 2D scans; loop closures for keyframed 2D logs (thousands of scans, loops of
    hundreds of metres) and for ordered 2D scans of ``LONG_SEQUENCE`` or more; an ordered 3D
    sequence's own recorded poses where the loader read them (3DTK's .pose files: slam6D starts
    from them; 1.7 cm from its result on our sample, every ICP variant 3-16 cm), held by the
    odometry factor (resolve_odometry_sigma)."""
    if not scans.is_3d:
        long = scans.sequence is not None or (scans.ordered and scans.num_scans >= LONG_SEQUENCE)
        return "loop-closure" if long else "icp-plane"
    if scans.recorded_poses and scans.init_poses is not None and scans.ordered:
        return "file"
    return "icp-planar" if scans.grid_shape is not None and scans.pose_dof == 3 else "icp-plane"


def start_settings(scans: ScanSet, cfg: Config) -> dict:
    """The values this run's settings "auto" of START_SETTINGS take (only those given as "auto"), by the
    warm start as warm_start "auto" resolves it: loop closure (2D; a keyframed log's: "log") or any other."""
    ws = cfg.warm_start.method if cfg.warm_start.method != "auto" else auto_warm_start(scans)
    start = "other" if ws != "loop-closure" or scans.is_3d else "log" if scans.sequence is not None else "loop-closure"
    table = START_SETTINGS[start]
    given = cfg.model_dump()
    return {key: value for key, value in table.items() if given[key.split(".")[0]][key.split(".")[1]] == "auto"}


# loss.odometry_sigma "auto" with the scans' own recorded poses as the warm start: [sigma_t (scan units:
# metres), sigma_r (deg)] = the larger of AUTO_ODOMETRY_SIGMA and AUTO_ODOMETRY_FACTOR x how far
# point-to-plane ICP from the recorded poses moves their relative motions (median): recorded poses
# that the scans contradict are held loosely (docs/results.md: the 3DTK sample, 6.4 cm / 0.81 deg ->
# [0.51 m, 10 deg]; a simulated odometry drifting 10 cm / 2 deg a step -> [1.5 m, 22 deg])
AUTO_ODOMETRY_SIGMA = (0.5, 10.0)
AUTO_ODOMETRY_FACTOR = 8.0
# ... and off when ICP turns the recorded relative motions by more than this (median, deg): the scans
# contradict them (held-out: odometries ICP turned 2.4-2.8 deg ended better with no factor; those it
# turned 0.8-1.0 deg, with it)
AUTO_ODOMETRY_GATE_DEG = 2.0


def resolve_odometry_sigma(scans: ScanSet, cfg: Config) -> tuple[float, float] | None:
    """loss.odometry_sigma for this run (None = no odometry factor), [sigma_t (scan units), sigma_r
    (deg)]: as given, or "auto" = on when the warm start is the ordered 3D scans' own recorded poses
    (``ScanSet.recorded_poses``: the loader read them with the data, as 3DTK's .pose files), off for
    every other start; its sigma from how well those poses agree with the scans, and off when the
    scans contradict them (AUTO_ODOMETRY_SIGMA, AUTO_ODOMETRY_FACTOR, AUTO_ODOMETRY_GATE_DEG)."""
    from deepmapping.methods.icp3d import odometry_agreement

    sigma = cfg.loss.odometry_sigma
    if sigma == "off" or not (scans.is_3d and scans.ordered):
        return None
    if sigma != "auto":
        return float(sigma[0]), float(sigma[1])
    ws = cfg.warm_start.method if cfg.warm_start.method != "auto" else auto_warm_start(scans)
    own = ws == "file" and cfg.warm_start.path is None and scans.recorded_poses and scans.init_poses is not None
    if not own:
        return None
    clouds = [p[v] for p, v in zip(scans.points, scans.valid)]
    trans, rot = odometry_agreement(clouds, scans.init_poses, cfg.icp.voxel_size,
                                    cfg.icp.max_correspondence_distance, cfg.icp.max_iterations)
    if rot > AUTO_ODOMETRY_GATE_DEG:
        return None
    return (max(AUTO_ODOMETRY_SIGMA[0], AUTO_ODOMETRY_FACTOR * trans),
            max(AUTO_ODOMETRY_SIGMA[1], AUTO_ODOMETRY_FACTOR * rot))


def _read_init(path, is_3d: bool) -> np.ndarray:
    if is_3d:
        return read_poses_3d(path)

    return read_poses(path)


def _load_checkpoint(checkpoint, cfg: Config) -> dict | None:
    if checkpoint is None or not Path(checkpoint).exists():
        return None
    from deepmapping.solver import checkpoint as ckpt

    try:
        data = ckpt.load(checkpoint)
    except Exception as exc:  # corrupt file: a torch/pickle error of any kind
        raise InputError(f"{checkpoint}: cannot read checkpoint ({type(exc).__name__})") from None
    # a checkpoint of an older version: its names moved, settings added since take their defaults
    if _saved_settings(data["config"]) != cfg.model_dump():
        raise ConfigError(f"{checkpoint}: was written with other settings; resume with the run's config")
    return data


def _saved_settings(saved: dict) -> dict | None:
    try:
        return validate_config(saved).model_dump()  # validate_config moves old names too
    except ConfigError:
        return None


def resolve_device(name: str) -> str:
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda asked for, but torch sees no CUDA device")
    return name


def _train(scans, cfg, init, t0, checkpoint, saved, on_log, on_epoch, on_place=None) -> Result:
    """DeepMapping (or direct optimization) from ``init``; with ``workers`` > 1 (or under torchrun)
    as worker 0 of several that train the one map (solver.distributed)."""
    from deepmapping.solver import distributed

    def start_others(port: int, addr: str) -> list:
        import torch.multiprocessing as mp

        ctx = mp.get_context("spawn")
        procs = [ctx.Process(target=_worker, args=(r, cfg, scans, init, saved, port, addr)) for r in range(1, cfg.workers)]
        for p in procs:
            p.start()
        return procs

    with distributed.group(cfg.workers, resolve_device(cfg.device), start_others):
        return _train_here(scans, cfg, init, t0, checkpoint, saved, on_log, on_epoch, on_place)


def _worker(rank: int, cfg: Config, scans: ScanSet, init, saved, port: int, addr: str) -> None:
    """A started worker (rank >= 1) of ``_train``: the same training, no output."""
    import signal
    import sys
    import traceback

    from deepmapping.solver import distributed

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is worker 0's to handle (it saves the checkpoint)
    distributed.join_group(rank, cfg.workers, port, addr, resolve_device(cfg.device))
    try:
        _train_here(scans, cfg, init, time.perf_counter(), None, saved, None, None)
    except Exception:  # worker 0 reports the run's error; this worker's own cause goes to stderr
        traceback.print_exc()
        sys.exit(1)
    finally:
        distributed.leave()


def _train_here(scans, cfg, init, t0, checkpoint, saved, on_log, on_epoch, on_place=None) -> Result:
    import os

    import torch

    from deepmapping.solver import checkpoint as ckpt
    from deepmapping.solver import distributed
    from deepmapping.solver.model import DeepMappingModel
    from deepmapping.solver.trainer import Trainer

    device = distributed.local_device(resolve_device(cfg.device))
    init, saved = distributed.from_first((init, saved))  # torchrun: each process loaded and warm-started; worker 0's count
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    elif distributed.active():  # the machine's cores shared by its workers
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // distributed.local_world()))
    torch.manual_seed(cfg.seed)
    frame = Frame.from_scans(scans.points, scans.valid, init)
    pts = torch.as_tensor(scans.points / frame.scale, dtype=torch.float32, device=device)
    valid = torch.as_tensor(scans.valid, device=device)
    mnet_cfg, map_resolution = resolve_map(scans, cfg, frame)
    model = DeepMappingModel(cfg.model_copy(update={"mnet": mnet_cfg}), pts,
                             torch.as_tensor(frame.to_norm(init), dtype=torch.float32, device=device),
                             valid=valid, grid_shape=scans.grid_shape, pose_dof=scans.pose_dof)
    model.to(device)
    if cfg.method == "direct":
        model.make_direct()

    def evaluate(poses_norm: np.ndarray) -> float | None:
        if scans.gt_poses is None:
            return None
        return ate(frame.from_norm(poses_norm), scans.gt_poses) * scans.unit_scale

    # worker 0's (its ICP check alone; ICP may differ in the last bits); the trainer works in the normalized frame
    odometry_sigma = distributed.from_first(resolve_odometry_sigma(scans, cfg) if distributed.rank() == 0 else None)
    odometry_norm = None if odometry_sigma is None else (odometry_sigma[0] / frame.scale, odometry_sigma[1])
    trainer = Trainer(cfg, model, valid, scans.ordered, evaluate, odometry_sigma=odometry_norm)
    trainer.extra = {"init_poses_input": init.tolist(), "frame": frame.to_dict(), "map_resolution": map_resolution}
    if saved is not None:
        ckpt.restore(trainer, saved)
    t_train = time.perf_counter()
    trainer.run(checkpoint, on_log, on_epoch, on_place)
    training_s = time.perf_counter() - t_train
    poses = frame.from_norm(model.all_poses().cpu().numpy().astype(np.float64))
    result = _finish(scans, cfg, poses, t0, init=init)
    result.map_resolution = map_resolution
    result.timings = {"curriculum_s": trainer.curriculum_s, "training_s": training_s - trainer.curriculum_s}
    result.history = dict(trainer.state.history, rollbacks=trainer.state.rollbacks,
                          stop_reason=trainer.state.stop_reason, reviewed=trainer.state.reviewed,
                          odometry_sigma=None if odometry_sigma is None else list(odometry_sigma))
    if trainer.use_curriculum:
        result.placements = frame.from_norm(model.init_poses.cpu().numpy().astype(np.float64))
    result.occupancy = _occupancy_fn(model, frame, device)
    if model.direct_poses is None:
        result.localize = _localize_fn(model, frame, device)
    return result


def resolve_map(scans: ScanSet, cfg: Config, frame):
    """The M-Net settings the model is built with (a resolution that follows the data when
    ``mnet.fourier_period_spacings`` > 0, solver.resolution) and what run.json reports of them."""
    spacing = resolution.point_spacing(scans.points, scans.valid) if cfg.mnet.fourier_period_spacings > 0 else 0.0
    return resolution.resolve(cfg.mnet, spacing, frame.scale)


def _occupancy_fn(model, frame, device):
    import torch

    def occupancy(xy: np.ndarray, chunk: int = 65536) -> np.ndarray:
        q = torch.as_tensor((np.asarray(xy) - frame.center) / frame.scale, dtype=torch.float32, device=device)
        with torch.no_grad():  # in chunks: a picture's million query points stay in bounded memory
            return torch.cat([torch.sigmoid(model.mnet(q[i : i + chunk])) for i in range(0, max(len(q), 1), chunk)]).cpu().numpy()

    return occupancy


def _localize_fn(model, frame, device):
    """``localize(points, valid=None, init=None) -> poses``: the trained L-Net on new scans.

    points (M, N, D) in sensor frames and the input's units (as ``ScanSet.points``), valid
    (M, N) (None = all beams valid); returns poses in the input's units, as ``Result.poses``.
    ``init``: each scan's prior pose, composed with the L-Net's output as in training
    (T = T_init ∘ f(S)) and fed to it when ``lnet.pose_input_freqs`` > 0; None = the identity,
    which is exactly what a cold start without the curriculum (``warm_start.method = "none"``,
    ``curriculum.enabled = "off"``) was trained with; a curriculum run composes f_theta with each
    scan's placement (``Result.placements``), so a new scan needs a prior near its pose.
    """
    import torch

    def localize(points: np.ndarray, valid: np.ndarray | None = None, init: np.ndarray | None = None,
                 chunk: int = 1024) -> np.ndarray:
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 3 or pts.shape[2] != model.scans.shape[2]:
            raise InputError(f"localize: points must be (M, N, {model.scans.shape[2]}), got shape {pts.shape}")
        mask = np.ones(pts.shape[:2], bool) if valid is None else np.asarray(valid, dtype=bool)
        pts = np.where(mask[..., None], pts, 0.0) / frame.scale  # invalid beams enter as zeros, as in training
        if init is None:
            init = identity_poses(len(pts), model.is_3d)
        prior = frame.to_norm(np.asarray(init, dtype=np.float64))
        out = [model.localize(torch.as_tensor(pts[i : i + chunk], dtype=torch.float32, device=device),
                              torch.as_tensor(mask[i : i + chunk], device=device),
                              torch.as_tensor(prior[i : i + chunk], dtype=torch.float32, device=device))
               for i in range(0, len(pts), chunk)]
        return frame.from_norm(torch.cat(out).cpu().numpy().astype(np.float64)) if out else np.asarray(init, float)

    return localize


def _finish(scans: ScanSet, cfg: Config, poses: np.ndarray, t0: float, init) -> Result:
    runtime = time.perf_counter() - t0
    metrics = None
    if scans.gt_poses is not None:
        metrics = evaluate_poses(scans, poses, cfg.eval.success_threshold)
        metrics["runtime_s"] = runtime
    elif scans.sequence is not None and scans.sequence.relations_path is not None:
        metrics = evaluate_relations(scans, poses) | {"runtime_s": runtime}
    return Result(method=cfg.method, poses=poses, runtime_s=runtime, config=cfg, init_poses=init, metrics=metrics)


def evaluate_relations(scans: ScanSet, poses: np.ndarray, relations_path=None) -> dict:
    """Kümmerle et al.'s relations metric of keyframe ``poses`` (2D), every scan of the input
    placed from its nearest keyframe by odometry (see methods.keyframes)."""
    seq = scans.sequence
    path = relations_path or (seq.relations_path if seq is not None else None)
    if seq is None or path is None:
        raise InputError(f"{scans.source}: no relations file to score against")
    scores = score_relations(read_relations(path), seq.stamps, place_all_scans(seq, poses))
    return {"relations": scores, "relations_file": str(path), "unit": scans.unit}


def evaluate_poses(scans: ScanSet, poses: np.ndarray, success_threshold: float | None = None) -> dict:
    """The paper's metrics (ATE, point distance, success; rotation errors) against scans.gt_poses.

    success_threshold None: 20 px (2D), 450 mm for AVD-like depth images (planar poses, the paper's
    protocol), 2 % of the typical range for other 3D data (evaluation.metrics3d.success_threshold_3d)."""
    metrics = evaluate(poses, scans.gt_poses, scans.points, scans.valid, unit_scale=scans.unit_scale,
                       success_threshold=success_threshold,
                       avd_protocol=scans.is_3d and scans.grid_shape is not None and scans.pose_dof == 3)
    return metrics | {"unit": scans.unit, "evo": evo_metrics(poses, scans.gt_poses, scans.unit_scale)}
