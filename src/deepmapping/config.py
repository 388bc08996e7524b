"""One typed configuration with nested sections, and named profiles.

The profiles are files, ``profiles/<name>.yaml``: ``paper`` reproduces §4.1 of the paper exactly
(networks, 19 free-space samples per beam, batch 128, 3000 epochs); ``default`` is the fast path
(see docs/method.md for what changed and why it is still DeepMapping); each file says what it is
for. ``resolve_profile`` picks the one a run uses.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from deepmapping.errors import ConfigError

Method = Literal["deepmapping", "direct", "icp-point", "icp-plane", "icp-planar", "multiway", "loop-closure",
                 "kiss-icp", "goicp", "pso"]
WarmStart = Literal["none", "icp-point", "icp-plane", "icp-planar", "multiway", "loop-closure", "kiss-icp", "file",
                    "auto"]


class _Section(BaseModel):
    # unknown keys and NaN / inf are errors; numbers that make no sense (negative epochs, lr <= 0,
    # a negative voxel size, ...) are refused by the bounds of each field
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


PosInt = Annotated[int, Field(ge=1)]
PosFloat = Annotated[float, Field(gt=0)]
NonNegFloat = Annotated[float, Field(ge=0)]
NonNegInt = Annotated[int, Field(ge=0)]


class LNetConfig(_Section):
    """L-Net f_theta: 1D atrous CNN over the organized scan, global max-pool, MLP -> (tx, ty, theta)."""

    # "auto": a CNN for organized scans (2D scans, depth images), PointNet for unorganized clouds
    extractor: Literal["auto", "cnn", "pointnet"] = "auto"
    conv_channels: list[PosInt] = [64, 128, 1024]
    kernel_size: int = Field(3, ge=1)
    dilation: int = Field(2, ge=1)
    # convolution stride (1 in the paper; >1 makes the L-Net cheap); "auto": 2 for depth images and
    # for scans of 128 beams or more, else 1 (solver.resolution.resolve_step)
    stride: PosInt | Literal["auto"] = 1
    point_channels: list[PosInt] = [64, 128, 256, 1024]  # PointNet's shared MLP (supplementary A)
    # 3D: the L-Net's correction turns a scan about its sensor (as the paper) or about the
    # scan's centroid (better conditioned when the sensor is far from what it sees, e.g. the bunny)
    pivot: Literal["sensor", "centroid"] = "sensor"
    fc_channels: list[PosInt] = [512, 256]
    zero_init_output: bool = False  # start as identity correction when warm-started
    # Standardize the pooled and hidden features with statistics fixed by one pass over all
    # scans at the start. Without it the features of all scans are nearly parallel, and the
    # L-Net learns one shared correction first and per-scan corrections very slowly.
    feature_norm: bool = False
    feature_std_floor: float = Field(0.0, ge=0)  # Standardize: std >= this x the layer's mean std (0 = off)
    # L-Net learning rate = optim.lr * lr_factor (direct poses use optim.lr); "auto": api.START_SETTINGS,
    # 0.05 from a loop-closure start (not a keyframed log's), else 0.1 (a model built directly from "auto"
    # takes 0.1)
    lr_factor: NonNegFloat | Literal["auto"] = 1.0
    # the PointNet L-Net's (unorganized clouds) instead, when set: few clouds standardized over few
    # samples make its corrections jumpy at the depth-image CNN's rate (3DTK, docs/3d.md)
    pointnet_lr_factor: float | None = Field(None, ge=0)
    # Also feed the L-Net its scan's warm-start pose (x, y, cos, sin with this many Fourier
    # frequencies; 0 = the scan only, as in the paper).
    pose_input_freqs: int = Field(0, ge=0)


class MNetConfig(_Section):
    """M-Net m_phi: global coordinate -> occupancy logit."""

    # "resmlp": residual blocks RB(n) of two FC(n) layers, one per entry of ``hidden``
    # (supplementary A: RB(64)-RB(64)-RB(64)-RB(128)-RB(128))
    # "auto" (default profile): "grid" from a loop-closure start (not a keyframed log's), else "fourier"
    # (api.START_SETTINGS; a model built directly from "auto" takes "fourier")
    kind: Literal["mlp", "resmlp", "fourier", "grid", "auto"] = "mlp"
    hidden: list[PosInt] = [64, 512, 512, 256, 128]
    fourier_features: int = Field(0, ge=0)  # number of log-spaced frequencies per axis (kind="fourier")
    fourier_max_freq: float = Field(32.0, gt=0)  # highest frequency: period 2/f on the map normalized to [-1, 1]
    # > 0: a map that follows the data (3D). The finest period becomes at most this many point
    # spacings (the median nearest-neighbour distance within a scan): the highest frequency is
    # raised above fourier_max_freq where the map is large for its sampling (an outdoor scan), and
    # bands are added at the same log spacing; solver.resolution computes it, run.json reports it
    fourier_period_spacings: float = Field(0.0, ge=0)
    grid_levels: int = Field(6, ge=1)  # kind="grid": multi-resolution feature grids
    grid_features: int = Field(4, ge=1)
    grid_base: int = Field(16, ge=1)  # coarsest resolution (cells across the map)
    grid_finest: int = Field(512, ge=1)
    lr_factor: float = Field(1.0, ge=0)  # M-Net learning rate = optim.lr * lr_factor
    # kind="fourier": open the frequency bands coarse to fine over this fraction of the epochs
    # (BARF-style; 0 = all bands from the start); kind="grid": the levels, likewise
    coarse_to_fine: float = Field(0.0, ge=0, le=1)


class LossConfig(_Section):
    free_samples: int = Field(19, ge=0)  # free-space samples per beam (paper: 19)
    free_sampling: Literal["uniform", "stratified"] = "uniform"
    # extra free-space samples on each beam just before its hit; "auto" (default profile): 4 from a loop-closure
    # start (not a keyframed log's), else 0 (api.START_SETTINGS; a Trainer built directly from "auto" takes 0)
    near_hit_samples: NonNegInt | Literal["auto"] = 0
    near_hit_distance: float = Field(0.02, ge=0)  # ... within this distance of the hit (normalized map units)
    # None = every beam each step; else a random subset of this many; "auto": 32 for depth images and
    # scans of 128 beams or more, else 64 (solver.resolution.resolve_step)
    beams_per_scan: PosInt | Literal["auto"] | None = None
    chamfer_weight: float = Field(10.0, ge=0)  # lambda of eq. 6 (paper: 10 for 2D)
    chamfer_window: int = Field(1, ge=0)  # N(i) = {i-w, ..., i+w} \ {i}
    # eq. 5's distance to the nearest point: "point" (the paper's), or "plane": along the nearest
    # point's surface normal (normals from each scan's own 16 nearest points)
    chamfer_metric: Literal["point", "plane"] = "point"
    # None: every distance counts (the paper's); a number t: a point whose nearest neighbour is further than
    # t x the scans' median point spacing counts t x that spacing (no gradient): parts seen by one scan only
    chamfer_truncate: float | None = Field(None, gt=0)
    # > 0: each scan of a batch also paired with its this many nearest scans of the batch by place
    # (sensor position and the centre of its points, from the poses; revisits), as well as with its
    # temporal neighbours: with optim.batch_order "place", loops are pulled together
    chamfer_place_neighbours: int = Field(0, ge=0)
    # The odometry factor (3D ordered scans): the warm start's relative motion between temporal
    # neighbours as a soft constraint, mean over pairs of |dt / sigma_t|^2 + (dtheta / sigma_r)^2
    # added to the loss; [sigma_t in the scans' units (metres), sigma_r in degrees]. "auto": on when
    # the warm start is the scans' own recorded poses (3DTK's .pose files), sigma at least [0.5, 10] and
    # 8 x how far ICP from them moves their relative motions (api.resolve_odometry_sigma); off for every other start
    # (an ICP start's errors would be held); "off": never.
    odometry_sigma: str | list[float] = "auto"

    @field_validator("odometry_sigma", mode="before")
    @classmethod
    def _odometry_sigma(cls, v):
        v = "off" if v is False or v is None else v  # YAML reads an unquoted off / no / null so
        ok = v in ("auto", "off") or (isinstance(v, (list, tuple)) and len(v) == 2 and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and 0 < x < float("inf") for x in v))
        if not ok:
            raise ValueError(f"must be 'auto', 'off' or [sigma_t, sigma_r_deg] (two numbers > 0), got {v!r}")
        return v if isinstance(v, str) else [float(x) for x in v]


class OptimConfig(_Section):
    lr: float = Field(1e-3, gt=0)
    batch_size: int = Field(128, ge=1)
    # "contiguous": blocks of consecutive scans (temporal neighbours together); "random": any scans together;
    # "place": scans that see the same place together (trainer.place_batches; with loss.chamfer_window >=
    # the scan count, the Chamfer term over every pair a batch holds); "auto": api.START_SETTINGS, random
    # from a loop-closure start (not a keyframed log's), else contiguous (a Trainer built directly from
    # "auto" takes contiguous)
    batch_order: Literal["contiguous", "random", "place", "auto"] = "contiguous"
    # a batch's loss taken in this many parts, one after the other, their gradients summed before the
    # step (one process): the step of the whole batch, the memory of a part
    batch_parts: int = Field(1, ge=1)
    epochs: int = Field(3000, ge=0)
    max_time_s: NonNegFloat | None = None  # stop after this much wall time (None = no limit)
    # first epochs train the M-Net only (poses held at the warm start); "auto": api.START_SETTINGS, 25 when the
    # warm start is loop closure (its poses are nearer than the loss's first steps leave them), else none
    mnet_warmup_epochs: NonNegInt | Literal["auto"] = 0
    # ... and at least this many first optimizer steps: a run over few scans has few steps an epoch
    mnet_warmup_steps: int = Field(0, ge=0)
    lr_final_factor: float = Field(1.0, ge=0)  # cosine decay to lr * factor (1.0 = constant lr, as the paper)
    eval_every: int = Field(50, ge=1)  # evaluate ATE (when gt known) and log every N epochs
    early_stop_tol: NonNegFloat | None = None  # stop when poses move less than this (units) over a log interval
    # The stopping rule (None = off): training ends when the mean loss of the last stop_window
    # epochs is lower than that of the stop_window epochs before them by less than this fraction
    # of it (the loss has stopped improving); optim.epochs stays the upper bound. Epochs of the
    # M-Net warm-up (poses held) do not count.
    stop_min_improvement: NonNegFloat | None = None
    stop_window: PosInt = 20
    checkpoint_every_s: float = Field(30.0, ge=0)


class CurriculumConfig(_Section):
    """Cold start (warm_start.method = "none"): the paper's SLAM setting (§3.4) as a schedule.

    Scans enter the map in sequence order, ``chunk`` at a time. Each new scan is placed where
    its predecessor is, moved on by the last motion (constant velocity), and turned by the
    best of ``hypotheses`` candidate headings, the one with the lowest DeepMapping loss (eq. 4
    under the current M-Net + lambda x Chamfer to its predecessor); then ``steps`` optimizer
    steps of the same loss move the placements and train the M-Net on the newest ``window``
    scans and ``revisit`` random earlier ones. When every scan is placed, the placements are the
    warm start of ordinary training (T_i = T_place,i ∘ f_theta(S_i)). No ICP, no
    correspondence search beyond the Chamfer term's nearest neighbours.
    """

    # "auto": on for a cold start (warm_start none) of an ordered sequence of 2D scans or planar
    # (AVD-like) 3D poses; 6-DoF poses start from the identity
    enabled: Literal["auto", "on", "off"] = "auto"
    chunk: int = Field(4, ge=1)
    steps: int = Field(30, ge=0)
    window: int = Field(16, ge=2)
    revisit: int = Field(16, ge=0)
    lr: float = Field(3e-3, gt=0)  # constant, for the placements and the M-Net
    hypotheses: int = Field(32, ge=1)  # the constant-velocity heading + (hypotheses - 1) random turns
    max_turn_deg: float = Field(30.0, ge=0, le=180)  # random turns are uniform in +- this
    max_shift: float = Field(0.25, ge=0)  # random shifts within this x the scan's median range
    rounds: int = Field(3, ge=1)  # rounds of hypotheses, each around the best with half the spread
    # hypotheses are ranked by select_bce_weight x eq. 4 + loss.chamfer_weight x Chamfer. 0.1, not
    # 1: under an M-Net that has seen only the placed scans, eq. 4 charges a new scan's points in
    # unseen space and so prefers it back inside the known map (a corridor: no motion); the
    # Chamfer term prefers the truth there (docs/method.md, "Ranking: less weight on eq. 4")
    select_bce_weight: float = Field(0.1, ge=0)
    # hypotheses are ranked on at most this many points of each scan (dense depth images: a
    # fixed random subset of the valid ones; 2D scans of <= 512 beams: all)
    select_points: int = Field(512, ge=16)
    # > 0: rank by select_bce_weight x eq. 4 + select_chamfer_weight x the Chamfer distance with
    # each nearest-neighbour distance capped at select_truncate x the scan's median range (and
    # divided by that cap); for views that overlap only in part (depth images)
    select_truncate: float = Field(0.0, ge=0)
    select_chamfer_weight: float = Field(1.0, ge=0)
    # > 0: the refine_top best hypotheses (of all rounds) each take refine_steps Adam steps
    # (lr refine_lr, normalized units) of the ranking loss before the final ranking
    refine_top: int = Field(0, ge=0)
    refine_steps: int = Field(20, ge=1)
    refine_lr: float = Field(0.01, gt=0)
    # > 0: before the rounds, a wide search: this many hypotheses uniform within wide_shift x the
    # median range of both centres and +- wide_turn_deg, ranked on wide_points points of the new
    # scan; the wide_refine best of its wide_keep are refined (as refine_top) and replace the
    # rounds' choice where their loss is lower (larger motions: every 8th scan and beyond).
    # It runs for the second scan, and for later ones when the median motion between the placed
    # scans exceeds wide_trigger x the rounds' spread (max_shift, max_turn_deg): slow sequences skip it
    wide_hypotheses: int = Field(2048, ge=0)  # 0: off
    wide_trigger: float = Field(0.5, ge=0)
    wide_shift: float = Field(1.5, ge=0)
    wide_turn_deg: float = Field(120.0, ge=0, le=180)
    wide_points: int = Field(16, ge=8)
    wide_keep: int = Field(64, ge=1)
    wide_refine: int = Field(32, ge=1)
    # the wide search's screen ranks by wide_bce_weight x eq. 4 + the Chamfer term (None: as
    # select_bce_weight; 0: Chamfer only, the M-Net not evaluated: fast on dense scans); its refined
    # best replaces the rounds' choice only if its loss is lower by more than wide_margin x theirs
    wide_bce_weight: float | None = Field(None, ge=0)
    wide_margin: float = Field(0.0, ge=0)
    wide_heading_only: bool = False  # True: take only its heading, the position from the rounds
    # where the wide search runs but the free-space check does not (the smaller motions), it runs
    # smaller: small_wide_hypotheses within small_wide_shift x the median range and
    # +- small_wide_turn_deg, the small_wide_refine best of its small_wide_keep refined
    # (0 hypotheses: the full size wherever it runs)
    small_wide_hypotheses: int = Field(1024, ge=0)
    small_wide_shift: float = Field(0.75, ge=0)
    small_wide_turn_deg: float = Field(90.0, ge=0, le=180)
    small_wide_keep: int = Field(16, ge=1)
    small_wide_refine: int = Field(8, ge=1)
    # + free_space_weight x how far the new scan's points lie in front of what the predecessor saw
    # along its pixels (2D: beams), and back (eq. 4's free-space labels from the two scans
    # themselves, not the M-Net): per point 0 within free_space_tolerance x the scan's median
    # range, rising to 1 at (1 + free_space_ramp) x that tolerance.
    # It runs for the second scan, and for later ones when the median motion between the placed
    # scans exceeds free_space_trigger x the rounds' spread (as wide_trigger)
    free_space_weight: float = Field(3.0, ge=0)  # 0: off
    free_space_trigger: float = Field(1.0, ge=0)
    free_space_tolerance: float = Field(0.05, gt=0)
    free_space_ramp: float = Field(10.0, gt=0)
    # 2D, where the free-space check runs: + turn_prior x (1 - cos(turn from the predecessor)) / 2, so
    # a corridor scan turned 180 deg onto its predecessor does not outrank the truth (0: off)
    turn_prior: float = Field(0.3, ge=0)
    # once every scan is placed, a placed scan far from both temporal neighbours while they agree (the
    # smaller of its Chamfer distances to them over review_ratio x theirs to each other) is placed again
    # by the rounds, around where it is and between the neighbours; the new place is taken if its loss
    # (with the Chamfer term to both) is lower by more than review_margin x the current one; at most
    # review_max scans, the highest ratios first (review_ratio 0: off)
    review_ratio: float = Field(1.5, ge=0)
    review_max: int = Field(16, ge=0)
    review_margin: float = Field(0.1, ge=0)
    log_every: int = Field(8, ge=1)  # log (loss, ATE) every N stages


class ICPConfig(_Section):
    max_iterations: int = Field(50, ge=0)
    max_correspondence_distance: PosFloat | None = None  # None = adaptive to the scan scale
    # 2D incremental ICP: a pair is also registered from the identity and by a bounded untrimmed
    # ICP, and takes that result when its overlap beats the constant-velocity one by this (None: off)
    recover_margin: float | None = 0.05
    voxel_size: PosFloat | None = None  # 3D: downsampling voxel before ICP / multiway (None = adaptive)
    multiway_edges: str = "all"  # 3D multiway registration: "all" pairs or "window:N"
    # icp-planar (3-DoF AVD-like poses): yaw offsets tried per pair, the best fitness wins
    yaw_hypotheses_deg: list[float] = [0.0, 30.0, -30.0]


class LoopClosureConfig(_Section):
    """``--method loop-closure`` / ``--warm-start loop-closure`` (2D, long sequences;
    methods.loop_closure.close_loops takes these as its keyword arguments). The lengths below
    (metres) are for scans whose median return range is 2 m, the indoor CARMEN logs they were
    tuned on; ``scale`` multiplies every one of them (and the pose graph's translation sigma)."""

    # "auto": the scans' median return range / 2 m (methods.loop_closure.data_scale: intel, fr079,
    # mit-csail 0.98-1.04; a hospital log with 10 m ranges 4.9; our simulator, in px/512, 0.10)
    scale: PosFloat | Literal["auto"] = "auto"

    # earlier keyframes within ``radius`` of a new one and at least ``min_gap`` keyframes back are
    # matched (up to ``max_candidates``); a match is kept when ``min_overlap`` of its points lie
    # within ``inlier_distance``
    radius: float = Field(4.0, gt=0)
    min_gap: int = Field(30, ge=1)
    max_candidates: int = Field(3, ge=0)
    min_overlap: float = Field(0.7, ge=0, le=1)
    inlier_distance: float = Field(0.1, gt=0)
    sequential_submap: int = Field(5, ge=1)  # each keyframe is matched to its last N keyframes merged
    sequential_method: Literal["point", "plane"] = "plane"
    # the odometry motion as a prior of each sequential point-to-line match: (metres, degrees)
    # standard deviations; [] = none (corridors then let matches slide)
    odometry_sigma: list[PosFloat] = [0.1, 5.0]
    # scans without odometry (a simulated trajectory, a folder of scans): true = each sequential match
    # starts from the previous keyframe's motion (constant velocity), held by odometry_sigma as odometry
    # would be; false = from the identity with no prior, where a straight corridor lets a match slide.
    # Off by default: on the paper's 75 trajectories 5 loop closures end over 1 px from the truth
    # against 7, but a 4096-scan one goes from 2.15 to 9.98 px (docs/results.md)
    constant_velocity: bool = False
    # a loop closure is kept only where the matched walls fix both translation directions:
    # smaller / larger eigenvalue of the inliers' mean n n^T (0 = a straight corridor)
    min_constraint: float = Field(0.2, ge=0, le=1)
    # ... and where it makes the map contradict itself (eq. 4's contradiction: returns where the
    # other visit's beams passed) no more than this: the smaller of the two visits' fractions of
    # returns in the other's free space (1 = no test; 0.05 from fr079's kept closures, 99th percentile)
    max_free_conflict: float = Field(0.05, ge=0, le=1)
    # ... and where it moves the keyframe by at most this fraction of the shortest path between the
    # two through the pose graph (at least 3 x inlier_distance, at most radius): a repeated room
    # matches as well as the true one, but further off than drift along that path explains
    max_drift: PosFloat = 0.2
    # a kept closure is refined by point-to-line ICP within inlier_distance over the pairs whose two
    # sensors see the surface from the same side: a wall seen from both rooms would otherwise pull the
    # match by its thickness towards its other face
    refine_closures: bool = True
    # a keyframe that closed no loop near its estimate also looks for its place among all earlier
    # keyframes (a descriptor, then a match at any heading), kept where three neighbouring keyframes
    # agree: loops whose return drift has put metres off (methods.loop_closure._recognize).
    # "auto": on for logs with odometry, off for scans without (where it was measured); a group is
    # adopted only where the map it bends contradicts itself no more than before (fr-clinic, no
    # reference: a look-alike group would have folded the campus by 245 m; docs/results.md)
    recognize_places: bool | Literal["auto"] = "auto"


class WarmStartConfig(_Section):
    # "auto" (3D): icp-planar for AVD-like depth images with planar poses (6-DoF ICP from the
    # identity is wrong on most of their 30 deg turns), icp-plane for 6-DoF depth images
    # (handheld, 7-Scenes) and point-cloud sequences
    # 2D: icp-plane for scans, loop-closure for keyframed logs (CARMEN) and ordered scans of 128 or more
    method: WarmStart = "auto"
    path: str | None = None  # initial poses file (method="file")


class EvalConfig(_Section):
    # ATE below this (in reporting units: px for 2D, mm for depth images) = success. None = 20 px
    # for 2D (supplementary B), 450 mm for AVD-like depth images with planar poses (supplementary
    # C), 2 % of the typical range for other 3D data (evaluation.metrics3d.success_threshold_3d)
    success_threshold: PosFloat | None = None
    # 3D occupancy export (points' units); None = half the M-Net's finest period (64-128 cells a side)
    voxel_size: PosFloat | None = None


class Config(_Section):
    profile: str = "default"
    method: Method = "deepmapping"
    seed: int = Field(0, ge=0, le=2**64 - 1)  # numpy and torch generators take 0 ... 2^64 - 1
    device: Literal["auto", "cpu", "cuda"] = "auto"
    threads: PosInt | None = None  # torch intra-op threads (None = torch default)
    workers: PosInt = 1  # processes training the one map (torch.distributed; solver/distributed.py)
    lnet: LNetConfig = Field(default_factory=LNetConfig)
    mnet: MNetConfig = Field(default_factory=MNetConfig)
    loss: LossConfig = Field(default_factory=LossConfig)
    optim: OptimConfig = Field(default_factory=OptimConfig)
    icp: ICPConfig = Field(default_factory=ICPConfig)
    loop: LoopClosureConfig = Field(default_factory=LoopClosureConfig)
    curriculum: CurriculumConfig = Field(default_factory=CurriculumConfig)
    warm_start: WarmStartConfig = Field(default_factory=WarmStartConfig)
    eval: EvalConfig = Field(default_factory=EvalConfig)

    def to_json(self) -> str:
        return json.dumps(self.model_dump(), indent=2)

    def with_overrides(self, overrides: dict) -> "Config":
        """Apply dotted overrides such as {"optim.epochs": 100}."""
        data = self.model_dump()
        for key, value in overrides.items():
            key = RENAMED.get(key, key)
            node = data
            *parents, leaf = key.split(".")
            for p in parents:
                if p not in node or not isinstance(node[p], dict):
                    raise ConfigError(f"unknown setting {key!r}")
                node = node[p]
            if leaf not in node:
                raise ConfigError(f"unknown setting {key!r}")
            node[leaf] = value
        return validate_config(data)


# The settings whose "auto" api.register resolves from the warm start (api.START_SETTINGS), as they are
# from any start but a loop closure: what a model or Trainer built directly from a config (not through
# api.register) takes for an unresolved "auto".
AUTO_FALLBACKS = {"optim.mnet_warmup_epochs": 0, "mnet.kind": "fourier", "loss.near_hit_samples": 0,
                  "optim.batch_order": "contiguous", "lnet.lr_factor": 0.1}


def unresolved_auto(value, key: str):
    """``value``, or ``AUTO_FALLBACKS[key]`` where it is still "auto"."""
    return AUTO_FALLBACKS[key] if value == "auto" else value


# settings that moved (old dotted name -> new); configs and overrides with the old names still load
RENAMED = {f"icp.loop_{name}": f"loop.{name}" for name in ("radius", "min_gap", "max_candidates", "min_overlap",
                                                          "inlier_distance", "sequential_submap", "sequential_method",
                                                          "odometry_sigma", "min_constraint")}


def migrate_settings(data: dict) -> dict:
    """``data`` with settings under their old names moved to the new ones (RENAMED)."""
    icp = data.get("icp")
    if not isinstance(icp, dict) or not any(f"icp.{k}" in RENAMED for k in icp):
        return data
    data = dict(data)
    data["icp"] = {k: v for k, v in icp.items() if f"icp.{k}" not in RENAMED}
    moved = {RENAMED[f"icp.{k}"].split(".", 1)[1]: v for k, v in icp.items() if f"icp.{k}" in RENAMED}
    data["loop"] = (data["loop"] if isinstance(data.get("loop"), dict) else {}) | moved
    return data


def validate_config(data: dict) -> Config:
    from pydantic import ValidationError

    data = migrate_settings(data)
    try:
        return Config.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(x) for x in err["loc"])
        raise ConfigError(f"invalid setting {loc!r}: {err['msg']}") from None


