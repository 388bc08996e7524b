"""Real 3D data checks: the Stanford Bunny and the 3DTK sample scans.

    .venv/bin/python benchmarks/real_3d.py                 # both (~15 min on 2 cores)
    .venv/bin/python benchmarks/real_3d.py --max-points 500 --set optim.epochs=5   # smoke run

Bunny (../shared/data/bunny, 10 range scans, exact poses in bun.conf): every method starts
from a coarse start, the true poses turned by about 10 deg about each scan's centroid and
shifted by about 1 cm (bun000, the fixed reference, exact); multiway also from the identity.
Reported per scan: rotation error (deg) and translation error at the scan's centroid (mm),
relative to bun000 (``deepmapping.io.bunny.bunny_pose_errors``).

3DTK (../shared/data/3dtk, three outdoor scans): every method starts from the odometry in
the .pose files; reported per scan: the difference to slam6D's own result (last line of
each .frames file; a reference, not ground truth) as translation (cm) and rotation (deg),
relative to scan000. Each method's poses are written as scanNNN.frames under --out.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from datetime import date
from pathlib import Path

import numpy as np

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
METHODS = {  # name -> config overrides on the default-3d profile
    "icp-plane": {"method": "icp-plane"},
    "multiway": {"method": "multiway"},
    "deepmapping": {},
    "direct": {"method": "direct"},
}


def coarse_start(scans, deg: float = 10.0, mm: float = 10.0, seed: int = 0) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    from deepmapping.geometry import se3
    from deepmapping.io.bunny import scan_centroids

    rng = np.random.default_rng(seed)
    k = scans.num_scans
    rot = Rotation.from_rotvec(rng.normal(size=(k, 3)) * np.radians(deg) / np.sqrt(3)).as_matrix()
    pert = se3.from_rt(rot, rng.normal(size=(k, 3)) * mm / 1000 / np.sqrt(3))
    pert[0] = np.eye(4)  # bun000 is the fixed reference
    c = se3.from_rt(np.broadcast_to(np.eye(3), (k, 3, 3)), scan_centroids(scans.points, scans.valid))
    return scans.gt_poses @ c @ pert @ se3.inverse(c)


def register_from(scans, init: np.ndarray, overrides: dict, profile: str = "default-3d") -> tuple[np.ndarray, float]:
    from deepmapping.api import register
    from deepmapping.config import load_config

    scans.init_poses = init
    cfg = load_config(profile, overrides={"warm_start.method": "file", **overrides})
    result = register(scans, cfg)
    return result.poses, result.runtime_s


def relative_errors(est, ref, unit_scale: float) -> list[dict]:
    from deepmapping.geometry import se3

    out = []
    for i in range(1, len(ref)):
        d = se3.relative(se3.relative(ref[0], ref[i]), se3.relative(est[0], est[i]))
        out.append({"trans": float(np.linalg.norm(d[:3, 3]) * unit_scale),
                    "rot_deg": float(se3.rotation_angle_deg(d[:3, :3]))})
    return out


def bunny(args, sets) -> dict:
    from deepmapping.io.bunny import bunny_pose_errors, load_bunny, scan_centroids

    scans = load_bunny(args.data / "bunny", max_points=args.max_points)
    centroids = scan_centroids(scans.points, scans.valid)
    starts = {"coarse": coarse_start(scans), "identity": np.tile(np.eye(4), (scans.num_scans, 1, 1))}
    report = {"start": {name: bunny_pose_errors(p, scans.gt_poses, scans.names, centroids) for name, p in starts.items()}}
    for start, init in starts.items():
        for method, ov in METHODS.items():
            if start == "identity" and method != "multiway":
                continue  # 45-180 deg apart: only a global method has a chance (none of ours does)
            # deepmapping and direct: the bunny profile (default-3d, poses about the scan's centroid, ...)
            trained = method in ("deepmapping", "direct")
            poses, runtime = register_from(scans, init, ov | (sets if trained else {}) | {"threads": args.threads},
                                           profile="bunny" if trained else "default-3d")
            report[f"{method} from {start}"] = {"runtime_s": runtime,
                                                "scans": bunny_pose_errors(poses, scans.gt_poses, scans.names, centroids)}
            print(f"bunny {method} from {start}: {_summary(report[f'{method} from {start}']['scans'])}", flush=True)
    return report


def threedtk(args, sets) -> dict:
    from deepmapping.io.threedtk import load_3dtk, write_frames

    scans = load_3dtk(args.data / "3dtk", max_points=args.max_points * 5)
    report = {"odometry": relative_errors(scans.init_poses, scans.gt_poses, 100.0)}
    for method, ov in METHODS.items():
        extra = sets if method in ("deepmapping", "direct") else {}
        poses, runtime = register_from(scans, scans.init_poses.copy(), ov | extra | {"threads": args.threads})
        report[method] = {"runtime_s": runtime, "scans": relative_errors(poses, scans.gt_poses, 100.0)}
        folder = args.out / "3dtk_frames" / method
        folder.mkdir(parents=True, exist_ok=True)
        for name, pose in zip(scans.names, poses):
            write_frames(folder / f"{name}.frames", pose[None])
        errs = report[method]["scans"]
        print(f"3dtk {method}: " + ", ".join(f"{e['trans']:.1f} cm / {e['rot_deg']:.2f} deg" for e in errs), flush=True)
    return report


def _summary(errors: list[dict]) -> str:
    rot = [e["rot_deg"] for e in errors[1:]]
    tr = [e["trans_mm"] for e in errors[1:]]
    return (f"rotation median {np.median(rot):.2f} max {max(rot):.2f} deg, "
            f"translation median {np.median(tr):.1f} max {max(tr):.1f} mm")


def main(argv=None) -> dict:
    import yaml

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-points", type=int, default=2000, help="points per bunny scan (3DTK: 5x)")
    ap.add_argument("--set", action="append", default=[], help="override for DeepMapping/direct, e.g. optim.epochs=100")
    ap.add_argument("--only", choices=["bunny", "3dtk"], default=None)
    ap.add_argument("--data", type=Path, default=SHARED, help="folder holding bunny/ and 3dtk/ (default ../shared/data)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "real_3d")
    args = ap.parse_args(argv)
    sets = {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in args.set)}
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    report = {"date": str(date.today()), "machine": platform.machine(), "argv": argv}
    if args.only in (None, "bunny"):
        report["bunny"] = bunny(args, sets)
    if args.only in (None, "3dtk"):
        report["3dtk"] = threedtk(args, sets)
    report["total_s"] = time.perf_counter() - t0
    (args.out / "results.json").write_text(json.dumps(report, indent=1))
    print(f"total {report['total_s']:.0f} s; results in {args.out}")
    return report


if __name__ == "__main__":
    main()
