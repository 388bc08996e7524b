import math

import numpy as np
import pytest
from PIL import Image

from deepmapping.output import plots

HALF = 10.0  # square room [-10, 10]^2


def room_scans(k=8, beams=90, max_range=15.0, seed=0):
    """k scans of the square room taken from poses inside it (sensor frames)."""
    rng = np.random.default_rng(seed)
    ang = np.linspace(0, 2 * np.pi * k / (k + 1), k)
    poses = np.stack([4 * np.cos(ang), 4 * np.sin(ang), rng.uniform(-np.pi, np.pi, k)], axis=1)
    phi = 2 * np.pi * np.arange(beams) / beams
    pts = np.zeros((k, beams, 2))
    valid = np.zeros((k, beams), bool)
    for i, (x, y, th) in enumerate(poses):
        d = np.stack([np.cos(th + phi), np.sin(th + phi)], axis=1)
        with np.errstate(divide="ignore"):
            tx = np.where(d[:, 0] > 0, (HALF - x) / d[:, 0], (-HALF - x) / d[:, 0])
            ty = np.where(d[:, 1] > 0, (HALF - y) / d[:, 1], (-HALF - y) / d[:, 1])
        r = np.minimum(np.abs(tx), np.abs(ty))
        ok = r <= max_range
        pts[i, ok, 0] = r[ok] * np.cos(phi[ok])
        pts[i, ok, 1] = r[ok] * np.sin(phi[ok])
        valid[i] = ok
    return pts.astype(np.float32), valid, poses


def png_size(path):
    with Image.open(path) as im:
        im.load()
        return im.size


def check_png(path, tmp_path, min_side=500, max_side=2500):
    assert path.exists() and path.stat().st_size > 1000
    w, h = png_size(path)
    assert min_side <= max(w, h) <= max_side and min(w, h) >= 300
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temp/other files


def test_register_points_matches_convention():
    pts = np.array([[[1.0, 0.0], [0.0, 2.0]]])
    g = plots.register_points(pts, np.array([[1.0, -1.0, np.pi / 2]]))
    np.testing.assert_allclose(g, [[[1.0, 0.0], [-1.0, -1.0]]], atol=1e-12)


def test_plot_map(tmp_path):
    pts, valid, poses = room_scans()
    gt = poses + np.array([0.1, -0.1, 0.0])
    out = tmp_path / "map.png"
    plots.plot_map(out, pts, valid, poses, gt_poses=gt, title="room", unit="m", unit_scale=0.5)
    check_png(out, tmp_path)
    plots.plot_map(out, pts, valid, poses, invert_y=True)  # overwrite, no gt
    check_png(out, tmp_path)


def disc_fn(xy):
    return (np.hypot(xy[:, 0] - 3.0, xy[:, 1] - 3.0) < 2.0).astype(float)


def test_occupancy_image_disc_free_unexplored():
    pts, valid, poses = room_scans()
    calls = []

    def fn(xy):
        calls.append(len(xy))
        return disc_fn(xy)

    img, (x0, x1, y0, y1) = plots.occupancy_image(fn, pts, valid, poses)
    h, w = img.shape
    assert max(h, w) == 512
    assert x0 < -HALF and x1 > HALF and y0 < -HALF and y1 > HALF
    res = (x1 - x0) / w
    assert math.isclose(res, (y1 - y0) / h)
    assert max(calls) <= 65536

    def at(x, y):
        return img[int((y - y0) / res), int((x - x0) / res)]

    assert at(3.0, 3.0) == 1.0  # occupied disc
    assert at(-5.0, -5.0) == 0.0  # free, explored
    assert at(0.0, -7.0) == 0.0
    assert np.isnan(img[0, 0]) and np.isnan(img[-1, -1])  # grid corners: outside the room
    inside = img[int((-9 - y0) / res):int((9 - y0) / res), int((-9 - x0) / res):int((9 - x0) / res)]
    assert np.isfinite(inside).all()  # whole room interior seen
    assert set(np.unique(img[np.isfinite(img)])) <= {0.0, 1.0}


def test_explored_mask_single_beam():
    g = np.array([[[5.0, 0.25]]])
    m = plots.explored_mask(g, np.array([[True]]), np.array([[0.0, 0.25]]),
                            x0=-1.0, y0=-3.0, res=0.5, nx=16, ny=12)
    row = int((0.25 + 3.0) / 0.5)
    for x in np.arange(0.0, 5.0, 0.5):
        assert m[row, int((x + 1.0) / 0.5)]
    assert m[row + 1, int((5.0 + 1.0) / 0.5)]  # neighbour of the hit
    assert not m[row + 3, 2] and not m[0, 0]
    assert m.sum() < 40


