"""The registration methods by name (``--method``, ``--warm-start``): for which data each one runs,
one line on what it does, and how it runs.

``deepmapping`` and ``direct`` are the solver's (the networks, or the same loss over the poses;
``deepmapping.solver``). Every other entry is a classical method, DeepMapping's baselines and its
warm starts: ``run(scans, cfg, init, progress) -> poses`` (2D: (K, 3); 3D: (K, 4, 4)), ``init`` the
initial poses or None, ``progress(done, total)`` after each pair.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from deepmapping.config import Config, LoopClosureConfig
from deepmapping.data import ScanSet
from deepmapping.errors import ConfigError
from deepmapping.methods.goicp import incremental_goicp
from deepmapping.methods.icp import incremental_icp
from deepmapping.methods.icp3d import incremental_icp_3d
from deepmapping.methods.icp_planar import incremental_icp_planar
from deepmapping.methods.kiss_odometry import kiss_icp_poses
from deepmapping.methods.loop_closure import close_loops, data_scale
from deepmapping.methods.multiway import multiway_registration
from deepmapping.methods.pso import incremental_pso

__all__ = ["Method", "METHODS", "CLASSICAL", "WARM_STARTS", "get_method", "run_classical",
           "pairwise_settings"]

# (scans, config, initial poses, progress) -> poses, or (poses, what the method reports of its run)
Run = Callable[[ScanSet, Config, "np.ndarray | None", "Callable[[int, int], None] | None"],
               "np.ndarray | tuple[np.ndarray, dict]"]


@dataclass(frozen=True)
class Method:
    name: str
    dims: tuple[int, ...]  # the scans it registers: 2 (planar laser scans), 3 (clouds, depth images)
    summary: str  # what it does, one line
    scope: str = ""  # the data it is for, when not every kind (the CLI's help: 'loop-closure (2D logs)')
    run: Run | None = None  # None: the solver's (deepmapping, direct)
    hint_other_dims: str = ""  # added to the error on data of the other dimension
    warm_start: bool = True  # classical methods: also offered as a warm start (--warm-start NAME)

    @property
    def label(self) -> str:
        return f"{self.name} ({self.scope})" if self.scope else self.name

    def check(self, scans: ScanSet) -> None:
        """ConfigError when the scans are of a dimension this method does not register."""
        dim = 3 if scans.is_3d else 2
        if dim not in self.dims:
            only = "3D" if dim == 2 else "2D"
            raise ConfigError(f"{self.name} is implemented for {only} scans only{self.hint_other_dims}")


METHODS: dict[str, Method] = {}


def _method(name: str, dims: tuple[int, ...], summary: str, scope: str = "", hint_other_dims: str = "",
            warm_start: bool = True):
    def add(run: Run | None) -> Run | None:
        METHODS[name] = Method(name, dims, summary, scope, run, hint_other_dims, warm_start)
        return run
    return add


_method("deepmapping", (2, 3), "DeepMapping: the L-Net and the M-Net trained on the occupancy loss")(None)
_method("direct", (2, 3), "the same loss optimized directly over the poses")(None)


def _clouds(scans: ScanSet) -> list[np.ndarray]:
    return [p[v].astype(np.float64) for p, v in zip(scans.points, scans.valid)]


def _scales(cfg: Config) -> dict:
    return {"voxel_size": cfg.icp.voxel_size, "max_correspondence_distance": cfg.icp.max_correspondence_distance}


def _incremental_icp(scans: ScanSet, cfg: Config, init, progress, kind: str) -> np.ndarray:
    if not scans.is_3d:  # ours: Open3D's ICP is 3D

        return incremental_icp(scans.points.astype(np.float64), scans.valid, method=kind, initial_poses=init,
                               max_iterations=cfg.icp.max_iterations,
                               max_correspondence_distance=cfg.icp.max_correspondence_distance,
                               recover_margin=cfg.icp.recover_margin, progress=progress)

    return incremental_icp_3d(_clouds(scans), method=kind, init=init, max_iterations=cfg.icp.max_iterations,
                              progress=progress, **_scales(cfg))


@_method("icp-point", (2, 3), "incremental point-to-point ICP")
def _icp_point(scans, cfg, init=None, progress=None):
    return _incremental_icp(scans, cfg, init, progress, "point")


@_method("icp-plane", (2, 3), "incremental point-to-plane ICP")
def _icp_plane(scans, cfg, init=None, progress=None):
    return _incremental_icp(scans, cfg, init, progress, "plane")


def loop_closure_settings(loop: LoopClosureConfig, scale: float, odometry: bool) -> dict:
    """close_loops' keyword arguments from ``loop`` settings: with odometry its motions are the
    sequential matches' prior; without, the previous keyframe's motion is (``loop.constant_velocity``)
    or there is none; ``loop.recognize_places`` "auto" is on with odometry only."""
    constant_velocity = loop.constant_velocity and not odometry
    odometry_sigma = (tuple(loop.odometry_sigma) or None) if odometry or constant_velocity else None
    recognize = odometry if loop.recognize_places == "auto" else loop.recognize_places
    return loop.model_dump() | {"odometry_sigma": odometry_sigma, "scale": scale, "constant_velocity": constant_velocity,
                                "recognize_places": recognize}


@_method("loop-closure", (2,), "incremental ICP, loop closures and a pose graph", "2D logs",
         hint_other_dims=" (3D: multiway)")
def _loop_closure(scans, cfg, init=None, progress=None):
    """Each pair started from ``init`` (e.g. odometry, which then also holds the sequential matches,
    ``loop.odometry_sigma``) or from the identity (no odometry, no prior; methods.loop_closure);
    lengths scaled to the scans' ranges (``loop.scale``, methods.loop_closure.data_scale)."""
    scale = data_scale(scans.points, scans.valid) if cfg.loop.scale == "auto" else cfg.loop.scale
    settings = loop_closure_settings(cfg.loop, scale, odometry=init is not None)
    guess = scans.identity_poses() if init is None else init
    poses, edges = close_loops(scans.points, scans.valid, guess, **settings, progress=progress)
    return poses, {"loop_scale": scale, "loop_closures": sum(e.j - e.i > 1 for e in edges)}


