"""3D pose files: KITTI / TUM / .npy round trips, format detection and one-line errors."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deepmapping.errors import InputError
from deepmapping.geometry import se3
from deepmapping.io.poses3d import (
    read_kitti_poses,
    read_poses_3d,
    read_tum_poses,
    write_kitti_poses,
    write_poses_3d,
    write_tum_poses,
)


def _poses(k=5, seed=0):
    rng = np.random.default_rng(seed)
    return se3.from_rt(Rotation.random(k, random_state=seed).as_matrix(), rng.normal(0, 3, (k, 3)))


@pytest.mark.parametrize("name, fmt", [("p.txt", "kitti"), ("p.kitti", "kitti"), ("p.txt", "tum"),
                                       ("p.tum", None), ("p.npy", None)])
def test_round_trip(tmp_path, name, fmt):
    poses = _poses()
    path = tmp_path / name
    write_poses_3d(path, poses, fmt)
    back = read_poses_3d(path)
    assert back.shape == (5, 4, 4) and back.dtype == np.float64
    np.testing.assert_allclose(back, poses, atol=1e-12)
    assert [p.name for p in tmp_path.iterdir()] == [name]  # atomic: no temp file left


def test_kitti_text_layout(tmp_path):
    poses = _poses(2)
    write_kitti_poses(tmp_path / "k.txt", poses)
    rows = [list(map(float, ln.split())) for ln in (tmp_path / "k.txt").read_text().splitlines()]
    assert len(rows) == 2 and all(len(r) == 12 for r in rows)
    np.testing.assert_allclose(np.reshape(rows[1], (3, 4)), poses[1, :3, :])


def test_tum_index_timestamps_and_comments(tmp_path):
    write_tum_poses(tmp_path / "t.txt", _poses(3))
    lines = (tmp_path / "t.txt").read_text().splitlines()
    assert lines[0].startswith("#") and [float(ln.split()[0]) for ln in lines[1:]] == [0.0, 1.0, 2.0]
    (tmp_path / "u.txt").write_text("# comment\n\n1.5 1 2 3 0 0 0 2\n")  # unnormalized quaternion
    got = read_tum_poses(tmp_path / "u.txt")
    np.testing.assert_allclose(got[0], se3.from_rt(np.eye(3), [1, 2, 3]))


def _err(path, reader=read_poses_3d) -> str:
    with pytest.raises(InputError) as e:
        reader(path)
    msg = str(e.value)
    assert "\n" not in msg and str(path) in msg
    return msg


def test_errors(tmp_path):
    assert "not found" in _err(tmp_path / "missing.txt")
    good = " ".join(["1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", "0"])
    p = tmp_path / "cols.txt"
    p.write_text(f"{good}\n{good}\n1 0 0 0 0 1 0 0 0 0 1\n")
    assert "line 3" in _err(p) and "12 columns" in _err(p)
    p.write_text(f"{good}\n{good.replace('1', 'nan', 1)}\n")
    assert "line 2" in _err(p) and "NaN" in _err(p)
    p.write_text("2 0 0 0 0 2 0 0 0 0 2 0\n")
    assert "not a rotation" in _err(p)
    p.write_text("1 2 3 4 5\n")
    assert "12 columns" in _err(p) and "8" in _err(p)
    p.write_text("# only a comment\n")
    assert "no pose" in _err(p)
    p.write_text("0 1 2 3 0 0 0 0\n")
    assert "zero quaternion" in _err(p)
    p.write_text("1 0 0 0 0 1 0 0 0 0 1 zero\n")
    assert "non-numeric" in _err(p, read_kitti_poses)


def test_npy_errors(tmp_path):
    p = tmp_path / "p.npy"
    np.save(p, np.zeros((3, 4)))
    assert "K x 4 x 4" in _err(p)
    bad = _poses(2)
    bad[1, :3, :3] *= -1  # det = -1: a reflection
    np.save(p, bad)
    assert "not a rotation" in _err(p) and "pose 1" in _err(p)
    bad = _poses(2)
    bad[0, 0, 3] = np.inf
    np.save(p, bad)
    assert "NaN or inf" in _err(p)
    p.write_bytes(b"garbage")
    assert "cannot read" in _err(p)
