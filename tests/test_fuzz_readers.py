"""Fuzzed readers: every reader of ``deepmapping.io`` returns valid data or
raises InputError naming the file, in bounded time, whatever the input.

Inputs: random bytes, truncations and byte corruptions of a valid file, wrong counts and
garbage in place of the tokens of text files (header counts, column counts), NaN / inf / huge
numbers in text and in binary payloads, unicode file and folder names; then the same
corruptions of one file of a whole dataset folder, read by its loader (``load_scans``).

Hypothesis runs derandomized (the same examples on every machine, no example database);
``@example`` pins the inputs of the bugs these tests found. Each reader call runs under an
alarm (``HANG_S``): a hang fails the test instead of stalling it.
"""

from __future__ import annotations

import bz2
import contextlib
import dataclasses
import gzip
import io
import json
import re
import signal
import struct
import tempfile
import threading
from datetime import timedelta
from functools import cache
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import scipy.io
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from PIL import Image

from deepmapping.data import ScanSet
from deepmapping.errors import InputError
from deepmapping.io import carmen, depth, kitti, poses, poses3d, rgbd, sevenscenes, threedtk, tum_rgbd
from deepmapping.io.bunny import read_bun_conf
from deepmapping.io.loaders import load_scans, read_scan_file
from deepmapping.io.pcd import read_pcd
from deepmapping.io.ply import read_ply

# overflow / invalid-value warnings of NumPy on huge numbers, and loadtxt's "no data" before the
# reader's own "no point" error, are expected here
pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning", "ignore:loadtxt. input contained no data")
HANG_S = 20  # a reader that takes longer than this on a file of a few hundred bytes hangs
FUZZ = settings(max_examples=30, deadline=timedelta(seconds=5), derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.filter_too_much])
FUZZ_MORE = settings(FUZZ, max_examples=60)  # the targeted tests (header counts, numbers)


class Hang(BaseException):
    """A reader ran past HANG_S (BaseException: a reader's ``except Exception`` cannot hide it)."""


@contextlib.contextmanager
def time_limit(seconds: float):
    if not hasattr(signal, "setitimer") or threading.current_thread() is not threading.main_thread():
        yield  # no alarm here (Windows, a worker thread): the hypothesis deadline still reports slow cases
        return

    def on_alarm(*_):
        raise Hang(f"no answer after {seconds} s")

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def outcome(read: Callable, path: Path):
    """read(path), or None when it raised an InputError naming ``path`` (or a file under it) on one line.

    Any other exception propagates and fails the test, as does a hang.
    """
    with time_limit(HANG_S):
        try:
            return read(path)
        except InputError as e:
            msg = str(e)
            assert str(path) in msg, f"the message does not name {path}: {msg!r}"
            assert "\n" not in msg and msg.strip(), f"not one line: {msg!r}"
            return None


@contextlib.contextmanager
def scratch():
    with tempfile.TemporaryDirectory(prefix="dm-fuzz-") as d:
        yield Path(d)


# ------------------------------------------------------------------------------------------
# what valid data is
# ------------------------------------------------------------------------------------------
def _finite(a) -> bool:
    return bool(np.isfinite(np.asarray(a, dtype=np.float64)).all())


def cloud(out):
    """read_pcd / read_ply: (N, 3) float32; NaN allowed here (PCL's invalid points), the loaders refuse it."""
    assert isinstance(out, np.ndarray) and out.dtype == np.float32 and out.ndim == 2 and out.shape[1] == 3
    return out


def finite_cloud(out):
    assert isinstance(out, np.ndarray) and out.ndim == 2 and out.shape[1] == 3 and len(out) >= 1, out
    assert _finite(out)
    return out


def scan_file(out):
    xyz, dim = out
    assert dim in (2, 3)
    return cloud(xyz)


def rigid(t):
    t = np.asarray(t)
    assert t.shape[-2:] == (4, 4) and t.dtype == np.float64 and _finite(t), t
    assert np.abs(t[..., 3, :] - [0, 0, 0, 1]).max() < 1e-6
    r = t[..., :3, :3]
    assert np.abs(np.swapaxes(r, -1, -2) @ r - np.eye(3)).max() < 2e-3
    assert np.abs(np.linalg.det(r) - 1).max() < 2e-3
    return t


def poses_3d(out):
    assert out.ndim == 3 and len(out) >= 1
    return rigid(out)


def poses_2d(out):
    assert isinstance(out, np.ndarray) and out.dtype == np.float64 and out.ndim == 2 and out.shape[1] == 3
    assert len(out) >= 1 and _finite(out)
    return out


def carmen_log(log: carmen.CarmenLog):
    s = log.num_scans
    assert s >= 1 and log.ranges.shape == log.angles.shape and log.ranges.shape[0] == s
    for a in (log.angles, log.poses, log.odometry, log.timestamps):
        assert _finite(a) and len(a) == s
    assert log.poses.shape == log.odometry.shape == (s, 3)
    assert len(log.stamps) == s and (np.diff(log.lines) > 0).all()
    assert (log.max_range > 0).all()
    assert _finite(log.points()) and log.valid().dtype == bool
    return log.points()


def frames(out):
    mats, codes = out
    assert codes.dtype.kind == "i" and codes.shape == (len(mats),)
    return poses_3d(mats)


def calib(out):
    return out if out is None else rigid(out)


def json_object(out):
    assert isinstance(out, dict)
    return json.dumps(out, sort_keys=True)


def depth_image(out):
    assert isinstance(out, np.ndarray) and out.dtype == np.uint16 and out.ndim == 2
    return out


def camera(out: depth.Camera):
    vals = (out.fx, out.fy, out.cx, out.cy, out.depth_scale)
    assert _finite(vals) and out.fx > 0 and out.fy > 0
    return vals


