"""Rebuild the small real-data excerpts in tests/data from the full data sets in ../shared/data.

The suite reads only these excerpts, so it passes on a clone with nothing beside it. They are
committed; this script says exactly where each one comes from (run it from the repository
root: ``.venv/bin/python tests/data/make_excerpts.py``). Outputs are deterministic.

- bunny/: bun.conf unchanged; each of the 10 range scans thinned to one point per 2 mm voxel
  (plus the scan's extreme x points, which place the loader's sensor origin), in the original
  ASCII PLY layout (vertex x y z, then an empty range_grid list element).
- 3dtk/: README, config.ini, .pose and .frames unchanged; each .3d thinned to 4000 random
  points plus its nearest, farthest and lowest-z points, and the nearest and farthest within
  config.ini's range limits (the loader's range and in-front filters are tested).
- carmen/ (the layout of ../shared/data/carmen, so `deepmapping experiment carmen --data` reads it):
  fr079.clf.gz: the log's header lines and raw fr079 scans 1000-1599 with the ODOM lines
  between them; corrected/freiburg-079-corrected.log.gz: the same scans of the corrected log
  (573 of the 600); fr079.relations: the relations whose two stamps are both in the excerpt.
  intel.clf.gz + intel.relations: intel scans 300-419 (7 m of motion), likewise.
"""

from __future__ import annotations

import bz2
import gzip
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
SHARED = HERE.parents[2] / "shared" / "data"


def _gz(path: Path, lines: list[str]) -> None:
    with gzip.GzipFile(path, "wb", mtime=0) as f:  # mtime 0: byte-identical reruns
        f.write(("\n".join(lines) + "\n").encode())


def bunny(out: Path) -> None:
    src = SHARED / "bunny"
    out.mkdir(parents=True, exist_ok=True)
    (out / "bun.conf").write_bytes((src / "bun.conf").read_bytes())
    for ply in sorted(src.glob("*.ply")):
        lines = ply.read_text().splitlines()
        n = int(next(ln.split()[2] for ln in lines if ln.startswith("element vertex")))
        start = lines.index("end_header") + 1
        xyz = np.array([ln.split()[:3] for ln in lines[start:start + n]], float)
        _, keep = np.unique(np.floor(xyz / 0.002).astype(np.int64), axis=0, return_index=True)
        keep = np.union1d(keep, [xyz[:, 0].argmin(), xyz[:, 0].argmax()])
        header = ["ply", "format ascii 1.0", "comment excerpt of the Stanford bunny scan " + ply.name,
                  f"element vertex {len(keep)}", "property float x", "property float y", "property float z",
                  "element range_grid 0", "property list uchar int vertex_indices", "end_header"]
        (out / ply.name).write_text("\n".join(header + [lines[start + k].strip() for k in keep]) + "\n")


def threedtk(out: Path) -> None:
    src = SHARED / "3dtk"
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for f in sorted(src.iterdir()):
        if f.suffix != ".3d":
            (out / f.name).write_bytes(f.read_bytes())
            continue
        lines = f.read_text().splitlines()
        xyz = np.array([ln.split()[:3] for ln in lines], float)
        r = np.linalg.norm(xyz, axis=1)
        inside = np.flatnonzero((r >= 48) & (r <= 3276))  # config.ini's range limits (cm)
        extremes = [r.argmin(), r.argmax(), xyz[:, 2].argmin(), inside[r[inside].argmin()], inside[r[inside].argmax()]]
        keep = np.union1d(rng.choice(len(xyz), 4000, replace=False), extremes)
        (out / f.name).write_text("\n".join(lines[k] for k in keep) + "\n")


def _flaser_lines(lines):
    return [k for k, ln in enumerate(lines) if ln.startswith("FLASER")]


def _relations(src: Path, stamps: set[str]) -> list[str]:
    return [r for r in src.read_text().splitlines() if r.split() and set(r.split()[:2]) <= stamps]


def carmen(out: Path) -> None:
    src = SHARED / "carmen"
    (out / "corrected").mkdir(parents=True, exist_ok=True)
    for log, first, last in (("fr079", 1000, 1600), ("intel", 300, 420)):
        with bz2.open(src / f"{log}.clf.bz2", "rt") as f:
            lines = [ln.rstrip("\n") for ln in f]
        scan_at = _flaser_lines(lines)
        head = [ln for ln in lines[:scan_at[0]]]  # comments and PARAM lines
        body = lines[scan_at[first]:scan_at[last - 1] + 1]
        _gz(out / f"{log}.clf.gz", head + body)
        stamps = {ln.split()[-3] for ln in body if ln.startswith("FLASER")}
        (out / f"{log}.relations").write_text("\n".join(_relations(src / f"{log}.relations", stamps)) + "\n")
    # the corrected fr079 log: the scans whose ranges are those of the excerpt (same order)
    with gzip.open(src / "corrected" / "freiburg-079-corrected.log.gz", "rt") as f:
        lines = [ln.rstrip("\n") for ln in f]
    def ranges(line):  # the logs print 7.3 and 7.30 alike
        tok = line.split()
        return tuple(round(float(v), 2) for v in tok[2:2 + int(tok[1])])

    with gzip.open(out / "fr079.clf.gz", "rt") as f:
        raw = {ranges(ln) for ln in f if ln.startswith("FLASER")}
    scan_at = _flaser_lines(lines)
    keep = [k for k in scan_at if ranges(lines[k]) in raw]
    head = [ln for ln in lines[:scan_at[0]]]
    body = lines[keep[0]:keep[-1] + 2]  # from the first kept scan to the NEFF line after the last
    _gz(out / "corrected" / "freiburg-079-corrected.log.gz", head + body)


if __name__ == "__main__":
    bunny(HERE / "bunny")
    threedtk(HERE / "3dtk")
    carmen(HERE / "carmen")
    for f in sorted(HERE.rglob("*")):
        if f.is_file() and f.name != "make_excerpts.py":
            print(f"{f.stat().st_size:>9}  {f.relative_to(HERE)}")