@_method("icp-planar", (3,), "ICP over (x, z, yaw) with yaw hypotheses", "3D, planar poses")
def _icp_planar(scans, cfg, init=None, progress=None):
    if scans.pose_dof != 3:
        raise ConfigError("icp-planar estimates planar [x, z, theta] poses: it needs 3-DoF scans (pose_dof 3)")

    return incremental_icp_planar(_clouds(scans), init=init, yaw_hypotheses_deg=cfg.icp.yaw_hypotheses_deg,
                                  progress=progress, **_scales(cfg))


@_method("multiway", (3,), "Open3D's multiway registration (pairwise ICP and a pose graph)", "3D")
def _multiway(scans, cfg, init=None, progress=None):
    return multiway_registration(_clouds(scans), init=init, edges=cfg.icp.multiway_edges, progress=progress,
                                 **_scales(cfg))


@_method("kiss-icp", (3,), "KISS-ICP's LiDAR odometry", "3D sequences, KISS-ICP odometry")
def _kiss_icp(scans, cfg, init=None, progress=None):
    return kiss_icp_poses(_clouds(scans), init=init, voxel_size=cfg.icp.voxel_size, threads=cfg.threads or 1,
                          progress=progress)


GOICP_S_PER_SCAN = 0.5  # Go-ICP's budget when optim.max_time_s is unset (what the 2D experiment gives it)


def pairwise_settings(scans: ScanSet, time_budget_s: float | None) -> dict:
    """Go-ICP and PSO as the paper's 2D baselines (here and in the 2D experiment): each scan onto its
    predecessor, 10 % of the points trimmed, the whole sequence within ``time_budget_s``; distance
    transforms of 1024^2 cells (~2.9 px on the paper's maps) for scans of 256+ beams, 512^2 below."""
    return {"time_budget_s": time_budget_s, "trim_fraction": 0.1,
            "dt_size": 1024 if scans.points.shape[1] >= 256 else 512}


@_method("goicp", (2,), "Go-ICP, globally optimal pairwise registration by branch and bound, motions chained",
         "2D, pairwise", warm_start=False)
def _goicp(scans, cfg, init=None, progress=None):
    """Unset ``optim.max_time_s``: GOICP_S_PER_SCAN per scan (to optimality can take hours). Each pair
    starts with ICP from the constant-velocity guess, so a short budget still returns ICP's pose."""
    settings = pairwise_settings(scans, cfg.optim.max_time_s)
    if settings["time_budget_s"] is None:
        settings["time_budget_s"] = GOICP_S_PER_SCAN * scans.num_scans
    poses, info = incremental_goicp(scans.points, scans.valid, mse_threshold=1e-5, progress=progress, **settings)
    return poses, info


@_method("pso", (2,), "particle swarm registration of each scan onto its predecessor, motions chained",
         "2D, pairwise", warm_start=False)
def _pso(scans, cfg, init=None, progress=None):
    """Unset ``optim.max_time_s``: one round (swarm) per pair."""
    poses, info = incremental_pso(scans.points, scans.valid, seed=cfg.seed, progress=progress,
                                  **pairwise_settings(scans, cfg.optim.max_time_s))
    return poses, info


CLASSICAL = tuple(name for name, m in METHODS.items() if m.run is not None)
WARM_STARTS = tuple(name for name in CLASSICAL if METHODS[name].warm_start)


def get_method(name: str) -> Method:
    if name not in METHODS:
        raise ConfigError(f"unknown method {name!r} (one of: {', '.join(METHODS)})")
    return METHODS[name]


def run_classical(scans: ScanSet, cfg: Config, name: str, init=None, progress=None,
                  info: dict | None = None) -> np.ndarray:
    """The poses of a classical method (``CLASSICAL``); ConfigError for data it does not handle.
    ``info``, when given, receives what the method reports about its run (Go-ICP: pairs solved to
    optimality, seconds per pair); a method's ``run`` returns poses or (poses, that dict)."""
    m = get_method(name)
    if m.run is None:
        raise ConfigError(f"{name} is not a classical registration method (one of: {', '.join(CLASSICAL)})")
    m.check(scans)
    out = m.run(scans, cfg, init, progress)
    poses, reported = out if isinstance(out, tuple) else (out, {})
    if info is not None:
        info.update(reported)
    return poses