def depth_list(out):
    stamps, files = out
    assert stamps.dtype == np.float64 and len(stamps) == len(files) >= 1 and _finite(stamps)
    assert (np.diff(stamps) > 0).all()
    return repr((stamps.tolist(), [f.name for f in files]))


def trajectory(out):
    stamps, mats = out
    assert stamps.shape == (len(mats),) and _finite(stamps)
    return np.concatenate([stamps, poses_3d(mats).ravel()])


def bun_conf(out):
    assert len(out) >= 2
    for name, pose in out:
        assert isinstance(name, str) and name
        rigid(pose)
    return np.stack([p for _, p in out])


def same(a, b) -> bool:
    if isinstance(a, str) or isinstance(b, str) or a is None or b is None:
        return a == b
    return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)


# ------------------------------------------------------------------------------------------
# valid sample files (built in memory, deterministic)
# ------------------------------------------------------------------------------------------
def rng(seed: int) -> np.random.Generator:
    return np.random.default_rng(seed)  # each sample its own seed: the same bytes whatever runs first

PCD_HEADER = ("# .PCD v0.7 - fuzz sample\nVERSION 0.7\nFIELDS x y z intensity normal\nSIZE 4 4 4 2 4\n"
              "TYPE F F F U F\nCOUNT 1 1 1 1 3\nWIDTH 4\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 4\nDATA {}\n")
PCD_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("i", "<u2"), ("n", "<f4", (3,))])


def pcd_records(n: int = 4) -> np.ndarray:
    rec = np.zeros(n, PCD_DTYPE)
    for k, f in enumerate(("x", "y", "z", "n")):
        rec[f] = rng(k).normal(0, 3, rec[f].shape).round(3)
    rec["i"] = np.arange(n) * 7
    return rec


def pcd_ascii() -> str:
    rows = [f"{r['x']:g} {r['y']:g} {r['z']:g} {r['i']} " + " ".join(f"{v:g}" for v in r["n"]) for r in pcd_records()]
    return PCD_HEADER.format("ascii") + "\n".join(rows) + "\n"


def pcd_binary() -> bytes:
    return PCD_HEADER.format("binary").encode() + pcd_records().tobytes()


def pcd_xy(points: np.ndarray) -> str:
    """A plain x y z ascii PCD (the authors' 2D scans)."""
    n = len(points)
    head = f"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nPOINTS {n}\nDATA ascii\n"
    return head + "".join(f"{x:.6g} {y:.6g} {z:.6g}\n" for x, y, z in points)


PLY_ASCII = """ply
format ascii 1.0
comment fuzz sample: a list property inside the vertex, then faces
element vertex 4
property float x
property float y
property float z
property list uchar int tags
element face 2
property list uchar int vertex_indices
end_header
0.5 1 2 2 7 8
1.5 -1 2.25 0
-3 0.125 4 1 9
2 2 2 3 1 2 3
3 0 1 2
3 1 2 3
"""


def ply_binary(points: np.ndarray | None = None) -> bytes:
    """Faces (list char int: signed counts) before the vertices, an extra double per vertex."""
    pts = rng(1).normal(0, 2, (4, 3)).astype("<f4") if points is None else np.asarray(points, "<f4")
    n = len(pts)
    head = ("ply\nformat binary_little_endian 1.0\nelement face 2\nproperty list char int vertex_indices\n"
            f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\nproperty double confidence\n"
            "end_header\n").encode()
    faces = b"".join(struct.pack("<b3i", 3, i, i + 1, i + 2) for i in range(2))
    rec = np.zeros(n, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("c", "<f8")])
    rec["x"], rec["y"], rec["z"], rec["c"] = pts[:, 0], pts[:, 1], pts[:, 2], 0.5
    return head + faces + rec.tobytes()


def flaser_log(num: int = 3) -> str:
    lines = ["# CARMEN logfile (fuzz sample)", "PARAM robot_front_laser_max 81.9 host 0.0"]
    for k in range(num):
        x, th = 1.0 * k, 0.1 * k
        lines.append(f"ODOM {x} 0.2 {th} 0.5 0 0 {1000.4 + k} host {0.4 + k}")
        ranges = " ".join(f"{r:g}" for r in (1.0 + k, 2.0, 3.5, 81.9, 2.5))
        lines.append(f"FLASER 5 {ranges} {x} 0.2 {th} {x} 0.2 {th} {1000.5 + k} host {0.5 + k}")
    return "\n".join(lines) + "\n"


def robotlaser_log(num: int = 3) -> str:
    lines = []
    for k in range(num):
        x, th = 1.0 * k, 0.1 * k
        lines.append(f"ROBOTLASER1 0 -1.5708 3.14159 0.785398 50 0.01 0 5 1 2 {3 + k} 4 5 2 0.5 0.5 "
                     f"{x} 0.1 {th} {x} 0.1 {th} 0.3 0 0.5 0.5 0 {2000.5 + k} host {0.5 + k}")
    return "\n".join(lines) + "\n"


def points_3d_text(header: bool = True, seed: int = 2) -> str:
    pts = rng(seed).uniform(60, 400, (6, 3)).round(2) * [1, -1, 1]
    head = "# 3DTK scan: x y z reflectance\n" if header else ""
    return head + "".join(f"{x} {y} {z} {i}\n" for i, (x, y, z) in enumerate(pts))


def frames_text() -> str:
    rows = []
    for code, (tx, th) in enumerate(((10.0, 0.0), (12.5, 0.2))):
        m = np.eye(4)
        m[:3, :3] = [[np.cos(th), 0, np.sin(th)], [0, 1, 0], [-np.sin(th), 0, np.cos(th)]]
        m[:3, 3] = [tx, -2.0, 30.0]
        rows.append(" ".join(f"{v:.9g}" for v in m.T.ravel()) + f" {code}")
    return "\n".join(rows) + "\n"