PROFILE_DIR = Path(__file__).parent / "profiles"
PROFILE_KEYS = ("base", "scans")  # a profile file's own keys: the profile it changes, the kind of scans it is for


def _read_profiles() -> dict[str, dict]:
    """Every named profile, ``profiles/<name>.yaml``: a complete config, or ``base: NAME`` and what
    changes from that profile; ``scans: 2d|3d`` when it is for one kind of scans only."""
    import yaml

    first = ("default", "default-3d", "paper", "paper-3d", "cold", "fast")  # then the others, by name
    files = sorted(PROFILE_DIR.glob("*.yaml"), key=lambda f: (first.index(f.stem) if f.stem in first else len(first), f.stem))
    out = {f.stem: yaml.safe_load(f.read_text(encoding="utf-8")) for f in files}
    if "default" not in out:
        raise ConfigError(f"{PROFILE_DIR}: the profile files are missing (broken install?)")
    return out


PROFILES: dict[str, dict] = _read_profiles()


def resolve_profile(profile: str, is_3d: bool, cold: bool = False, handheld: bool = False) -> str:
    """The profile a run uses: 3D scans get the 3D variant (default -> default-3d, paper ->
    paper-3d), a cold start of the default profile gets ``cold`` (2D), the default profile on
    ``handheld`` 6-DoF depth images (data.ScanSet.handheld) from a warm start gets ``handheld``."""
    if profile not in PROFILES:
        raise ConfigError(f"unknown profile '{profile}' (choose from {', '.join(PROFILES)})")
    if is_3d and PROFILES[profile].get("scans") == "2d":
        raise ConfigError(f"profile {profile!r} is for 2D scans; 3D data: --profile default (default-3d)")
    if is_3d and f"{profile}-3d" in PROFILES:
        profile = f"{profile}-3d"
    if profile == "default" and cold:
        profile = "cold"
    if profile == "default-3d" and handheld and not cold:  # measured from a warm start only
        profile = "handheld"
    return profile


