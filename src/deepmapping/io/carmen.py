"""CARMEN logs (``.clf`` / ``.log``, plain, ``.gz`` or ``.bz2``): laser scans, odometry, timestamps.

Message layouts (as in the Radish / Freiburg benchmark logs, checked on ``../shared``):

- ``FLASER n r_1 ... r_n x y theta odom_x odom_y odom_theta ipc_timestamp hostname logger_timestamp``;
  the n beams span -90 ... +90 deg evenly (``RLASER`` is the same for a rear laser, not read).
- ``ROBOTLASER1 type start_angle fov resolution max_range accuracy remission_mode n r_1 ... r_n
  m v_1 ... v_m laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv fwd_safety
  side_safety turn_axis ipc_timestamp hostname logger_timestamp``.
- ``ODOM x y theta tv rv accel ipc_timestamp hostname logger_timestamp``.

The pose of a scan line is the laser's pose in the odometry frame (or the corrected pose in a
``*-corrected`` log): it is the warm start. A range at the sensor's maximum (or beyond, or <= 0)
is no return. FLASER has no maximum field: 81.9 m (the SICK's no-return value in most Freiburg
logs), or lower where the log's largest reading repeats often (``saturation_range``: the intel log
writes 81.83 m for no return, 2.8 % of its readings). Malformed lines raise InputError naming the
file and the line.
"""

from __future__ import annotations

import bz2
import gzip
import io
import os
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deepmapping.data import FullSequence, ScanSet
from deepmapping.errors import ConfigError, InputError
from deepmapping.io.atomic import atomic_write
from deepmapping.sequence import select_keyframes

__all__ = ["CarmenLog", "read_carmen", "write_with_poses", "match_scans", "open_text", "is_carmen_file",
           "CARMEN_SUFFIXES", "FLASER_MAX_RANGE", "saturation_range"]

CARMEN_SUFFIXES = (".clf", ".log")
FLASER_MAX_RANGE = 81.9  # the SICK's no-return value in the Freiburg logs (FLASER has no max field)
MAX_RANGE_TOL = 1e-3
SATURATION_SHARE = 1e-3  # the largest reading is a no-return code when this share of readings (and 10) has it


@dataclass
class CarmenLog:
    """The laser messages of one log, in file order (one message type: FLASER or ROBOTLASER1).

    ranges (S, n) metres; angles (S, n) radians in the laser frame (0 = ahead, counter-clockwise;
    per scan: ROBOTLASER1 logs interleave scans with shifted start angles and 180/181 beams;
    a scan with fewer beams is padded with range 0 = no return);
    poses (S, 3) laser pose [x, y, theta] of each scan line; odometry (S, 3) the robot's
    odometry of the line (FLASER's odom fields; ROBOTLASER1's robot pose); timestamps (S,)
    ``ipc_timestamp``; stamps (S,) the same as written in the file (exact matching); lines (S,)
    1-based line numbers; max_range: readings >= this are no return.
    """

    path: str
    message: str
    ranges: np.ndarray
    angles: np.ndarray
    poses: np.ndarray
    odometry: np.ndarray
    timestamps: np.ndarray
    stamps: list[str]
    lines: np.ndarray
    max_range: np.ndarray  # (S,)

    @property
    def num_scans(self) -> int:
        return int(self.ranges.shape[0])

    def valid(self) -> np.ndarray:
        return (self.ranges > 0) & (self.ranges < self.max_range[:, None] - MAX_RANGE_TOL) & np.isfinite(self.ranges)

    def points(self) -> np.ndarray:
        """(S, n, 2) beam end points in the laser frame; no-return beams are (0, 0)."""
        xy = self.ranges[..., None] * np.stack([np.cos(self.angles), np.sin(self.angles)], -1)
        return np.where(self.valid()[..., None], xy, 0.0)


def is_carmen_file(path: str | os.PathLike) -> bool:
    name = Path(path).name.lower()
    for packed in (".gz", ".bz2"):
        name = name.removesuffix(packed)
    return Path(path).is_file() and name.endswith(CARMEN_SUFFIXES)


