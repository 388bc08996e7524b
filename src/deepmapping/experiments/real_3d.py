"""``deepmapping experiment real-3d``: real 3D scans, the Stanford bunny and the 3DTK sample.

The data folder (``--data``, default ``../shared/data``) holds ``bunny/`` and ``3dtk/``.

Bunny (10 range scans, exact poses in bun.conf): every method starts from a coarse start, the
true poses turned by about 10 deg about each scan's centroid and shifted by about 1 cm (bun000,
the fixed reference, exact); multiway also from the identity (45-180 deg apart: only a global
method has a chance). DeepMapping and direct optimization use the ``bunny`` profile, the
classical methods ``default-3d``. Reported per scan: rotation error (deg) and translation
error at the scan's centroid (mm), relative to bun000 (``io.bunny.bunny_pose_errors``).

3DTK (three outdoor scans): every method starts from the odometry in the .pose files, with
``default-3d`` (DeepMapping and direct optimization hold it by the odometry factor, as the default
command does); reported per scan: the difference to slam6D's own result (last line of each
.frames file; a reference, not ground truth) as translation (cm) and rotation (deg), relative
to scan000. Each method's poses are written as ``3dtk_frames/<method>/scanNNN.frames``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from deepmapping.api import register
from deepmapping.config import load_config
from deepmapping.errors import ConfigError
from deepmapping.experiments.base import Job
from deepmapping.experiments.report import markdown_table, write_report
from deepmapping.geometry import se3
from deepmapping.io.atomic import make_folder
from deepmapping.io.bunny import bunny_pose_errors, load_bunny, scan_centroids
from deepmapping.io.threedtk import load_3dtk, write_frames

DATA = "."  # ../shared/data itself: bunny/ and 3dtk/
METHODS = {  # name -> overrides of the method's profile
    "icp-plane": {"method": "icp-plane"},
    "multiway": {"method": "multiway"},
    "deepmapping": {},
    "direct": {"method": "direct"},
}
TRAINED = ("deepmapping", "direct")
FULL = {"max_points": 2000, "epochs": None}  # points per bunny scan (3DTK: 5x)
QUICK = {"max_points": 60, "epochs": 2}  # a smoke run in seconds, not a measurement


def jobs(quick: bool, data: str) -> list[Job]:
    """Bunny: the starts, then each method from the coarse start (multiway from the identity
    too); 3DTK: the odometry, then each method; for whichever of the two ``data`` holds."""
    s = QUICK if quick else FULL
    out = []
    if (Path(data) / "bunny").is_dir():
        runs = [("start", None)] + [(m, "coarse") for m in METHODS] + [("multiway", "identity")]
        out += [Job(f"bunny-{m}" + (f"-from-{st}" if st else ""), "deepmapping.experiments.real_3d:run_bunny",
                    {"data": data, "method": m, "start": st} | s) for m, st in runs]
    if (Path(data) / "3dtk").is_dir():
        out += [Job(f"3dtk-{m}", "deepmapping.experiments.real_3d:run_3dtk", {"data": data, "method": m} | s)
                for m in ("odometry", *METHODS)]
    if not out:
        raise ConfigError(f"{data}: neither bunny/ nor 3dtk/ in it")
    return out


def coarse_start(scans, deg: float = 10.0, mm: float = 10.0, seed: int = 0) -> np.ndarray:
    """The true poses turned by about ``deg`` about each scan's centroid and shifted by about
    ``mm`` (the first scan, the fixed reference, exact)."""
    rng = np.random.default_rng(seed)
    k = scans.num_scans
    rot = Rotation.from_rotvec(rng.normal(size=(k, 3)) * np.radians(deg) / np.sqrt(3)).as_matrix()
    pert = se3.from_rt(rot, rng.normal(size=(k, 3)) * mm / 1000 / np.sqrt(3))
    pert[0] = np.eye(4)
    c = se3.from_rt(np.broadcast_to(np.eye(3), (k, 3, 3)), scan_centroids(scans.points, scans.valid))
    return scans.gt_poses @ c @ pert @ se3.inverse(c)


def _register_from(scans, init: np.ndarray, method: str, epochs: int | None, profile: str) -> tuple[np.ndarray, float]:
    import torch

    overrides = {"warm_start.method": "file", "threads": torch.get_num_threads(), **METHODS[method]}
    if method in TRAINED and epochs is not None:
        overrides["optim.epochs"] = epochs
    scans.init_poses = init
    result = register(scans, load_config(profile, overrides=overrides))
    return result.poses, result.runtime_s


def run_bunny(data: str, method: str, start: str | None, max_points: int, epochs: int | None = None) -> dict:
    """Per-scan errors of ``method`` from ``start`` ("coarse", "identity"); method "start": of
    both starts themselves."""
    scans = load_bunny(Path(data) / "bunny", max_points=max_points)
    centroids = scan_centroids(scans.points, scans.valid)
    starts = {"coarse": coarse_start(scans), "identity": scans.identity_poses()}
    row = {"data": "bunny", "method": method, "start": start}
    if method == "start":
        return row | {"starts": {n: bunny_pose_errors(p, scans.gt_poses, scans.names, centroids)
                                 for n, p in starts.items()}}
    poses, runtime = _register_from(scans, starts[start], method, epochs,
                                    "bunny" if method in TRAINED else "default-3d")
    return row | {"runtime_s": runtime, "scans": bunny_pose_errors(poses, scans.gt_poses, scans.names, centroids)}


def relative_errors(est: np.ndarray, ref: np.ndarray, unit_scale: float) -> list[dict]:
    """Each scan's pose relative to the first, ``est`` against ``ref``: translation (metres x
    ``unit_scale``) and rotation (deg) of the difference."""
    out = []
    for i in range(1, len(ref)):
        d = se3.relative(se3.relative(ref[0], ref[i]), se3.relative(est[0], est[i]))
        out.append({"trans": float(np.linalg.norm(d[:3, 3]) * unit_scale),
                    "rot_deg": float(se3.rotation_angle_deg(d[:3, :3]))})
    return out


def run_3dtk(data: str, method: str, max_points: int, epochs: int | None = None) -> dict:
    """Per-scan differences (cm, deg) of ``method`` (or "odometry") to slam6D's result, and the poses."""
    scans = load_3dtk(Path(data) / "3dtk", max_points=max_points * 5)
    row = {"data": "3dtk", "method": method, "names": list(scans.names)}
    if method == "odometry":
        return row | {"scans": relative_errors(scans.init_poses, scans.gt_poses, 100.0),
                      "poses": scans.init_poses.tolist()}
    poses, runtime = _register_from(scans, scans.init_poses.copy(), method, epochs, "default-3d")
    return row | {"runtime_s": runtime, "scans": relative_errors(poses, scans.gt_poses, 100.0),
                  "poses": poses.tolist()}