def rigid_poses(k: int, seed: int = 0) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    out = np.tile(np.eye(4), (k, 1, 1))
    out[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.3, (k, 3))).as_matrix()
    out[:, :3, 3] = rng.normal(0, 2, (k, 3))
    return out


def kitti_text(p: np.ndarray) -> str:
    return "".join(" ".join(f"{v:.17g}" for v in m[:3].ravel()) + "\n" for m in p)


def tum_text(p: np.ndarray) -> str:
    from deepmapping.geometry import se3

    q = se3.to_xyz_quat(p)
    return "# timestamp tx ty tz qx qy qz qw\n" + "".join(
        f"{k} " + " ".join(f"{v:.17g}" for v in row) + "\n" for k, row in enumerate(q))


def calib_text() -> str:
    tr = rigid_poses(1, seed=5)[0]
    return "P0: " + " ".join(["7.1e+02"] + ["0"] * 11) + "\nTr: " + " ".join(f"{v:.17g}" for v in tr[:3].ravel()) + "\n"


def npy(arr) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.asarray(arr), allow_pickle=False)
    return buf.getvalue()


def mat(arr, key: str = "pose") -> bytes:
    buf = io.BytesIO()
    scipy.io.savemat(buf, {key: np.asarray(arr)})
    return buf.getvalue()


def png16(img) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.asarray(img, np.uint16)).save(buf, format="PNG")
    return buf.getvalue()


def depth_images(k: int = 3) -> list[np.ndarray]:
    return [(1500 + 100 * i + 37 * np.add.outer(np.arange(6), np.arange(8))).astype(np.uint16) for i in range(k)]


def pose_4x4_text(p: np.ndarray) -> str:
    return "".join(" ".join(f"{v:.9e}" for v in row) + "\n" for row in p)


def tum_stamped_text(p: np.ndarray, stamps) -> str:
    from deepmapping.geometry import se3

    return "# ground truth\n" + "".join(f"{t:.4f} " + " ".join(f"{v:.9g}" for v in row) + "\n"
                                       for t, row in zip(stamps, se3.to_xyz_quat(p)))


DEPTH_STAMPS = (1305031102.175304, 1305031102.211214, 1305031102.243211)
DEPTH_LIST = "# depth maps\n# timestamp filename\n" + "".join(f"{t:.6f} depth/{t:.6f}.png\n" for t in DEPTH_STAMPS)
K_TEXT = " 5.0e+00\t 0.0e+00\t 3.5e+00\t\n 0.0e+00\t 5.0e+00\t 2.5e+00\t\n 0.0e+00\t 0.0e+00\t 1.0e+00\t\n"
INTRINSICS = {"width": 8, "height": 6, "fx": 5.0, "fy": 5.0, "cx": 3.5, "cy": 2.5, "depth_scale": 1000.0,
              "max_depth_m": 10.0}
BUN_CONF = ("camera 0.0 0.0 0.3 0.0 0.0 0.0 1.0\n"
            "bmesh bun000.ply 0 0 0 0 0 0 1\n"
            "bmesh bun045.ply -0.0520 -0.000983 -0.0170 -0.0002 0.3897 0.0 0.9209\n")


@dataclasses.dataclass(frozen=True)
class Spec:
    """One reader and a valid sample: ``text`` (encoded by ``encode``) or ``raw`` bytes."""

    name: str
    suffix: str  # the file name ends with this (readers that pick the format by suffix need it)
    read: Callable
    valid: Callable  # raises AssertionError on invalid data; returns something to compare
    text: Callable[[], str] | None = None
    raw: Callable[[], bytes] | None = None
    encode: Callable[[str], bytes] = str.encode

    @property
    def sample(self) -> bytes:
        return _sample(self)

    def __str__(self) -> str:
        return self.name


@cache
def _sample(spec: Spec) -> bytes:
    return spec.encode(spec.text()) if spec.text is not None else spec.raw()


