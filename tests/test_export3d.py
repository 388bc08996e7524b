"""3D outputs: M-Net occupancy grid, marching-cubes mesh, registered cloud, pictures."""

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from deepmapping.geometry import se3
from deepmapping.output.export3d import (
    occupancy_grid,
    occupancy_mesh,
    read_occupancy_grid,
    registered_cloud,
    scan_colors,
    write_mesh_ply,
    write_occupancy_grid,
    write_registered_cloud,
)
from deepmapping.output.plots3d import plot_cloud_3d, plot_trajectories_3d, view_basis

CENTRE, RADIUS = np.array([0.1, -0.2, 0.3]), 0.7


def sphere(xyz):
    """Occupancy of a solid ball: 1 inside, 0 outside, 0.5 on the sphere."""
    return 1.0 / (1.0 + np.exp((np.linalg.norm(xyz - CENTRE, axis=1) - RADIUS) / 0.02))


def test_sphere_grid_and_mesh(tmp_path):
    calls = []

    def fn(xyz):
        calls.append(len(xyz))
        return sphere(xyz)

    grid, origin, voxel = occupancy_grid(fn, CENTRE - 1.0, CENTRE + 1.0, 0.05, chunk=5000)
    assert grid.shape == (40, 40, 40) and grid.dtype == np.float32 and voxel == 0.05
    assert max(calls) <= 5000 and sum(calls) == grid.size
    ijk = np.array([[0, 0, 0], [20, 13, 7], [39, 39, 39]])
    np.testing.assert_allclose(grid[tuple(ijk.T)], sphere(origin + voxel * ijk), atol=1e-6)
    verts, tris = occupancy_mesh(grid, origin, voxel)
    assert len(verts) > 1000 and tris.shape[1] == 3
    r = np.linalg.norm(verts - CENTRE, axis=1)
    assert np.abs(r - RADIUS).max() < voxel
    # faces wind so that normals point out of the ball (to lower occupancy)
    a, b, c = (verts[tris[:, i]] for i in range(3))
    n = np.cross(b - a, c - a)
    assert (np.einsum("ij,ij->i", n, (a + b + c) / 3 - CENTRE) > 0).mean() > 0.99
    write_occupancy_grid(tmp_path / "occ.npz", grid, origin, voxel)
    g2, o2, v2 = read_occupancy_grid(tmp_path / "occ.npz")
    assert np.array_equal(g2, grid) and np.array_equal(o2, origin) and v2 == voxel


def test_mesh_empty_when_level_not_crossed():
    grid = np.zeros((8, 8, 8), np.float32)
    for g, level in ((grid, 0.5), (grid + 0.9, 0.5), (grid + 0.2, 0.2)):
        v, t = occupancy_mesh(g, np.zeros(3), 0.1, level)
        assert v.shape == (0, 3) and t.shape == (0, 3)
    with pytest.raises(ValueError, match="too large"):
        occupancy_grid(sphere, [0, 0, 0], [10, 10, 10], 0.01)


def test_mesh_ply_open3d(tmp_path):
    import open3d as o3d

    grid, origin, voxel = occupancy_grid(sphere, CENTRE - 1.0, CENTRE + 1.0, 0.1)
    verts, tris = occupancy_mesh(grid, origin, voxel)
    write_mesh_ply(tmp_path / "mesh.ply", verts, tris)
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "mesh.ply"))
    assert len(mesh.vertices) == len(verts) and len(mesh.triangles) == len(tris)
    np.testing.assert_allclose(np.asarray(mesh.vertices), verts, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(mesh.triangles), tris)
    with pytest.raises(ValueError):
        write_mesh_ply(tmp_path / "bad.ply", verts[:3], [[0, 1, 3]])


def scans3d(k=4, n=50, seed=0):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(k, n, 3))
    valid = rng.random((k, n)) > 0.2
    poses = se3.from_rt(Rotation.random(k, random_state=seed).as_matrix(), rng.normal(size=(k, 3)))
    return pts, valid, poses


def test_registered_cloud_coloured_by_scan(tmp_path):
    import open3d as o3d

    pts, valid, poses = scans3d()
    cloud, index = registered_cloud(pts, valid, poses)
    assert len(cloud) == valid.sum() and np.array_equal(np.bincount(index), valid.sum(1))
    k, j = np.argwhere(valid)[7]
    np.testing.assert_allclose(cloud[7], poses[k, :3, :3] @ pts[k, j] + poses[k, :3, 3])
    write_registered_cloud(tmp_path / "cloud.ply", pts, valid, poses)
    pc = o3d.io.read_point_cloud(str(tmp_path / "cloud.ply"))
    np.testing.assert_allclose(np.asarray(pc.points), cloud, atol=1e-5)
    rgb = np.round(np.asarray(pc.colors) * 255).astype(int)
    for s in range(len(pts)):
        assert (rgb[index == s] == scan_colors(len(pts))[s]).all()
    assert len({tuple(c) for c in scan_colors(10)}) == 10  # distinct per scan


def test_view_basis():
    for up in ("x", "y", "z", "-x", "-y", "-z"):
        V, labels = view_basis(up)
        assert np.linalg.det(V) == pytest.approx(1.0) and labels[2] == up
    V, labels = view_basis("-y")  # y down: the top view is x (right) and z (up the page)
    assert labels == ["x", "z", "-y"]
    with pytest.raises(ValueError):
        view_basis("w")


def check_png(path):
    assert path.exists() and path.stat().st_size > 5000
    with Image.open(path) as im:
        assert min(im.size) > 300 and np.asarray(im.convert("L")).std() > 5  # not blank


def test_plots(tmp_path):
    pts, valid, poses = scans3d(k=6, n=300)
    gt = se3.from_rt(np.eye(3), [1, 2, 3]) @ poses
    plot_cloud_3d(tmp_path / "cloud.png", pts, valid, poses, gt_poses=gt, title="t", unit_scale=100, unit="cm")
    check_png(tmp_path / "cloud.png")
    plot_cloud_3d(tmp_path / "bare.png", pts, valid, poses, up_axis="z", show_trajectory=False, max_points=100)
    check_png(tmp_path / "bare.png")
    plot_trajectories_3d(tmp_path / "traj.png", {"a": poses, "b": gt}, gt=gt)
    check_png(tmp_path / "traj.png")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bare.png", "cloud.png", "traj.png"]
