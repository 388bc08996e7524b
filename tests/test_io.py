"""File I/O: PCD, PLY, pose files and the scan-folder loaders."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from deepmapping.errors import ConfigError, InputError
from deepmapping.io.loaders import LOADERS, detect_format, load_scans, natural_key, register_loader
from deepmapping.io.pcd import read_pcd, write_pcd
from deepmapping.io.ply import read_ply, write_ply
from deepmapping.io.poses import (
    read_gt_mat,
    read_pose_text,
    read_poses,
    write_gt_mat,
    write_pose_text,
    write_poses_npy,
)

RNG = np.random.default_rng(0)


def _rand_pts(n: int = 50) -> np.ndarray:
    return (RNG.standard_normal((n, 3)) * np.array([1e3, 1e-3, 7.0])).astype(np.float32)


# ---------------------------------------------------------------- PCD


@pytest.mark.parametrize("binary", [True, False])
def test_pcd_round_trip_bit_exact(tmp_path: Path, binary: bool) -> None:
    pts = _rand_pts()
    pts[0] = [np.float32(1) / 3, np.finfo(np.float32).tiny, -np.finfo(np.float32).max]
    f = tmp_path / "a.pcd"
    write_pcd(f, pts, binary=binary)
    out = read_pcd(f)
    assert out.dtype == np.float32 and out.shape == pts.shape
    assert out.tobytes() == pts.tobytes()
    assert [p.name for p in tmp_path.iterdir()] == ["a.pcd"]  # no temp file left behind


def test_pcd_binary_header_layout(tmp_path: Path) -> None:
    write_pcd(tmp_path / "a.pcd", np.zeros((4, 3)))
    raw = (tmp_path / "a.pcd").read_bytes()
    head = raw.split(b"DATA binary\n")[0].decode()
    for line in ("VERSION 0.7", "FIELDS x y z", "SIZE 4 4 4", "TYPE F F F", "COUNT 1 1 1",
                 "WIDTH 4", "HEIGHT 1", "POINTS 4"):
        assert line + "\n" in head
    assert raw.endswith(b"\x00" * 48)


def test_pcd_write_2d_pads_z(tmp_path: Path) -> None:
    write_pcd(tmp_path / "a.pcd", np.array([[1.0, 2.0], [3.0, 4.0]]))
    np.testing.assert_array_equal(read_pcd(tmp_path / "a.pcd"), [[1, 2, 0], [3, 4, 0]])


def test_pcd_handwritten_ascii(tmp_path: Path) -> None:
    f = tmp_path / "hand.pcd"
    f.write_text(
        "# .PCD v.7 - Point Cloud Data file format\n"
        "VERSION .7\n"
        "FIELDS x y z rgb\n"
        "SIZE 4 4 4 4\n"
        "TYPE F F F F\n"
        "COUNT 1 1 1 1\n"
        "WIDTH 3\n"
        "HEIGHT 1\n"
        "VIEWPOINT 0 0 0 1 0 0 0\n"
        "POINTS 3\n"
        "DATA ascii\n"
        "0.93773 0.33763 0 4.2108e+06\n"
        "0.90805 0.35641 0 4.2108e+06\n"
        "\n"
        "-0.5 1.5e-3 2 4.2108e+06\n"
    )
    np.testing.assert_array_equal(
        read_pcd(f), np.array([[0.93773, 0.33763, 0], [0.90805, 0.35641, 0], [-0.5, 1.5e-3, 2]], np.float32)
    )


def test_pcd_ascii_count_gt1_and_field_order(tmp_path: Path) -> None:
    f = tmp_path / "o.pcd"
    f.write_text(
        "VERSION 0.7\nFIELDS desc y intensity x\nSIZE 4 4 2 8\nTYPE F F U F\nCOUNT 3 1 1 1\n"
        "WIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n"
        "9 9 9 1.5 7 -2\n"
        "9 9 9 2.5 7 -3\n"
    )
    np.testing.assert_array_equal(read_pcd(f), [[-2, 1.5, 0], [-3, 2.5, 0]])


def _binary_pcd(fields, sizes, types, counts, records: bytes, n: int, data="binary") -> bytes:
    head = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(fields)}\nSIZE {' '.join(map(str, sizes))}\n"
        f"TYPE {' '.join(types)}\nCOUNT {' '.join(map(str, counts))}\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
    )
    return head.encode() + records


def test_pcd_binary_extra_fields(tmp_path: Path) -> None:
    # x(F4) y(F4) z(F4) rgb(F4) intensity(U2) normal(F8 x3) label(I1) : packed, little-endian
    pts = _rand_pts(5)
    recs = b"".join(
        struct.pack("<ffff", *p, 1.5e-38) + struct.pack("<H", 7) + struct.pack("<3d", 0.1, 0.2, 0.3)
        + struct.pack("<b", -1)
        for p in pts.tolist()
    )
    f = tmp_path / "extra.pcd"
    f.write_bytes(_binary_pcd(["x", "y", "z", "rgb", "intensity", "normal", "label"],
                              [4, 4, 4, 4, 2, 8, 1], ["F", "F", "F", "F", "U", "F", "I"],
                              [1, 1, 1, 1, 1, 3, 1], recs, 5))
    assert read_pcd(f).tobytes() == pts.tobytes()


def test_pcd_open3d_style_f8_with_normals_and_rgb(tmp_path: Path) -> None:
    # Open3D (tensor API) may write double positions, then normals and packed rgb
    pts = RNG.standard_normal((4, 3))
    recs = b"".join(struct.pack("<3d3ff", *p, 0, 0, 1, 0.0) for p in pts.tolist())
    f = tmp_path / "o3d.pcd"
    f.write_bytes(_binary_pcd(["x", "y", "z", "normal_x", "normal_y", "normal_z", "rgb"],
                              [8, 8, 8, 4, 4, 4, 4], list("FFFFFFF"), [1] * 7, recs, 4))
    np.testing.assert_array_equal(read_pcd(f), pts.astype(np.float32))


def test_pcd_no_z_field(tmp_path: Path) -> None:
    f = tmp_path / "xy.pcd"
    f.write_bytes(_binary_pcd(["x", "y"], [4, 4], ["F", "F"], [1, 1], struct.pack("<4f", 1, 2, 3, 4), 2))
    np.testing.assert_array_equal(read_pcd(f), [[1, 2, 0], [3, 4, 0]])


@pytest.mark.parametrize(
    "content, msg",
    [
        (None, "not found"),
        (b"", "not a PCD"),
        (b"\x89PNG\r\n\x1a\n\x00\x00garbage", "not a PCD"),
        (b"hello world\nDATA binary\n", "not a PCD"),
        (_binary_pcd(["x", "y", "z"], [4, 4, 4], list("FFF"), [1] * 3, b"\x00" * 20, 2), "truncated"),
        (_binary_pcd(["a", "b", "z"], [4, 4, 4], list("FFF"), [1] * 3, b"\x00" * 24, 2), "no x/y"),
        (_binary_pcd(["x", "y", "z"], [4, 4, 4], list("FFF"), [1] * 3, b"\x00" * 24, 2,
                     data="binary_compressed"), "binary_compressed"),
        (_binary_pcd(["x", "y", "z"], [4, 4], list("FFF"), [1] * 3, b"\x00" * 24, 2), "lengths differ"),
        (_binary_pcd(["x", "y", "z"], [4, 4, 4], list("FFF"), [1] * 3, b"", 2, data="ascii")
         + b"1 2 3\n", "truncated"),
        (_binary_pcd(["x", "y", "z"], [4, 4, 4], list("FFF"), [1] * 3, b"", 1, data="ascii")
         + b"1 two 3\n", "non-numeric"),
        (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH n\nPOINTS n\nDATA ascii\n",
         "invalid"),
    ],
)
def test_pcd_bad_inputs(tmp_path: Path, content, msg: str) -> None:
    f = tmp_path / "bad_scan.pcd"
    if content is not None:
        f.write_bytes(content)
    with pytest.raises(InputError, match=msg) as ei:
        read_pcd(f)
    assert str(ei.value).startswith(str(f) + ":")
    assert "\n" not in str(ei.value)


# ---------------------------------------------------------------- PLY


@pytest.mark.parametrize("with_colors", [False, True])
def test_ply_round_trip(tmp_path: Path, with_colors: bool) -> None:
    pts = _rand_pts(30)
    cols = RNG.integers(0, 256, (30, 3)).astype(np.uint8) if with_colors else None
    write_ply(tmp_path / "a.ply", pts, cols)
    assert (tmp_path / "a.ply").read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    assert read_ply(tmp_path / "a.ply").tobytes() == pts.tobytes()


def test_ply_ascii_with_faces_and_extra_props(tmp_path: Path) -> None:
    f = tmp_path / "a.ply"
    f.write_text(
        "ply\nformat ascii 1.0\ncomment hi\n"
        "element vertex 3\nproperty uchar red\nproperty float x\nproperty float y\n"
        "property float z\nproperty double nx\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "255 1 2 3 0.5\n0 4 5 6 0.5\n10 -1 -2.5 0 0\n3 0 1 2\n"
    )
    np.testing.assert_array_equal(read_ply(f), [[1, 2, 3], [4, 5, 6], [-1, -2.5, 0]])


@pytest.mark.parametrize("endian", ["<", ">"])
def test_ply_binary_endianness_and_element_before_vertex(tmp_path: Path, endian: str) -> None:
    name = "binary_little_endian" if endian == "<" else "binary_big_endian"
    pts = RNG.standard_normal((3, 3))
    head = (
        f"ply\nformat {name} 1.0\nelement meta 2\nproperty list uchar int ids\nproperty short s\n"
        "element vertex 3\nproperty double x\nproperty double y\nproperty double z\nproperty int i\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    meta = struct.pack(endian + "B2ih", 2, 5, 6, 1) + struct.pack(endian + "Bh", 0, 2)
    verts = b"".join(struct.pack(endian + "3di", *p, 9) for p in pts.tolist())
    face = struct.pack(endian + "B3i", 3, 0, 1, 2)
    f = tmp_path / "b.ply"
    f.write_bytes(head + meta + verts + face)
    np.testing.assert_array_equal(read_ply(f), pts.astype(np.float32))


@pytest.mark.parametrize(
    "content, msg",
    [
        (None, "not found"),
        (b"not a ply\n", "not a PLY"),
        (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nend_header\n1 2\n",
         "truncated"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
         b"end_header\n" + b"\x00" * 12, "truncated"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\nproperty float b\nend_header\n1 2\n",
         "no x/y"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty flt x\nend_header\n1\n", "invalid PLY header"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 b\n",
         "invalid PLY ascii"),
    ],
)
def test_ply_bad_inputs(tmp_path: Path, content, msg: str) -> None:
    f = tmp_path / "bad_scan.ply"
    if content is not None:
        f.write_bytes(content)
    with pytest.raises(InputError, match=msg) as ei:
        read_ply(f)
    assert str(ei.value).startswith(str(f) + ":")


# ---------------------------------------------------------------- poses


def _rand_poses(k: int = 7) -> np.ndarray:
    p = RNG.standard_normal((k, 3)) * [123.456, 1e-7, 3.0]
    p[0] = [1 / 3, np.pi, -np.pi / 7]
    return p


def test_pose_text_round_trip_full_precision(tmp_path: Path) -> None:
    p = _rand_poses()
    write_pose_text(tmp_path / "p.txt", p)
    assert (tmp_path / "p.txt").read_text().startswith("#")
    out = read_pose_text(tmp_path / "p.txt")
    assert out.dtype == np.float64 and out.tobytes() == p.tobytes()


def test_pose_text_comments_blank_lines_commas(tmp_path: Path) -> None:
    f = tmp_path / "p.txt"
    f.write_text("# x y theta\n\n1 2 3  # trailing\n   \n4,5,6\n-1e-3 0 0.5\n")
    np.testing.assert_array_equal(read_pose_text(f), [[1, 2, 3], [4, 5, 6], [-1e-3, 0, 0.5]])


@pytest.mark.parametrize(
    "text, msg",
    [("1 2 3\n1 2\n", "line 2: expected 3 columns"), ("# c\n\n1 2 3 4\n", "line 3: expected 3 columns"),
     ("1 2 x\n", "line 1: non-numeric"), ("1 nan 3\n", "line 1: NaN"), ("# nothing\n", "no pose")],
)
def test_pose_text_bad(tmp_path: Path, text: str, msg: str) -> None:
    f = tmp_path / "poses_bad.txt"
    f.write_text(text)
    with pytest.raises(InputError, match=msg) as ei:
        read_pose_text(f)
    assert str(ei.value).startswith(str(f) + ":")


def test_pose_mat_and_npy_round_trip(tmp_path: Path) -> None:
    p = _rand_poses()
    write_gt_mat(tmp_path / "gt_pose.mat", p)
    assert read_gt_mat(tmp_path / "gt_pose.mat").tobytes() == p.tobytes()
    write_poses_npy(tmp_path / "p.npy", p)
    assert read_poses(tmp_path / "p.npy").tobytes() == p.tobytes()
    assert read_poses(tmp_path / "gt_pose.mat").tobytes() == p.tobytes()
    assert sorted(x.name for x in tmp_path.iterdir()) == ["gt_pose.mat", "p.npy"]


def test_pose_mat_bad(tmp_path: Path) -> None:
    from scipy.io import savemat

    f = tmp_path / "gt_pose.mat"
    with pytest.raises(InputError, match="not found"):
        read_gt_mat(f)
    savemat(f, {"poses": np.zeros((3, 3))})
    with pytest.raises(InputError, match="no variable 'pose'.*poses"):
        read_gt_mat(f)
    savemat(f, {"pose": np.zeros((3, 4))})
    with pytest.raises(InputError, match="K x 3"):
        read_gt_mat(f)
    f.write_bytes(b"MATLAB 5.0 MAT-file garbage" + b"\x00" * 50)
    with pytest.raises(InputError, match="gt_pose.mat: ") as ei:
        read_gt_mat(f)
    assert "\n" not in str(ei.value)


# ---------------------------------------------------------------- loaders


def _authors_folder(root: Path, k: int = 3, n: int = 16, names=None) -> tuple[np.ndarray, np.ndarray]:
    root.mkdir(parents=True, exist_ok=True)
    pts = RNG.uniform(-1, 1, (k, n, 2)).astype(np.float32)
    pts[1, 3] = 0.0  # beam without return
    pts[2, :5] = 0.0
    names = names or [f"{i:03d}.pcd" for i in range(k)]
    for name, p in zip(names, pts):
        write_pcd(root / name, np.concatenate([p, np.zeros((n, 1), np.float32)], 1))
    gt = np.column_stack([RNG.uniform(0, 512, k), RNG.uniform(0, 512, k), RNG.uniform(-3, 3, k)])
    write_gt_mat(root / "gt_pose.mat", gt)
    return pts, gt


def test_authors_round_trip(tmp_path: Path) -> None:
    pts, gt = _authors_folder(tmp_path / "run")
    assert detect_format(tmp_path / "run") == "authors"
    s = load_scans(tmp_path / "run")
    assert s.points.dtype == np.float32 and s.points.shape == (3, 16, 2)
    np.testing.assert_array_equal(s.points, pts)
    np.testing.assert_array_equal(s.gt_poses[:, :2], gt[:, :2] / 512)
    np.testing.assert_array_equal(s.gt_poses[:, 2], gt[:, 2])
    assert s.valid[0].all() and not s.valid[1, 3] and s.valid[1].sum() == 15 and s.valid[2].sum() == 11
    assert s.unit_scale == 512 and s.unit == "px" and s.ordered
    assert s.names == ["000.pcd", "001.pcd", "002.pcd"] and s.source == str(tmp_path / "run")
    assert s.init_poses is None


def test_authors_numeric_order_and_init(tmp_path: Path) -> None:
    names = ["2.pcd", "10.pcd", "1000.pcd", "999.pcd"]
    pts, gt = _authors_folder(tmp_path, k=4, names=names)
    init = RNG.standard_normal((4, 3))
    write_pose_text(tmp_path / "init.txt", init)
    s = load_scans(tmp_path, init_path=tmp_path / "init.txt")
    assert s.names == ["2.pcd", "10.pcd", "999.pcd", "1000.pcd"]
    np.testing.assert_array_equal(s.points[2], pts[3])
    np.testing.assert_array_equal(s.init_poses, init)  # same units as points: no /512
    assert sorted(["b10", "b2", "a"], key=natural_key) == ["a", "b2", "b10"]


def test_folder_format_npy_with_gt_txt(tmp_path: Path) -> None:
    pts = RNG.uniform(-5, 5, (3, 8, 2))
    for i, p in enumerate(pts):
        np.save(tmp_path / f"scan_{i}.npy", p)
    gt = _rand_poses(3)
    write_pose_text(tmp_path / "gt_pose.txt", gt)
    write_poses_npy(tmp_path / "init_poses.npy", gt * 0)  # never read as a scan
    assert detect_format(tmp_path) == "folder"
    s = load_scans(tmp_path, init_path=tmp_path / "init_poses.npy")
    assert s.unit == "m" and s.unit_scale == 1 and s.num_scans == 3
    np.testing.assert_array_equal(s.points, pts.astype(np.float32))
    np.testing.assert_array_equal(s.gt_poses, gt)
    np.testing.assert_array_equal(s.init_poses, np.zeros((3, 3)))


def test_folder_format_mixed_pcd_ply_and_explicit_gt(tmp_path: Path) -> None:
    pts = RNG.uniform(-5, 5, (2, 6, 3)).astype(np.float32)
    pts[:, :, 2] = 0
    write_pcd(tmp_path / "a0.pcd", pts[0])
    write_ply(tmp_path / "a1.ply", pts[1])
    gt = _rand_poses(2)
    write_gt_mat(tmp_path / "elsewhere.mat", gt)
    s = load_scans(tmp_path, gt_path=tmp_path / "elsewhere.mat")
    np.testing.assert_array_equal(s.points, pts[:, :, :2])
    np.testing.assert_array_equal(s.gt_poses, gt)  # folder format: no /512
    s2 = load_scans(tmp_path, fmt="folder")
    assert s2.gt_poses is None


def test_registry_and_unknown_format(tmp_path: Path) -> None:
    _authors_folder(tmp_path)
    assert {"authors", "folder"} <= set(LOADERS)
    with pytest.raises(ConfigError, match="unknown scan format 'e57'"):
        load_scans(tmp_path, fmt="e57")
    calls = []
    register_loader("dummy", lambda p, g, i: calls.append(p) or "ok", lambda p: (p / "DUMMY").exists())
    try:
        (tmp_path / "DUMMY").touch()
        assert detect_format(tmp_path) == "dummy" and load_scans(tmp_path) == "ok"
    finally:
        from deepmapping.io import loaders

        loaders.LOADERS.pop("dummy")
        loaders.DETECTORS[:] = [d for d in loaders.DETECTORS if d[0] != "dummy"]


def _npy(folder: Path, name: str, arr) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / name, np.asarray(arr))
    return folder / name


def test_loader_missing_not_folder_empty(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such file") as ei:
        load_scans(tmp_path / "nope")
    assert "nope" in str(ei.value)
    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(InputError, match="not a folder") as ei:
        load_scans(tmp_path / "file.txt")
    assert "file.txt" in str(ei.value)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no scan files") as ei:
        load_scans(tmp_path / "empty")
    assert str(ei.value).startswith(str(tmp_path / "empty"))


def test_loader_one_scan(tmp_path: Path) -> None:
    _npy(tmp_path, "000.npy", np.ones((4, 2)))
    with pytest.raises(InputError, match="at least two scans") as ei:
        load_scans(tmp_path)
    assert "000.npy" in str(ei.value)


def test_loader_corrupt_files(tmp_path: Path) -> None:
    _npy(tmp_path, "000.npy", np.ones((4, 2)))
    (tmp_path / "001.npy").write_bytes(b"garbage")
    with pytest.raises(InputError, match="001.npy: cannot read"):
        load_scans(tmp_path)
    (tmp_path / "001.npy").unlink()
    write_pcd(tmp_path / "001.pcd", np.ones((4, 3)) * [1, 1, 0])
    (tmp_path / "001.pcd").write_bytes((tmp_path / "001.pcd").read_bytes()[:-5])
    with pytest.raises(InputError, match="001.pcd: truncated"):
        load_scans(tmp_path)
    (tmp_path / "001.pcd").unlink()
    _npy(tmp_path, "001.npy", np.ones((4, 2, 1)))
    with pytest.raises(InputError, match=r"001.npy: scan must be an \(N, 2\)"):
        load_scans(tmp_path)


def test_loader_no_valid_point(tmp_path: Path) -> None:
    _npy(tmp_path, "000.npy", np.ones((4, 2)))
    _npy(tmp_path, "001.npy", np.zeros((4, 2)))
    with pytest.raises(InputError, match="001.npy: scan has no valid point"):
        load_scans(tmp_path)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_loader_nonfinite(tmp_path: Path, bad: float) -> None:
    _npy(tmp_path, "000.npy", np.ones((4, 2)))
    a = np.ones((4, 2))
    a[2, 1] = bad
    _npy(tmp_path, "001.npy", a)
    with pytest.raises(InputError, match="001.npy: contains NaN or inf"):
        load_scans(tmp_path)


def test_loader_different_dimension_and_nonzero_z(tmp_path: Path) -> None:
    _npy(tmp_path, "000.npy", np.ones((4, 2)))
    _npy(tmp_path, "001.npy", np.ones((4, 3)) * [1, 1, 0])
    with pytest.raises(InputError, match="001.npy: scans of different dimension"):
        load_scans(tmp_path)
    _npy(tmp_path, "000.npy", np.ones((4, 3)))  # non-zero z: a folder of 3D clouds
    scans = load_scans(tmp_path)
    assert scans.is_3d and scans.pose_dof == 6 and scans.points.shape == (2, 4, 3) and scans.gt_poses is None


def test_folder_of_3d_clouds_with_xyz_and_poses(tmp_path: Path) -> None:
    from deepmapping.geometry import se3
    from deepmapping.io.poses3d import write_tum_poses

    (tmp_path / "a.xyz").write_text("# x y z r\n1 2 3 9\n4 5 6 9\n\n7,8,9\n")
    write_pcd(tmp_path / "b.pcd", np.array([[1.0, 0.0, 2.0], [0.0, 1.0, 3.0]]))
    poses = np.stack([np.eye(4), se3.from_rt(np.eye(3), [1.0, 0.0, 0.0])])
    write_tum_poses(tmp_path / "poses.txt", poses)
    scans = load_scans(tmp_path)
    np.testing.assert_array_equal(scans.points[0], [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    assert scans.valid.sum(1).tolist() == [3, 2] and scans.names == ["a.xyz", "b.pcd"]
    np.testing.assert_allclose(scans.gt_poses, poses)
    (tmp_path / "a.xyz").write_text("1 2 3\n4 5\n")
    with pytest.raises(InputError, match="a.xyz: line 2: expected 'x y z'"):
        load_scans(tmp_path)


def test_authors_nonzero_z(tmp_path: Path) -> None:
    _authors_folder(tmp_path)
    write_pcd(tmp_path / "001.pcd", np.ones((16, 3)))
    with pytest.raises(InputError, match="001.pcd: 3D scans are not supported in this layout"):
        load_scans(tmp_path)


def test_loader_different_sizes(tmp_path: Path) -> None:
    _npy(tmp_path, "000.npy", np.ones((256, 2)))
    _npy(tmp_path, "001.npy", np.ones((256, 2)))
    _npy(tmp_path, "003.npy", np.ones((200, 2)))
    with pytest.raises(InputError) as ei:
        load_scans(tmp_path)
    assert str(ei.value).endswith(
        "scans of different sizes are not supported for organized 2D scans: "
        "003.npy has 200 points, 000.npy has 256"
    )
    assert str(ei.value).startswith(str(tmp_path / "003.npy"))


def test_loader_pose_count_mismatch(tmp_path: Path) -> None:
    _authors_folder(tmp_path)
    write_gt_mat(tmp_path / "gt_pose.mat", np.zeros((2, 3)))
    with pytest.raises(InputError, match="gt_pose.mat: 2 ground-truth poses for 3 scans"):
        load_scans(tmp_path)
    _authors_folder(tmp_path)
    write_pose_text(tmp_path / "init.txt", np.zeros((4, 3)))
    with pytest.raises(InputError, match="init.txt: 4 initial poses for 3 scans"):
        load_scans(tmp_path, init_path=tmp_path / "init.txt")
    with pytest.raises(InputError, match="missing.txt: file not found"):
        load_scans(tmp_path, init_path=tmp_path / "missing.txt")


def test_folder_gt_text_bad_line_named(tmp_path: Path) -> None:
    _npy(tmp_path, "000.npy", np.ones((4, 2)))
    _npy(tmp_path, "001.npy", np.ones((4, 2)))
    (tmp_path / "poses.txt").write_text("0 0 0\n1 1\n")
    with pytest.raises(InputError, match="poses.txt: line 2: expected 3 columns"):
        load_scans(tmp_path)