_pcd_text = cache(pcd_ascii)
_frames = cache(frames_text)
_3d = cache(points_3d_text)
SPECS = [
    Spec("pcd-ascii", ".pcd", read_pcd, cloud, text=_pcd_text),
    Spec("pcd-binary", ".pcd", read_pcd, cloud, raw=cache(pcd_binary)),
    Spec("ply-ascii", ".ply", read_ply, cloud, text=lambda: PLY_ASCII),
    Spec("ply-binary", ".ply", read_ply, cloud, raw=cache(ply_binary)),
    Spec("carmen-flaser", ".clf", carmen.read_carmen, carmen_log, text=flaser_log),
    Spec("carmen-robotlaser", ".log", carmen.read_carmen, carmen_log, text=robotlaser_log),
    Spec("carmen-gz", ".clf.gz", carmen.read_carmen, carmen_log, text=flaser_log,
         encode=lambda t: gzip.compress(t.encode(), mtime=0)),
    Spec("carmen-bz2", ".log.bz2", carmen.read_carmen, carmen_log, text=robotlaser_log,
         encode=lambda t: bz2.compress(t.encode())),
    Spec("3dtk-3d", ".3d", threedtk.read_3d, finite_cloud, text=_3d),
    Spec("3dtk-xyz", ".xyz", threedtk.read_3d, finite_cloud, text=lambda: points_3d_text(header=False)),
    Spec("3dtk-pose", ".pose", threedtk.read_pose, rigid, text=lambda: "10.5 -2 30\n0.5 12 -1.25\n"),
    Spec("3dtk-frames", ".frames", lambda p: threedtk.read_frames(p, return_codes=True), frames, text=_frames),
    Spec("kitti-bin", ".bin", kitti.read_velodyne_bin, finite_cloud,
         raw=lambda: rng(3).normal(0, 5, (5, 4)).astype("<f4").tobytes()),
    Spec("kitti-calib", ".txt", kitti.read_calib_tr, calib, text=calib_text),
    Spec("kitti-poses", ".txt", poses3d.read_kitti_poses, poses_3d, text=lambda: kitti_text(rigid_poses(3))),
    Spec("tum-poses", ".tum", poses3d.read_tum_poses, poses_3d, text=lambda: tum_text(rigid_poses(3, 1))),
    Spec("poses-3d-text", ".txt", poses3d.read_poses_3d, poses_3d, text=lambda: tum_text(rigid_poses(2, 2))),
    Spec("poses-3d-npy", ".npy", poses3d.read_poses_3d, poses_3d, raw=lambda: npy(rigid_poses(3, 3))),
    Spec("poses-2d-text", ".txt", poses.read_poses, poses_2d,
         text=lambda: "# x y theta\n0 0 0\n1.5, 0.25, 0.1  # comment\n\n3 0.5 -0.2\n"),
    Spec("gt-pose-mat", ".mat", poses.read_poses, poses_2d, raw=lambda: mat([[0, 0, 0], [8, 1, 0.1], [16, 3, 0.2]])),
    Spec("poses-2d-npy", ".npy", poses.read_poses, poses_2d, raw=lambda: npy([[0, 0, 0], [1, 0.5, 0.1]])),
    Spec("scan-npy", ".npy", read_scan_file, scan_file, raw=lambda: npy(rng(4).normal(0, 1, (6, 2)).astype("f4"))),
    Spec("scan-xyz", ".xyz", read_scan_file, scan_file, text=lambda: "# x y z\n1 2 3\n4,5,6\n-1 0.5 2 99\n"),
    Spec("depth-png", ".png", rgbd.read_depth_png, depth_image, raw=lambda: png16(depth_images(1)[0])),
    Spec("intrinsics-json", ".json", rgbd.read_json, json_object, text=lambda: json.dumps(INTRINSICS)),
    Spec("bun-conf", ".conf", read_bun_conf, bun_conf, text=lambda: BUN_CONF),
    Spec("7scenes-pose", ".pose.txt", sevenscenes.read_pose_matrix, rigid, text=lambda: pose_4x4_text(rigid_poses(1, 9)[0])),
    Spec("camera-k", ".txt", lambda p: depth.read_k_matrix(p, 1000.0), camera, text=lambda: K_TEXT),
    Spec("tum-depth-list", ".txt", tum_rgbd.read_depth_list, depth_list, text=lambda: DEPTH_LIST),
    Spec("tum-trajectory", ".txt", poses3d.read_tum_trajectory, trajectory,
         text=lambda: tum_stamped_text(rigid_poses(3, 10), np.array(DEPTH_STAMPS) + 0.003)),
]
TEXT_SPECS = [s for s in SPECS if s.text is not None]
BY_NAME = {s.name: s for s in SPECS}


def read_bytes(spec: Spec, data: bytes, name: str = "sample"):
    """Write ``data`` as <tmp>/<name><suffix>, read it with the spec's reader, check the outcome."""
    with scratch() as d:
        path = d / f"{name}{spec.suffix}"
        path.write_bytes(data)
        out = outcome(spec.read, path)
        return None if out is None else spec.valid(out)


# ------------------------------------------------------------------------------------------
# corruptions
# ------------------------------------------------------------------------------------------
NASTY = ["nan", "NaN", "-nan", "inf", "-inf", "Infinity", "1e400", "-1e400", "1e308", "-1e308", "3.5e38",
         "1e39", "1e-400", "0", "-0", "-1", "-7", "1e20", "99999999999999999999999", "4294967296",
         "2147483648", "-2147483649", "1000000000000", "0x10", "1_000", "1,5", "١٢", "½", "--1", ".", "e5", "",
         "1 2", "\n", "#", "ply", "FLASER", "end_header", "DATA", "binary", "element", "list"]
TOKENS = (st.sampled_from(NASTY) | st.floats().map(repr) | st.integers(-2**80, 2**80).map(str)
          | st.text(max_size=4))
NUMBERS = (st.sampled_from(["nan", "-nan", "inf", "-inf", "1e400", "-1e400", "1e308", "-1e308", "1e39",
                            "1e-320", "0", "-0"])
           | st.floats(allow_nan=True, allow_infinity=True).map(repr)
           | st.floats(min_value=-1e300, max_value=1e300).map(lambda v: f"{v:.17g}"))
NUMBER_RE = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")


def replace_tokens(text: str, subs: list[tuple[int, str]], numeric: bool = False) -> str:
    """Replace the i-th (modulo) whitespace-separated token (only numbers when ``numeric``) by s."""
    parts = re.split(r"(\s+)", text)
    idx = [i for i, p in enumerate(parts) if p and not p.isspace() and (not numeric or NUMBER_RE.match(p))]
    for i, s in subs:
        if idx:
            parts[idx[i % len(idx)]] = s
    return "".join(parts)


def mutate(raw: bytes, edits: list[tuple[int, int]]) -> bytes:
    """Set byte (pos modulo length) to value; a value of 256 deletes it, 257 doubles it."""
    b = bytearray(raw)
    for pos, val in edits:
        if not b:
            break
        i = pos % len(b)
        if val == 256:
            del b[i]
        elif val == 257:
            b.insert(i, b[i])
        else:
            b[i] = val
    return bytes(b)


EDITS = st.lists(st.tuples(st.integers(0, 2**16), st.integers(0, 257)), min_size=1, max_size=6)
SUBS = st.lists(st.tuples(st.integers(0, 2**16), TOKENS), min_size=1, max_size=3)
NUMBER_SUBS = st.lists(st.tuples(st.integers(0, 2**16), NUMBERS), min_size=1, max_size=6)
NAME_CHARS = st.characters(codec="utf-8", exclude_categories=("Cc", "Cs", "Zl", "Zp"), exclude_characters="/\\")
NAMES = st.text(NAME_CHARS, min_size=1, max_size=12).filter(lambda s: s.strip() and not s.startswith("."))


