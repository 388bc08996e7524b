"""A map that follows the data: the 3D M-Net's finest detail from the point spacing and the
map's extent (``mnet.fourier_period_spacings``), and the occupancy export's voxel from it.

The fixed Fourier encoding of the fast profiles (16 bands up to frequency 32 on the map
normalized to [-1, 1]) has a finest period of 3 % of the map: 3.4-7.8 point spacings on the
bunny, the AVD-like rooms and 7-Scenes, 72 on the 3DTK outdoor scans (32 m of scene sampled
every 1.6 cm). With the rule the finest period is at most ``fourier_period_spacings`` point
spacings; where the fixed encoding is already that fine nothing changes.

And a step that follows the scans' size (``resolve_step``): ``lnet.stride`` and
``loss.beams_per_scan`` "auto".
"""

from __future__ import annotations

import math

import numpy as np

from deepmapping.config import Config, MNetConfig
from deepmapping.methods.icp3d import point_spacing as spacing

LONG_SCAN_BEAMS = 128  # "auto" step: scans of this many beams or more (and depth images) take the cheap step
CHEAP_STEP = {"stride": 2, "beams_per_scan": 32}  # on long scans: same accuracy, 2.2x less time (docs/method.md)
SHORT_STEP = {"stride": 1, "beams_per_scan": 64}  # shorter scans: stride 2 leaves 8 of 64 beams, 32 beams measured worse


def resolve_step(cfg: Config, num_points: int, grid_shape: tuple[int, int] | None) -> Config:
    """``cfg`` with ``lnet.stride`` and ``loss.beams_per_scan`` "auto" made numbers: CHEAP_STEP for
    depth images and scans of at least LONG_SCAN_BEAMS beams, SHORT_STEP for shorter ones."""
    step = CHEAP_STEP if grid_shape is not None or num_points >= LONG_SCAN_BEAMS else SHORT_STEP
    lnet, loss = cfg.lnet, cfg.loss
    if lnet.stride == "auto":
        lnet = lnet.model_copy(update={"stride": step["stride"]})
    if loss.beams_per_scan == "auto":
        loss = loss.model_copy(update={"beams_per_scan": step["beams_per_scan"]})
    return cfg.model_copy(update={"lnet": lnet, "loss": loss})


EXPORT_MIN_CELLS, EXPORT_MAX_CELLS = 64, 128  # occupancy export: cells along the map's longest side


def point_spacing(points: np.ndarray, valid: np.ndarray) -> float:
    """Median nearest-neighbour distance within a scan (a few evenly spread scans), data units."""
    return spacing([p[v] for p, v in zip(points, valid)])


def fourier_encoding(cfg: MNetConfig, spacing: float, scale: float) -> tuple[float, int]:
    """(highest frequency, number of bands) of the M-Net's Fourier encoding for data sampled every
    ``spacing`` on a map of half-extent ``scale`` (both in data units): the configured ones, or
    with ``fourier_period_spacings`` > 0 a highest frequency raised so that the finest period
    (2 / f in normalized units) is at most that many spacings, with bands added at the same log
    spacing (band k at f_max^(k / (n - 1)))."""
    base, bands = cfg.fourier_max_freq, cfg.fourier_features
    if cfg.kind != "fourier" or cfg.fourier_period_spacings <= 0 or bands < 2 or not spacing > 0:
        return base, bands
    wanted = 2.0 * scale / (cfg.fourier_period_spacings * spacing)
    if wanted <= base or base <= 1.0:
        return base, bands
    return wanted, 1 + round((bands - 1) * math.log(wanted) / math.log(base))


def resolve(cfg: MNetConfig, spacing: float, scale: float) -> tuple[MNetConfig, dict]:
    """The M-Net settings the model is built with, and what to report (data units)."""
    f, n = fourier_encoding(cfg, spacing, scale)
    report = {"point_spacing": spacing, "map_half_extent": scale, "fourier_max_freq": f, "fourier_features": n,
              "finest_period": 2.0 * scale / f if cfg.kind == "fourier" and n else None,
              "grid_finest_cell": 2.0 * scale / cfg.grid_finest if cfg.kind == "grid" else None}
    return cfg.model_copy(update={"fourier_max_freq": f, "fourier_features": n}), report


def export_voxel(extent: float, finest_period: float | None) -> float:
    """Occupancy export voxel: half the M-Net's finest period, between EXPORT_MIN_CELLS and
    EXPORT_MAX_CELLS cells along the longest side (memory: at most 128^3 float32, 8 MB)."""
    lo, hi = extent / EXPORT_MAX_CELLS, extent / EXPORT_MIN_CELLS
    return hi if finest_period is None else float(np.clip(finest_period / 2.0, lo, hi))