def _bunny_row(name: str, errors: list[dict], runtime) -> list:
    rot = [e["rot_deg"] for e in errors[1:]]
    tr = [e["trans_mm"] for e in errors[1:]]
    return [name, float(np.median(rot)), float(max(rot)), float(np.median(tr)), float(max(tr)), runtime]


def report(out: Path, results: dict[str, dict], quick: bool) -> Path:
    """A bunny table (median and worst over scans 1-9), a 3DTK table (each scan), the .frames."""
    sections = ["Quick: a smoke run, not a measurement." if quick else
                "Bunny: 2000 points per scan; 3DTK: 10000 points per scan."]
    bunny = [r for r in results.values() if r.get("data") == "bunny"]
    if bunny:
        rows = []
        for r in bunny:
            if r["method"] == "start":
                rows += [_bunny_row(f"{n} start", e, "-") for n, e in r["starts"].items()]
            else:
                rows.append(_bunny_row(f"{r['method']} from {r['start']}", r["scans"], r["runtime_s"]))
        sections.append("## Stanford bunny: errors relative to bun000\n\n" + markdown_table(
            ["run", "rotation median (deg)", "worst", "translation median (mm)", "worst", "runtime (s)"], rows))
    tdtk = [r for r in results.values() if r.get("data") == "3dtk"]
    if tdtk:
        rows = [[r["method"], *(f"{e['trans']:.1f} cm / {e['rot_deg']:.2f}°" for e in r["scans"]),
                 r.get("runtime_s", "-")] for r in tdtk]
        names = tdtk[0]["names"][1:]
        sections.append("## 3DTK: difference to slam6D's result, relative to scan000\n\n" + markdown_table(
            ["method", *names, "runtime (s)"], rows) + "\n\nPoses as slam6D .frames: `3dtk_frames/<method>/`.")
        for r in tdtk:
            folder = make_folder(Path(out) / "3dtk_frames" / r["method"])
            for name, pose in zip(r["names"], np.asarray(r["poses"])):
                write_frames(folder / f"{name}.frames", pose[None])
    return write_report(out, "Real 3D scans: the Stanford bunny and 3DTK", sections)