# ------------------------------------------------------------------------------------------
# every reader: samples, random bytes, truncations, corruptions, tokens, numbers, unicode names
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("spec", SPECS, ids=str)
def test_the_valid_sample_reads(spec):
    assert read_bytes(spec, spec.sample) is not None, f"{spec.name}: the valid sample was refused"


@pytest.mark.parametrize("spec", SPECS, ids=str)
@FUZZ
@given(data=st.binary(max_size=400))
@example(data=b"")
@example(data=b"\x1f\x8b\x08\x00" + bytes(40))  # a gzip header, then nothing valid: was zlib.error
def test_random_bytes(spec, data):
    read_bytes(spec, data)


@pytest.mark.parametrize("spec", SPECS, ids=str)
@FUZZ
@given(cut=st.floats(0, 1, exclude_max=True))
@example(cut=0.0)
@example(cut=0.5)
def test_truncated_file(spec, cut):
    read_bytes(spec, spec.sample[: int(cut * len(spec.sample))])


@pytest.mark.parametrize("spec", SPECS, ids=str)
@FUZZ
@given(edits=EDITS)
@example(edits=[(12, 0x55)])  # carmen-gz: a corrupt deflate stream (zlib.error escaped)
def test_corrupted_bytes(spec, edits):
    read_bytes(spec, mutate(spec.sample, edits))


@pytest.mark.parametrize("spec", TEXT_SPECS, ids=str)
@FUZZ
@given(subs=SUBS)
def test_garbage_tokens(spec, subs):
    """Any token (header count, column, keyword) replaced by garbage, nothing or several tokens."""
    read_bytes(spec, spec.encode(replace_tokens(spec.text(), subs)))


@pytest.mark.parametrize("spec", TEXT_SPECS, ids=str)
@FUZZ
@given(subs=NUMBER_SUBS)
def test_nan_inf_huge_numbers_in_text(spec, subs):
    read_bytes(spec, spec.encode(replace_tokens(spec.text(), subs, numeric=True)))


@pytest.mark.parametrize("spec", SPECS, ids=str)
@settings(FUZZ, max_examples=15)
@given(folder=NAMES, name=NAMES)
@example(folder="données ✓", name="スキャン 001")
def test_unicode_paths(spec, folder, name):
    """A valid file under a unicode folder and file name reads as the plain one; a missing one is named."""
    want = read_bytes(spec, spec.sample)
    with scratch() as d:
        path = d / folder / f"{name}{spec.suffix}"
        path.parent.mkdir()
        path.write_bytes(spec.sample)
        got = outcome(spec.read, path)
        assert got is not None, f"{path}: refused under a unicode name"
        assert same(spec.valid(got), want)
        path.unlink()
        assert outcome(spec.read, path) is None


# ------------------------------------------------------------------------------------------
# header counts and binary payloads, per format
# ------------------------------------------------------------------------------------------
COUNTS = st.integers(-2**66, 2**66) | st.integers(-3, 20)


def _pcd_with(header_line: str, value: str, kind: str) -> bytes:
    spec = BY_NAME[f"pcd-{kind}"]
    text_end = spec.sample.index(b"DATA")
    head = spec.sample[:text_end].decode()
    head = re.sub(rf"^{header_line} .*$", f"{header_line} {value}", head, flags=re.M)
    return head.encode() + spec.sample[text_end:]


@FUZZ_MORE
@given(key=st.sampled_from(["POINTS", "WIDTH", "HEIGHT", "COUNT", "SIZE", "TYPE", "FIELDS"]),
       values=st.lists(COUNTS, max_size=6), kind=st.sampled_from(["ascii", "binary"]))
@example(key="POINTS", values=[10**12], kind="binary")  # was MemoryError
@example(key="POINTS", values=[10**12], kind="ascii")  # was MemoryError
@example(key="COUNT", values=[1, 1, 1, 1, 10**15], kind="binary")  # was ValueError (dtype too big)
@example(key="COUNT", values=[1, 1, 1, 2**64, 1], kind="ascii")  # was OverflowError (np.cumsum)
def test_pcd_header_counts(key, values, kind):
    letters = {"TYPE": "FUI", "FIELDS": "xyzin"}.get(key)
    value = " ".join(letters[v % len(letters)] if letters else str(v) for v in values)
    read_bytes(BY_NAME[f"pcd-{kind}"], _pcd_with(key, value, kind))


@FUZZ_MORE
@given(element=st.sampled_from(["face", "vertex"]), count=COUNTS, list_len=st.integers(-128, 127),
       binary=st.booleans())
@example(element="vertex", count=-3, list_len=3, binary=False)  # was ValueError (negative dimensions)
@example(element="vertex", count=10**12, list_len=3, binary=False)  # was MemoryError
@example(element="vertex", count=-3, list_len=3, binary=True)  # was ValueError (negative dimensions)
@example(element="face", count=10**9, list_len=-1, binary=True)
def test_ply_element_counts_and_list_lengths(element, count, list_len, binary):
    n = {"vertex": 4, "face": 2}[element]
    if binary:
        raw = BY_NAME["ply-binary"].sample.replace(f"element {element} {n}".encode(), f"element {element} {count}".encode())
        start = raw.index(b"end_header\n") + len(b"end_header\n")
        raw = raw[:start] + struct.pack("<b", list_len) + raw[start + 1:]  # the first face's list length
    else:
        raw = PLY_ASCII.replace(f"element {element} {n}", f"element {element} {count}")
        raw = raw.replace("0.5 1 2 2 7 8", f"0.5 1 2 {list_len} 7 8").encode()
    read_bytes(BY_NAME["ply-binary" if binary else "ply-ascii"], raw)