def profile_settings(profile: str) -> dict:
    """The complete settings of a named profile (its base's, then its own changes)."""
    if profile not in PROFILES:
        raise ConfigError(f"unknown profile '{profile}' (choose from {', '.join(PROFILES)})")
    own = {k: v for k, v in PROFILES[profile].items() if k not in PROFILE_KEYS}
    base = PROFILES[profile].get("base")
    if base is None:
        missing = sorted(set(_flatten(Config().model_dump())) - {"profile"} - set(_flatten(own)))
        if missing:
            raise ConfigError(f"{PROFILE_DIR / profile}.yaml: a profile without 'base' lists every setting; "
                              f"missing {', '.join(missing)}")
        return copy.deepcopy(own)  # callers may change what they get; PROFILES stays as read
    return _deep_merge(profile_settings(base), own)


def profile_changes(profile: str) -> dict:
    """What a profile written as ``base`` + changes changes, as dotted keys ({"loss.chamfer_weight": 50.0})."""
    return _flatten({k: v for k, v in PROFILES[profile].items() if k not in PROFILE_KEYS})


def load_config(profile: str = "default", path: str | Path | None = None, overrides: dict | None = None) -> Config:
    """Profile defaults, then a YAML/JSON file, then dotted overrides."""
    data = profile_settings(profile) | {"profile": profile}
    if path is None:
        cfg = validate_config(data)
    else:
        path = Path(path)
        try:
            cfg = validate_config(_deep_merge(data, _read_config_file(path)))
        except ConfigError as exc:
            msg = str(exc)
            raise ConfigError(msg if msg.startswith(f"{path}: ") else f"{path}: {msg}") from None
    return cfg.with_overrides(overrides) if overrides else cfg


def _read_config_file(path: Path) -> dict:
    import yaml

    try:
        loaded = yaml.safe_load(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: cannot read config (not a UTF-8 text file)") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f", line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"{path}: cannot read config ({type(exc).__name__}{where})") from None
    # ValueError: a value YAML cannot build (a date 2020-13-45, !!int x); RecursionError: nested too deep
    except (OSError, ValueError, RecursionError) as exc:
        raise ConfigError(f"{path}: cannot read config ({type(exc).__name__})") from None
    if not isinstance(loaded, dict):
        raise ConfigError(f"{path}: config must be a mapping of sections")
    return loaded


def _flatten(data: dict, prefix: str = "") -> dict:
    """{"a": {"b": 1}} -> {"a.b": 1}"""
    out = {}
    for k, v in data.items():
        out |= _flatten(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v}
    return out


def _deep_merge(base: dict, extra: dict) -> dict:
    out = dict(base)
    for k, v in extra.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out
