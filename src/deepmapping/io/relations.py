"""Relations files: derived from a corrected log (for logs without the benchmark's file), written atomically."""

from __future__ import annotations

import os

import numpy as np

from deepmapping.errors import InputError
from deepmapping.evaluation.relations import Relations, derive_relations
from deepmapping.io.atomic import atomic_write
from deepmapping.io.carmen import match_scans, read_carmen

__all__ = ["corrected_trajectory", "relations_from_corrected", "write_relations"]


def corrected_trajectory(corrected: str | os.PathLike, raw: str | os.PathLike) -> tuple[list[str], np.ndarray]:
    """The poses (S, 3) of a ``*-corrected`` log at the timestamps of the same scans in the raw log
    (matched by their ranges: corrected logs rewrite the timestamps), in the raw log's order."""
    ref, log = read_carmen(corrected), read_carmen(raw)
    idx = match_scans(ref, log)
    ok = np.flatnonzero(idx >= 0)
    if ok.size < 2:
        raise InputError(f"{corrected}: {ok.size} of its {ref.num_scans} scans found in {raw} (same ranges); "
                         "is it the corrected log of that log?")
    order = ok[np.argsort(idx[ok], kind="stable")]
    return [log.stamps[k] for k in idx[order]], ref.poses[order]


def relations_from_corrected(corrected: str | os.PathLike, raw: str | os.PathLike, seed: int = 0,
                             count: int = 3000) -> Relations:
    """Relations (``derive_relations``) from the poses of a ``*-corrected`` log (``corrected_trajectory``)."""
    rel = derive_relations(*corrected_trajectory(corrected, raw), count=count, seed=seed)
    rel.path = f"derived from {corrected}"
    return rel


def write_relations(path: str | os.PathLike, relations: Relations) -> None:
    """The ``.relations`` format (``t_i t_j dx dy dz roll pitch yaw``; dz, roll, pitch 0), atomically."""
    lines = [f"# {len(relations)} relations, {relations.path}\n"]
    lines += [f"{a} {b} {dx:.6f} {dy:.6f} 0 0 0 {dyaw:.6f}\n"
              for a, b, (dx, dy, dyaw) in zip(relations.stamp_i, relations.stamp_j, relations.motion)]
    atomic_write(path, lambda f: f.write("".join(lines).encode("ascii")))