def test_occupancy_image_resolution_and_bad_fn():
    pts, valid, poses = room_scans()
    img, ext = plots.occupancy_image(disc_fn, pts, valid, poses, resolution=0.5)
    assert abs((ext[1] - ext[0]) / img.shape[1] - 0.5) < 1e-9
    with pytest.raises(ValueError):
        plots.occupancy_image(lambda xy: np.zeros(3), pts, valid, poses)


def test_plot_occupancy(tmp_path):
    pts, valid, poses = room_scans()
    out = tmp_path / "occ.png"
    plots.plot_occupancy(out, disc_fn, pts, valid, poses, unit="m", unit_scale=0.1, title="occ")
    check_png(out, tmp_path)
    with Image.open(out) as im:
        a = np.asarray(im.convert("L"))
    assert (a < 30).any() and (a > 225).any()
    assert ((a > 110) & (a < 145)).sum() > 1000  # grey unexplored margin
    plots.plot_occupancy(out, disc_fn, pts, valid, poses, resolution=0.25, invert_y=True)
    check_png(out, tmp_path)


@pytest.mark.parametrize("with_ate", [True, False])
def test_plot_curves(tmp_path, with_ate):
    n = 50
    hist = {"iteration": list(range(0, 10 * n, 10)), "time_s": list(np.linspace(0, 30, n)),
            "loss": list(1.0 / (1 + np.arange(n)))}
    if with_ate:
        hist["ate"] = [float(20 / (1 + i)) if i % 5 == 0 else None for i in range(n)]
        hist["ate"][10] = float("nan")
        hist["unit"] = "px"
    out = tmp_path / "curves.png"
    plots.plot_curves(out, hist)
    check_png(out, tmp_path)
    w, h = png_size(out)
    assert (h > 0.6 * w) == with_ate  # 2x2 vs 1x2 layout


def test_plot_trajectories(tmp_path):
    _, _, poses = room_scans()
    out = tmp_path / "traj.png"
    plots.plot_trajectories(out, {"icp": poses + 0.5, "deepmapping": poses + 0.1}, gt=poses,
                            unit="m", unit_scale=2.0, title="trajectories", invert_y=True)
    check_png(out, tmp_path)


def test_plot_environment(tmp_path):
    occ = np.full((120, 200), 255, np.uint8)
    occ[:5], occ[-5:], occ[:, :5], occ[:, -5:] = 0, 0, 0, 0
    occ[40:60, 80:120] = 0
    t = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    poses = np.stack([100 + 70 * np.cos(t), 60 + 40 * np.sin(t), t + np.pi / 2], axis=1)
    out = tmp_path / "env.png"
    plots.plot_environment(out, occ, poses)
    check_png(out, tmp_path)
    plots.plot_environment(out, occ, None)
    check_png(out, tmp_path)


def test_explored_mask_fan_fill_respects_occlusion():
    # one scan at the origin: a near wall (range 2) for beam angles in [0, pi/2], range 8 elsewhere
    b = 180
    phi = 2 * np.pi * np.arange(b) / b
    r = np.where(phi <= np.pi / 2, 2.0, 8.0)
    g = np.stack([r * np.cos(phi), r * np.sin(phi)], axis=1)[None]
    valid = np.ones((1, b), bool)
    res, n = 0.1, 200
    m = plots.explored_mask(g, valid, np.zeros((1, 2)), x0=-10.0, y0=-10.0, res=res, nx=n, ny=n)

    def at(x, y):
        return m[int((y + 10) / res), int((x + 10) / res)]

    c = 5 / math.sqrt(2)
    assert at(1.0, 1.0) and at(-c, c) and at(-c, -c) and at(c, -c)  # seen, incl. between beams
    assert not at(c, c) and not at(4.0, 1.0)  # behind the near wall
    assert not at(9.5, 9.5) and not at(-9.5, 0.0)  # beyond the far wall
    m_lines = plots.explored_mask(g, valid, np.zeros((1, 2)), -10.0, -10.0, res, n, n, fill=False)
    assert (m_lines <= m).all() and m.sum() > 1.3 * m_lines.sum()
