"""The relations metric of Kümmerle et al. 2009 ("On measuring the accuracy of SLAM algorithms").

A relation ``t_i t_j dx dy dz roll pitch yaw`` is the pose at ``t_j`` seen from the pose at
``t_i`` (inv(T_i)·T_j), metres and radians. For an estimated 2D trajectory, each relation's
error is ``inv(relation) · inv(T_i)·T_j``: its translation norm (m) and absolute rotation (deg).
Timestamps are matched exactly, as written in the files (strings), so no rounding can pair
the wrong scans; relations whose scans are not in the trajectory are counted, not dropped.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deepmapping.errors import InputError
from deepmapping.geometry import se2

__all__ = ["Relations", "read_relations", "relation_errors", "score_relations", "derive_relations", "LONG_RELATION_S"]

LONG_RELATION_S = 10.0  # relations spanning more than this are (mostly) loop closures


@dataclass
class Relations:
    stamp_i: list[str]
    stamp_j: list[str]
    motion: np.ndarray  # (R, 3) [dx, dy, dyaw]
    path: str = "<memory>"

    def __len__(self) -> int:
        return len(self.stamp_i)

    def span_s(self) -> np.ndarray:
        return np.abs(np.array([float(b) - float(a) for a, b in zip(self.stamp_i, self.stamp_j)]))


def read_relations(path: str | os.PathLike) -> Relations:
    """Read a ``.relations`` file (8 columns per line, ``#`` comments and blank lines skipped)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    si, sj, motion = [], [], []
    for lineno, line in enumerate(path.read_text(encoding="ascii", errors="replace").splitlines(), start=1):
        tok = line.split("#", 1)[0].split()
        if not tok:
            continue
        if len(tok) != 8:
            raise InputError(f"{path}:{lineno}: a relation has 8 fields (t_i t_j dx dy dz roll pitch yaw), found {len(tok)}")
        try:
            vals = [float(t) for t in tok]
        except ValueError as e:
            raise InputError(f"{path}:{lineno}: not a number ({e})") from None
        if not np.isfinite(vals).all():
            raise InputError(f"{path}:{lineno}: NaN or inf")
        si.append(tok[0])
        sj.append(tok[1])
        motion.append([vals[2], vals[3], vals[7]])
    if not si:
        raise InputError(f"{path}: no relation found")
    return Relations(si, sj, np.array(motion), str(path))


def relation_errors(relations: Relations, stamps: list[str], poses: np.ndarray):
    """Per-relation errors of 2D ``poses`` (S, 3) at ``stamps`` (S,): (trans_m, rot_deg, matched mask)."""
    poses = np.asarray(poses, dtype=np.float64)
    if len(stamps) != len(poses):
        raise InputError(f"{len(stamps)} timestamps for {len(poses)} poses (counts differ)")
    index = {s: k for k, s in enumerate(stamps)}
    i = np.array([index.get(s, -1) for s in relations.stamp_i])
    j = np.array([index.get(s, -1) for s in relations.stamp_j])
    matched = (i >= 0) & (j >= 0)
    est = se2.relative(poses[i[matched]], poses[j[matched]])
    err = se2.relative(relations.motion[matched], est)
    return np.linalg.norm(err[:, :2], axis=1), np.degrees(np.abs(err[:, 2])), matched


def _stats(trans: np.ndarray, rot: np.ndarray) -> dict:
    if len(trans) == 0:
        return {"count": 0}
    return {"count": int(len(trans)),
            "trans_mean_m": float(trans.mean()), "trans_std_m": float(trans.std()),
            "trans_median_m": float(np.median(trans)),
            "rot_mean_deg": float(rot.mean()), "rot_std_deg": float(rot.std()), "rot_median_deg": float(np.median(rot))}


def score_relations(relations: Relations, stamps: list[str], poses: np.ndarray) -> dict:
    """Mean ± std and median of the errors: all matched relations, shorter and longer than 10 s;
    ``unmatched`` counts the relations with a timestamp not in ``stamps``."""
    trans, rot, matched = relation_errors(relations, stamps, poses)
    long = relations.span_s()[matched] > LONG_RELATION_S
    return {"relations": len(relations), "unmatched": int((~matched).sum()),
            "all": _stats(trans, rot), "short": _stats(trans[~long], rot[~long]), "long": _stats(trans[long], rot[long])}


def derive_relations(stamps: list[str], poses: np.ndarray, near_m: float = 1.0, count: int = 3000,
                     long_share: float = 0.4, seed: int = 0) -> Relations:
    """Relations from a reference trajectory (``poses`` (S, 3) at ``stamps``) for a log without the
    benchmark's file, made like the benchmark's: pairs of scans whose reference positions are at
    most ``near_m`` apart (intel's and fr079's files: 90 % of the pairs under 1 m, any turn), drawn
    at random (``seed``): ``count`` in all, ``long_share`` of them more than 10 s apart (the
    files: about 40 %), fewer where fewer such pairs exist. The reference scores 0 on them."""
    from scipy.spatial import cKDTree

    poses = np.asarray(poses, dtype=np.float64)
    if len(stamps) != len(poses) or len(stamps) < 2:
        raise InputError(f"{len(stamps)} timestamps for {len(poses)} poses: need two or more of each, as many")
    t = np.array([float(s) for s in stamps])
    pairs = cKDTree(poses[:, :2]).query_pairs(near_m, output_type="ndarray").reshape(-1, 2)
    i, j = pairs.min(1), pairs.max(1)
    swap = t[j] < t[i]  # the earlier scan first (some logs' clocks step back)
    i, j = np.where(swap, j, i), np.where(swap, i, j)
    long = t[j] - t[i] > LONG_RELATION_S
    rng = np.random.default_rng(seed)
    n_long = min(int(round(count * long_share)), int(long.sum()))
    picks = [rng.permutation(np.flatnonzero(long))[:n_long],
             rng.permutation(np.flatnonzero(~long))[:count - n_long]]
    keep = np.concatenate(picks)
    keep = keep[np.lexsort((t[j[keep]], t[i[keep]]))]
    i, j = i[keep], j[keep]
    return Relations([stamps[k] for k in i], [stamps[k] for k in j], se2.relative(poses[i], poses[j]), "<derived>")