def open_text(path: str | os.PathLike) -> io.TextIOBase:
    """Open a text file, transparently decompressing ``.gz`` and ``.bz2``."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file not found")
    if not path.is_file():
        raise InputError(f"{path}: not a file")
    suffix = path.suffix.lower()
    opener = {".gz": gzip.open, ".bz2": bz2.open}.get(suffix)
    if opener is None:
        return open(path, encoding="ascii", errors="replace")
    return opener(path, "rt", encoding="ascii", errors="replace")


class _Bad(Exception):
    pass


def _floats(tokens: list[str]) -> list[float]:
    try:
        return [float(t) for t in tokens]
    except ValueError as e:
        raise _Bad(f"not a number ({e})") from None


def _flaser(tok: list[str]):
    n = int(tok[1])
    if len(tok) < 2 + n + 9:
        raise _Bad(f"FLASER with {n} readings needs {n + 11} fields, found {len(tok)}")
    ranges = _floats(tok[2:2 + n])
    rest = _floats(tok[2 + n:2 + n + 7])
    angles = (n, -np.pi / 2, np.pi, FLASER_MAX_RANGE)
    return ranges, angles, rest[0:3], rest[3:6], tok[2 + n + 6]


def _robotlaser(tok: list[str]):
    start, fov, _res, max_range = _floats(tok[2:6])
    n = int(tok[8])
    m_at = 9 + n
    if len(tok) <= m_at:
        raise _Bad(f"ROBOTLASER1 with {n} readings is cut short")
    m = int(tok[m_at])
    if m < 0:
        raise _Bad(f"ROBOTLASER1 with {m} remissions")
    tail = m_at + 1 + m
    if len(tok) < tail + 12:
        raise _Bad(f"ROBOTLASER1 with {n} readings and {m} remissions needs {tail + 14} fields, found {len(tok)}")
    ranges = _floats(tok[9:9 + n])
    rest = _floats(tok[tail:tail + 6])
    return ranges, (n, start, fov, max_range), rest[0:3], rest[3:6], tok[tail + 11]


_PARSERS = {"FLASER": _flaser, "ROBOTLASER1": _robotlaser}


def read_carmen(path: str | os.PathLike, message: str | None = None) -> CarmenLog:
    """Read the laser scans of a CARMEN log. ``message`` picks FLASER or ROBOTLASER1 (default:
    the first one found)."""
    path = Path(path)
    rows = []
    try:
        with open_text(path) as f:
            for lineno, line in enumerate(f, start=1):
                tok = line.split()
                if not tok or tok[0] not in _PARSERS or (message and tok[0] != message):
                    continue
                message = message or tok[0]
                try:
                    ranges, geom, pose, odom, stamp = _PARSERS[tok[0]](tok)
                    ts = float(stamp)
                except (_Bad, ValueError, IndexError) as e:
                    raise InputError(f"{path}:{lineno}: malformed {tok[0]} line ({e})") from None
                if (not 0 < geom[0] <= 10000 or not np.isfinite(geom[1]) or not 0 < geom[2] <= 2 * np.pi + 1e-6
                        or not geom[3] > 0):
                    raise InputError(f"{path}:{lineno}: implausible {tok[0]} beam layout "
                                     f"({geom[0]} beams, start {geom[1]:g} rad, fov {geom[2]:g} rad, "
                                     f"max range {geom[3]:g})")
                if not (np.isfinite(pose).all() and np.isfinite(odom).all() and np.isfinite(ts)):
                    raise InputError(f"{path}:{lineno}: NaN or inf in the pose or timestamp")
                rows.append((ranges, geom, pose, odom, ts, stamp, lineno))
    except (OSError, EOFError, UnicodeDecodeError, zlib.error) as e:  # zlib.error: corrupt .gz data
        raise InputError(f"{path}: cannot read log ({e})") from None
    if not rows:
        raise InputError(f"{path}: no {message or 'FLASER or ROBOTLASER1'} laser message found")
    width = max(r[1][0] for r in rows)
    ranges = np.zeros((len(rows), width))
    angles = np.zeros((len(rows), width))
    for i, (r, (n, start, fov, _), *_rest) in enumerate(rows):
        ranges[i, :n] = r
        angles[i] = start + fov * np.arange(width) / max(n - 1, 1)
    max_range = np.array([r[1][3] for r in rows], dtype=np.float64)
    if message == "FLASER":
        max_range = np.minimum(max_range, saturation_range(ranges))
    return CarmenLog(
        path=str(path), message=message, ranges=ranges, angles=angles,
        poses=np.array([r[2] for r in rows]), odometry=np.array([r[3] for r in rows]),
        timestamps=np.array([r[4] for r in rows]), stamps=[r[5] for r in rows],
        lines=np.array([r[6] for r in rows]), max_range=max_range,
    )


def write_with_poses(source: str | os.PathLike, out: str | os.PathLike, poses: np.ndarray,
                     stamps: list[str] | None = None) -> None:
    """Write ``source``'s laser messages (those ``read_carmen`` reads, in its order) to ``out``
    (plain text) with their poses replaced by ``poses`` (S, 3): FLASER's laser pose and odometry
    fields, ROBOTLASER1's laser and robot poses; ``stamps`` (S,) replace the timestamps
    (``ipc_timestamp`` and ``logger_timestamp``). ODOM lines are left out (they would contradict
    the new poses); other lines are kept. Atomic: ``out`` is whole or not written."""
    log = read_carmen(source)
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (log.num_scans, 3) or (stamps is not None and len(stamps) != log.num_scans):
        raise ValueError(f"{source}: {log.num_scans} scans, got {poses.shape[0]} poses"
                         f"{'' if stamps is None else f' and {len(stamps)} timestamps'}")
    rows = {int(line): k for k, line in enumerate(log.lines)}
    lines = []
    with open_text(source) as f:
        for lineno, line in enumerate(f, start=1):
            tok = line.split()
            if tok and tok[0] == "ODOM":
                continue
            k = rows.get(lineno)
            if k is not None:
                at = 2 + int(tok[1]) if tok[0] == "FLASER" else 10 + int(tok[8]) + int(tok[9 + int(tok[8])])
                pose = [f"{v:.6f}" for v in poses[k]]
                tok[at:at + 6] = pose + pose
                if stamps is not None:
                    stamp_at = at + 6 if tok[0] == "FLASER" else at + 11
                    tok[stamp_at] = tok[stamp_at + 2] = stamps[k]
                line = " ".join(tok) + "\n"
            lines.append(line if line.endswith("\n") else line + "\n")
    atomic_write(out, lambda f: f.write("".join(lines).encode("ascii")))


def saturation_range(ranges: np.ndarray) -> float:
    """The no-return value of a log without a maximum field: its largest finite reading if at least
    ``SATURATION_SHARE`` of the readings (and 10) have that very value and it is over twice the
    median of the others (a sensor's code for "nothing hit", e.g. 81.83 m in the intel log:
    measured ranges are not that often exactly the largest); inf otherwise (then only the fixed
    ``FLASER_MAX_RANGE`` applies)."""
    r = ranges[np.isfinite(ranges) & (ranges > 0)]
    if r.size == 0:
        return np.inf
    top = float(r.max())
    at_top = r >= top - MAX_RANGE_TOL / 2
    hits = int(np.count_nonzero(at_top))
    if hits < max(10, SATURATION_SHARE * ranges.size) or hits == r.size:
        return np.inf
    return top if top > 2 * float(np.median(r[~at_top])) else np.inf


def match_scans(log: CarmenLog, raw: CarmenLog, decimals: int = 2) -> np.ndarray:
    """For each scan of ``log`` (e.g. a ``*-corrected`` log, whose timestamps restart at 0), the
    index of the same scan in ``raw`` (identical ranges at ``decimals``), or -1.

    Logs rewritten by a SLAM system keep the ranges but not the timestamps; the clock offset
    is estimated from the scans whose ranges occur once in both logs, and each scan is then
    matched to the raw scan nearest in time with identical ranges.
    """
    def keys(lg):
        return [np.round(r, decimals).tobytes() for r in lg.ranges]

    raw_keys, log_keys = keys(raw), keys(log)
    where: dict[bytes, list[int]] = {}
    for k, key in enumerate(raw_keys):
        where.setdefault(key, []).append(k)
    unique = [(i, where[key][0]) for i, key in enumerate(log_keys) if len(where.get(key, [])) == 1]
    if not unique:
        return np.full(log.num_scans, -1)
    offset = np.median([raw.timestamps[k] - log.timestamps[i] for i, k in unique])
    out = np.full(log.num_scans, -1)
    for i, key in enumerate(log_keys):
        cands = where.get(key)
        if cands:
            out[i] = min(cands, key=lambda k: abs(raw.timestamps[k] - log.timestamps[i] - offset))
    return out


DEFAULT_KEYFRAMES = "motion:0.5,15"


def relations_next_to(path: Path) -> Path | None:
    """``intel.relations`` next to ``intel.clf.bz2`` (the Freiburg benchmark's layout), if present."""
    stem = path.name.split(".")[0]
    cand = path.with_name(f"{stem}.relations")
    return cand if cand.is_file() else None


def load_carmen(path: str | os.PathLike, gt_path=None, init_path=None, keyframes: str | None = None,
                non_keyframes: str = "icp"):
    """A CARMEN log as a 2D ScanSet of its keyframes (``keyframes`` spec, see deepmapping.sequence;
    default ``motion:0.5,15``). init_poses = the log's laser poses (odometry: the warm start);
    ``sequence`` keeps every scan (timestamps, odometry) so a pose can be written for each, and
    the relations file for scoring: ``gt_path`` (a ``.relations`` file) or the one next to the log
    (``<name>.relations``). ``non_keyframes``:
    how the other scans get their pose, "odometry" from the nearest keyframe, or "icp" (then
    matched to that keyframe's scan)."""
    path = Path(path)
    relations = gt_path is not None and str(gt_path).endswith(".relations")
    if (gt_path is not None and not relations) or init_path is not None:
        raise ConfigError(f"{path}: a CARMEN log carries its own poses (odometry); --init is not read for it, "
                          "--gt only as a relations file (FILE.relations)")
    if relations and not Path(gt_path).is_file():
        raise InputError(f"{gt_path}: file not found")
    log = read_carmen(path)
    kf = select_keyframes(keyframes or DEFAULT_KEYFRAMES, log.poses, log.timestamps)
    if len(kf) < 2:
        raise InputError(f"{path}: only {len(kf)} keyframe with keyframes={keyframes or DEFAULT_KEYFRAMES!r}; "
                         "choose a denser spec (e.g. every:1)")
    valid = log.valid()[kf]
    empty = np.flatnonzero(~valid.any(axis=1))
    if len(empty):
        raise InputError(f"{path}:{log.lines[kf[empty[0]]]}: scan has no return (every range at the maximum)")
    rel = Path(gt_path) if relations else relations_next_to(path)
    if non_keyframes not in ("odometry", "icp"):
        raise ConfigError(f"non_keyframes must be 'odometry' or 'icp', got {non_keyframes!r}")
    seq = FullSequence(stamps=log.stamps, timestamps=log.timestamps, odometry=log.poses, keyframes=kf,
                       relations_path=str(rel) if rel else None, points=log.points(), valid=log.valid(),
                       placement=non_keyframes)
    return ScanSet(points=log.points()[kf].astype(np.float32), valid=valid, gt_poses=None,
                   init_poses=log.poses[kf].copy(), unit_scale=1.0, unit="m", ordered=True,
                   names=[log.stamps[k] for k in kf], source=str(path), sequence=seq)