@FUZZ_MORE
@given(count=COUNTS, fill=st.binary(min_size=1, max_size=4),
       types=st.sampled_from(["char char", "char int", "uchar int", "short uchar", "int char", "char double"]))
@example(count=10**9, fill=b"\xff", types="char char")  # was a hang: length -1 of 1-byte items, no progress
@example(count=5, fill=b"\x00", types="uchar int")
def test_ply_list_records(count, fill, types):
    """An element of list records before the vertices, with any count and record bytes."""
    head = (f"ply\nformat binary_little_endian 1.0\nelement face {count}\nproperty list {types} v\n"
            "element vertex 1\nproperty float x\nproperty float y\nend_header\n").encode()
    read_bytes(BY_NAME["ply-binary"], head + fill * 8 + bytes(8))


@FUZZ_MORE
@given(values=st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=0, max_size=40),
       fmt=st.sampled_from(["pcd", "ply", "kitti-bin", "scan-npy", "scan-npy-f64"]))
def test_nan_inf_huge_in_binary_clouds(values, fmt):
    """Binary payloads with NaN / inf / extreme floats: the readers keep the numbers (PCL marks invalid
    points with NaN) or refuse them, but do not crash; the loaders refuse them (test_loader_...)."""
    pts = np.asarray(values[: len(values) // 3 * 3], np.float32).reshape(-1, 3)
    if fmt == "pcd":
        rec = pcd_records(len(pts))
        rec["x"], rec["y"], rec["z"] = pts.T
        head = PCD_HEADER.replace("WIDTH 4", f"WIDTH {len(pts)}").replace("POINTS 4", f"POINTS {len(pts)}")
        raw = head.format("binary").encode() + rec.tobytes()
        read_bytes(BY_NAME["pcd-binary"], raw)
    elif fmt == "ply":
        read_bytes(BY_NAME["ply-binary"], ply_binary(pts))
    elif fmt == "kitti-bin":
        out = read_bytes(BY_NAME["kitti-bin"], np.column_stack([pts, np.ones(len(pts), "f4")]).astype("<f4").tobytes())
        assert out is None or np.array_equal(out, pts)
    else:
        dt = "f8" if fmt.endswith("f64") else "f4"
        read_bytes(BY_NAME["scan-npy"], npy(np.asarray(values, dt)[: len(values) // 2 * 2].reshape(-1, 2)))


@FUZZ_MORE
@given(vals=st.lists(st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from([1e308, -1e308, 1e-320]),
                     min_size=0, max_size=48),
       fmt=st.sampled_from(["2d-npy", "2d-mat", "3d-npy-44", "3d-npy-34"]))
@example(vals=[0.0, 0.0, np.nan], fmt="2d-mat")
def test_nan_inf_huge_in_binary_poses(vals, fmt):
    a = np.asarray(vals, np.float64)
    if fmt.startswith("2d"):
        a = a[: len(a) // 3 * 3].reshape(-1, 3)
        spec = BY_NAME["gt-pose-mat" if fmt == "2d-mat" else "poses-2d-npy"]
        read_bytes(spec, mat(a) if fmt == "2d-mat" else npy(a))
    else:
        rows = 4 if fmt.endswith("44") else 3
        a = a[: len(a) // (4 * rows) * 4 * rows].reshape(-1, rows, 4)
        if len(a) and rows == 4:
            a[:, 3] = [0, 0, 0, 1]
        read_bytes(BY_NAME["poses-3d-npy"], npy(a))


@FUZZ_MORE
@given(n=COUNTS, m=COUNTS, robot=st.booleans())
@example(n=-5, m=0, robot=False)
@example(n=5, m=-8, robot=True)
def test_carmen_beam_and_remission_counts(n, m, robot):
    if robot:
        text = robotlaser_log(2).replace("0 5 1 2", f"0 {n} 1 2", 1).replace(" 4 5 2 0.5 0.5 ", f" 4 5 {m} 0.5 0.5 ", 1)
        read_bytes(BY_NAME["carmen-robotlaser"], text.encode())
    else:
        read_bytes(BY_NAME["carmen-flaser"], flaser_log(2).replace("FLASER 5", f"FLASER {n}", 1).encode())


@FUZZ_MORE
@given(start=NUMBERS, fov=NUMBERS, max_range=NUMBERS)
@example(start="nan", fov="3.14159", max_range="50")  # was accepted: NaN beam angles
@example(start="inf", fov="3.14159", max_range="50")
def test_carmen_robotlaser_beam_layout(start, fov, max_range):
    text = robotlaser_log(2).replace("0 -1.5708 3.14159 0.785398 50 ", f"0 {start} {fov} 0.785398 {max_range} ")
    read_bytes(BY_NAME["carmen-robotlaser"], text.encode())


@FUZZ_MORE
@given(code=NUMBERS | st.integers(-2**70, 2**70).map(str))
@example(code="inf")  # was OverflowError
@example(code="nan")  # was ValueError
@example(code="1e30")  # was an object array of codes
def test_3dtk_frames_algorithm_code(code):
    read_bytes(BY_NAME["3dtk-frames"], _frames().replace(" 1\n", f" {code}\n").encode())


@FUZZ_MORE
@given(vals=st.lists(NUMBERS, min_size=12, max_size=12))
@example(vals=["nan"] * 12)  # was accepted (NaN LiDAR poses after inv(Tr))
@example(vals=["0"] * 12)  # was accepted: singular, np.linalg.inv raised LinAlgError in load_kitti
def test_kitti_calib_tr(vals):
    read_bytes(BY_NAME["kitti-calib"], f"P0: 1 0 0 0 0 1 0 0 0 0 1 0\nTr: {' '.join(vals)}\n".encode())


@FUZZ_MORE
@given(q=st.lists(NUMBERS, min_size=4, max_size=4))
@example(q=["1e200", "1e200", "0", "0"])  # was a zero matrix (|q|^2 overflowed)
@example(q=["1e-7", "0", "0", "0"])
def test_tum_quaternions(q):
    read_bytes(BY_NAME["tum-poses"], f"0 1 2 3 {' '.join(q)}\n1 0 0 0 0 0 0 1\n".encode())


@FUZZ_MORE
@given(doc=st.recursive(st.none() | st.booleans() | st.floats() | st.integers(-10**400, 10**400) | st.text(max_size=5),
                        lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=6), c, max_size=4),
                        max_leaves=12),
       keys=st.lists(st.sampled_from(sorted(INTRINSICS)), max_size=3))
@example(doc=10**400, keys=["fx"])  # was OverflowError (an int too large for a float)
@example(doc="deep", keys=[])
def test_rgbd_intrinsics_and_meta(doc, keys):
    """load_rgbd on intrinsics.json / meta.json holding anything JSON can."""
    with scratch() as d:
        files = rgbd_files()
        intr = dict(INTRINSICS)
        for k in keys:
            intr[k] = doc
        files["intrinsics.json"] = ("[" * 100_000 if doc == "deep" else json.dumps(intr)).encode()
        files["meta.json"] = json.dumps({"pose_dof": doc}).encode()
        root = d / "traj"
        write_tree(root, files)
        out = outcome(lambda p: rgbd.load_rgbd(p), root)
        assert out is None or valid_scanset(out)


# ------------------------------------------------------------------------------------------
# loaders: one file of a valid dataset folder corrupted
# ------------------------------------------------------------------------------------------
def write_tree(root: Path, files: dict[str, bytes]) -> None:
    for rel, raw in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(raw)


def valid_scanset(s: ScanSet) -> bool:
    s.validate()
    assert _finite(s.points) and s.num_scans >= 2 and s.valid.any(axis=1).all()
    for p in (s.gt_poses, s.init_poses):
        assert p is None or _finite(p)
    return True


def scans_2d(k: int = 3, n: int = 12) -> list[np.ndarray]:
    ang = np.linspace(-np.pi, np.pi, n, endpoint=False)
    return [np.column_stack([(2 + 0.1 * i) * np.cos(ang), (1.5 + 0.05 * i) * np.sin(ang)]) for i in range(k)]


def authors_files() -> dict[str, bytes]:
    files = {f"{i:03d}.pcd": pcd_xy(np.column_stack([s / 512, np.zeros(len(s))])).encode()
             for i, s in enumerate(scans_2d())}
    files["gt_pose.mat"] = mat([[0, 0, 0], [3, 1, 0.05], [6, 2, 0.1]])
    return files


def folder_2d_files() -> dict[str, bytes]:
    files = {f"{i}.npy": npy(s.astype("f4")) for i, s in enumerate(scans_2d())}
    files["poses.txt"] = b"0 0 0\n0.1 0 0.01\n0.2 0.05 0.02\n"
    return files


def clouds_3d_files() -> dict[str, bytes]:
    files = {f"{i:02d}.xyz": "".join(f"{x:.5g} {y:.5g} {z:.5g}\n" for x, y, z in rng(10 + i).normal(0, 3, (9, 3)))
             .encode() for i in range(3)}
    files["poses.txt"] = kitti_text(rigid_poses(3, 4)).encode()
    return files


def lidar_files() -> dict[str, bytes]:
    files = {f"scans/{i:06d}.ply": ply_binary(rng(20 + i).normal(0, 4, (7, 3))) for i in range(2)}
    files["scans/000002.pcd"] = pcd_binary()
    files["gt_poses.txt"] = kitti_text(rigid_poses(3, 6)).encode()
    files["meta.json"] = b'{"pose_dof": 6}'
    return files


@cache
def _rgbd_files() -> tuple[tuple[str, bytes], ...]:
    files = {f"depth/{i:06d}.png": png16(img) for i, img in enumerate(depth_images())}
    files["intrinsics.json"] = json.dumps(INTRINSICS).encode()
    files["gt_poses.txt"] = tum_text(rigid_poses(3, 7)).encode()
    files["meta.json"] = b'{"pose_dof": 6}'
    return tuple(files.items())


def rgbd_files() -> dict[str, bytes]:
    return dict(_rgbd_files())


def sevenscenes_files() -> dict[str, bytes]:
    files = {}
    for i, (img, pose) in enumerate(zip(depth_images(), rigid_poses(3, 11))):
        files[f"frame-{i:06d}.depth.png"] = png16(img)
        files[f"frame-{i:06d}.pose.txt"] = pose_4x4_text(pose).encode()
    files["camera-intrinsics.txt"] = K_TEXT.encode()
    return files


def tum_rgbd_files() -> dict[str, bytes]:
    files = {f"depth/{t:.6f}.png": png16(img) for t, img in zip(DEPTH_STAMPS, depth_images())}
    files["depth.txt"] = DEPTH_LIST.encode()
    files["groundtruth.txt"] = tum_stamped_text(rigid_poses(3, 12), np.array(DEPTH_STAMPS) - 0.004).encode()
    files["camera-intrinsics.txt"] = K_TEXT.encode()  # the images are 8 x 6, not TUM's 640 x 480
    return files


def threedtk_files() -> dict[str, bytes]:
    files = {}
    for i in range(3):
        files[f"scan{i:03d}.3d"] = points_3d_text(seed=30 + i).encode()
        files[f"scan{i:03d}.pose"] = f"{10 * i} -2 30\n0 {5 * i} 0\n".encode()
        files[f"scan{i:03d}.frames"] = frames_text().encode()
    return files


def kitti_files() -> dict[str, bytes]:
    files = {f"velodyne/{i:06d}.bin": rng(40 + i).normal(0, 5, (6, 4)).astype("<f4").tobytes() for i in range(3)}
    files["calib.txt"] = calib_text().encode()
    files["poses.txt"] = kitti_text(rigid_poses(3, 8)).encode()
    return files


def bunny_files() -> dict[str, bytes]:
    return {"bun.conf": BUN_CONF.encode(), "bun000.ply": ply_binary(rng(50).normal(0, 0.05, (8, 3))),
            "bun045.ply": PLY_ASCII.encode()}


LAYOUTS: dict[str, tuple[str, Callable[[], dict[str, bytes]]]] = {
    # name: (load_scans format, files); "carmen" is one log file, the others a folder
    "authors": ("authors", authors_files),
    "folder-2d": ("folder", folder_2d_files),
    "clouds-3d": ("folder", clouds_3d_files),
    "lidar": ("lidar", lidar_files),
    "rgbd": ("rgbd", rgbd_files),
    "7scenes": ("7scenes", sevenscenes_files),
    "tum-rgbd": ("tum-rgbd", tum_rgbd_files),
    "3dtk": ("3dtk", threedtk_files),
    "kitti": ("kitti", kitti_files),
    "bunny": ("bunny", bunny_files),
    "carmen": ("carmen", lambda: {"log.clf": flaser_log(4).encode()}),
}


def load_layout(layout: str, root: Path, files: dict[str, bytes]):
    fmt, _ = LAYOUTS[layout]
    if layout == "carmen":
        path = root.with_name(root.name + ".clf")
        path.write_bytes(files["log.clf"])
        return outcome(lambda p: load_scans(p, fmt=fmt, keyframes="every:1"), path)
    write_tree(root, files)
    return outcome(lambda p: load_scans(p, fmt=fmt), root)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_the_valid_layout_loads(layout, tmp_path):
    scans = load_layout(layout, tmp_path / "data", LAYOUTS[layout][1]())
    assert scans is not None and valid_scanset(scans)


@pytest.mark.parametrize("layout", LAYOUTS)
@settings(FUZZ, max_examples=40)
@given(data=st.data(), root_name=NAMES)
def test_loader_with_one_corrupted_file(layout, data, root_name):
    """A valid dataset with one file truncated, corrupted, replaced, deleted or given garbage tokens or
    NaN / inf / huge numbers, in a folder with a unicode name: a validated ScanSet or one InputError
    naming a path inside the dataset (the loader's own checks, e.g. finite points, included)."""
    files = LAYOUTS[layout][1]()
    target = data.draw(st.sampled_from(sorted(files)), label="file")
    raw = files[target]
    how = data.draw(st.sampled_from(["truncate", "bytes", "random", "tokens", "numbers", "delete"]), label="how")
    if how == "truncate":
        files[target] = raw[: data.draw(st.integers(0, max(len(raw) - 1, 0)), label="cut")]
    elif how == "bytes":
        files[target] = mutate(raw, data.draw(EDITS, label="edits"))
    elif how == "random":
        files[target] = data.draw(st.binary(max_size=200), label="bytes")
    elif how == "delete" and layout != "carmen":
        del files[target]
    else:
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:  # a binary file: corrupt its bytes instead
            files[target] = mutate(raw, data.draw(EDITS, label="edits"))
        else:
            subs = data.draw(NUMBER_SUBS if how == "numbers" else SUBS, label="subs")
            files[target] = replace_tokens(text, subs, numeric=how == "numbers").encode()
    with scratch() as d:
        scans = load_layout(layout, d / root_name, files)
    assert scans is None or valid_scanset(scans)


@pytest.mark.parametrize("tr", [["0"] * 12, ["nan"] * 12, ["2", "0", "0", "0", "0", "2", "0", "0", "0", "0", "2", "0"]],
                         ids=["singular", "nan", "scaled"])
def test_kitti_loader_refuses_a_calib_tr_that_is_not_rigid(tr, tmp_path):
    """Tr is inverted: a singular one raised LinAlgError, a NaN one gave NaN poses."""
    files = kitti_files()
    files["calib.txt"] = f"Tr: {' '.join(tr)}\n".encode()
    root = tmp_path / "seq"
    assert load_layout("kitti", root, files) is None
    with pytest.raises(InputError, match=r"calib\.txt(: line |:)1:"):
        load_scans(root, fmt="kitti")


@pytest.mark.parametrize("layout", ["authors", "folder-2d", "lidar", "kitti"])
@settings(FUZZ, max_examples=20)
@given(value=st.sampled_from([np.nan, np.inf, -np.inf, 3e38, -3e38]), at=st.integers(0, 10**6))
def test_loader_refuses_nan_inf_points(layout, value, at):
    """NaN / inf coordinates in one scan (binary payloads too): the loader refuses the dataset, naming
    the file; a huge finite one (3e38) may pass."""
    files = LAYOUTS[layout][1]()
    name = sorted(n for n in files if n.endswith((".pcd", ".npy", ".ply", ".bin")))[0]
    if name.endswith(".npy"):
        arr = np.load(io.BytesIO(files[name]))
        arr.flat[at % arr.size] = value
        files[name] = npy(arr)
    elif name.endswith(".pcd"):
        rows = files[name].decode().split("DATA ascii\n")[1].splitlines()
        pts = np.array([[float(v) for v in ln.split()] for ln in rows])
        pts.flat[at % pts.size] = value
        files[name] = pcd_xy(pts).encode()
    elif name.endswith(".ply"):
        pts = read_bytes(BY_NAME["ply-binary"], files[name]).copy()
        pts.flat[at % pts.size] = value
        files[name] = ply_binary(pts)
    else:
        arr = np.frombuffer(files[name], "<f4").copy().reshape(-1, 4)
        arr[:, :3].flat[at % (arr.size // 4 * 3)] = value
        files[name] = arr.tobytes()
    with scratch() as d:
        scans = load_layout(layout, d / "data", files)
    if not np.isfinite(value):
        assert scans is None, f"{layout}: {value} in {name} was accepted"
