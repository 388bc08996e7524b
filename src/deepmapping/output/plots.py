"""Pictures: registered maps, M-Net occupancy maps, training curves, trajectories, environments.

Every function writes one PNG atomically (``path + ".tmp.png"`` then ``os.replace``) and
creates no other file. matplotlib is imported inside the functions; figures are built with
``matplotlib.figure.Figure`` and rendered by the Agg canvas, so no window is ever opened and
the caller's pyplot state/backend is left untouched.

Poses follow ``docs/conventions.md``: ``[x, y, theta]``, global = ``R(theta) @ p + [x, y]``.
Coordinates are drawn in display units: ``coordinate * unit_scale`` labelled ``unit``.
``invert_y=True`` draws y growing downwards, to match the simulator's image frame.
"""

from __future__ import annotations

import math
import os

import numpy as np

from deepmapping.io.atomic import atomic_write, make_folder

__all__ = [
    "register_points",
    "explored_mask",
    "occupancy_image",
    "plot_map",
    "plot_occupancy",
    "plot_curves",
    "plot_trajectories",
    "plot_environment",
]

DPI = 150
_GREY = (0.5, 0.5, 0.5)


# --------------------------------------------------------------------------- helpers


def _as_poses(poses, name="poses") -> np.ndarray:
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim == 1 and p.shape == (3,):
        p = p[None]
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (K, 3), got {np.shape(poses)}")
    return p


def _as_scans(points, valid, poses):
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 3 or pts.shape[2] != 2:
        raise ValueError(f"points: expected shape (K, N, 2), got {pts.shape}")
    if valid is None:
        val = np.all(np.isfinite(pts), axis=2)
    else:
        val = np.asarray(valid, dtype=bool)
        if val.shape != pts.shape[:2]:
            raise ValueError(f"valid: expected shape {pts.shape[:2]}, got {val.shape}")
        val = val & np.all(np.isfinite(pts), axis=2)
    ps = _as_poses(poses)
    if ps.shape[0] != pts.shape[0]:
        raise ValueError(f"poses: {ps.shape[0]} poses for {pts.shape[0]} scans")
    return pts, val, ps


def register_points(points, poses) -> np.ndarray:
    """Sensor-frame points (K, N, 2) -> global frame (K, N, 2) with poses (K, 3)."""
    pts = np.asarray(points, dtype=np.float64)
    ps = _as_poses(poses)
    c, s = np.cos(ps[:, 2])[:, None], np.sin(ps[:, 2])[:, None]
    x, y = pts[..., 0], pts[..., 1]
    gx = c * x - s * y + ps[:, 0:1]
    gy = s * x + c * y + ps[:, 1:2]
    return np.stack([gx, gy], axis=-1)


def new_figure(figsize):
    from matplotlib.figure import Figure  # no pyplot: rendered by the Agg canvas in save_figure

    return Figure(figsize=figsize, dpi=DPI, layout="constrained")


def save_figure(fig, path) -> None:
    """Render ``fig`` with Agg to ``path`` atomically (rendered in memory, then io.atomic)."""
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    make_folder(os.path.dirname(os.path.abspath(os.fspath(path))))
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, facecolor="white")
    atomic_write(path, lambda f: f.write(buf.getvalue()))


def unit_label(unit: str) -> str:
    return f" [{unit}]" if unit else ""


def _marker_size(n: int) -> float:
    # area in pt^2: ~4 for a few thousand points, down to ~0.3 for a million
    return float(np.clip(3.0e4 / max(n, 1), 0.4, 6.0))


def _draw_traj(ax, xy, *, color, label, ls="-", lw=1.2, start=True, zorder=3):
    if len(xy) == 0:
        return
    ax.plot(xy[:, 0], xy[:, 1], ls=ls, color=color, lw=lw, label=label, zorder=zorder)
    if start:
        ax.plot(xy[0, 0], xy[0, 1], marker="o", ms=6, mfc=color, mec="white", mew=1.0,
                ls="none", zorder=zorder + 1)


def legend_below(ax):
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.figure.legend(handles, labels, loc="outside lower center",
                         ncol=min(len(handles), 4), fontsize=8, frameon=False)


# --------------------------------------------------------------------------- plot_map


def plot_map(path, points, valid, poses, gt_poses=None, title="", unit="px", unit_scale=1.0,
             invert_y=False):
    """Registered point clouds coloured per scan, estimated trajectory (black) and,
    if given, the ground-truth trajectory (already aligned by the caller, dashed red)."""
    pts, val, ps = _as_scans(points, valid, poses)
    k = pts.shape[0]
    g = register_points(pts, ps) * unit_scale
    scan_idx = np.broadcast_to(np.arange(k)[:, None], val.shape)[val]
    gv = g[val]
    traj = ps[:, :2] * unit_scale

    fig = new_figure((7.0, 6.2))
    ax = fig.add_subplot(1, 1, 1)
    sc = ax.scatter(gv[:, 0], gv[:, 1], c=scan_idx, cmap="viridis", vmin=0, vmax=max(k - 1, 1),
                    s=_marker_size(len(gv)), marker="o", linewidths=0, rasterized=True, zorder=1)
    if gt_poses is not None:
        gt = _as_poses(gt_poses, "gt_poses")[:, :2] * unit_scale
        _draw_traj(ax, gt, color="tab:red", label="ground truth", ls="--", lw=1.2, zorder=3)
    _draw_traj(ax, traj, color="black", label="estimated trajectory", lw=1.4, zorder=5)
    ax.plot([], [], marker="o", ms=6, mfc="black", mec="white", ls="none", label="start")
    cb = fig.colorbar(sc, ax=ax, shrink=0.85, pad=0.02)
    cb.set_label("scan index")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x" + unit_label(unit))
    ax.set_ylabel("y" + unit_label(unit))
    if invert_y:
        ax.invert_yaxis()
    ax.set_title(title or f"Registered point clouds ({k} scans)")
    ax.grid(True, lw=0.3, alpha=0.5)
    legend_below(ax)
    save_figure(fig, path)


# --------------------------------------------------------------------------- occupancy


def _grid(points_g, val, ps, resolution):
    """Grid covering registered valid points and sensor positions (+5 % margin)."""
    xy = np.concatenate([points_g[val], ps[:, :2]], axis=0)
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if len(xy) == 0:
        raise ValueError("no valid points to build an occupancy grid")
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    span = hi - lo
    size = float(span.max())
    if size <= 0:
        size = 1.0
    margin = 0.05 * np.maximum(span, 0.05 * size)
    lo, hi = lo - margin, hi + margin
    span = hi - lo
    if resolution is None:
        resolution = float(span.max()) / 512.0
    resolution = float(resolution)
    if not (resolution > 0 and math.isfinite(resolution)):
        raise ValueError(f"resolution must be positive, got {resolution}")
    nx = max(int(math.ceil(span[0] / resolution)), 1)
    ny = max(int(math.ceil(span[1] / resolution)), 1)
    if nx * ny > 64_000_000:
        raise ValueError(f"occupancy grid too large ({ny}x{nx} cells); increase resolution")
    # centre the grid on the box
    cx, cy = (lo + hi) / 2.0
    x0 = cx - nx * resolution / 2.0
    y0 = cy - ny * resolution / 2.0
    return x0, y0, resolution, nx, ny


def _mark(xy, out, x0, y0, res, nx, ny):
    ix = np.floor((xy[:, 0] - x0) / res).astype(np.int64)
    iy = np.floor((xy[:, 1] - y0) / res).astype(np.int64)
    ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    out[iy[ok] * nx + ix[ok]] = True


def _fill_wedges(out, hits_g, sensor, x0, y0, res, nx, ny, gap_factor=2.5) -> np.ndarray:
    """Mark cells inside the fan of one scan: between two angularly adjacent hits (gap at
    most ``gap_factor`` x the scan's median beam spacing) and closer than the segment that
    joins them (the shorter range where the two ranges jump, i.e. at occlusion edges).

    Returns a bool per hit: True where the beam is not covered by the fill on both sides and
    must still be rasterised as a line."""
    n = len(hits_g)
    need = np.ones(n, dtype=bool)
    d = hits_g - sensor
    r_all = np.hypot(d[:, 0], d[:, 1])
    need[r_all <= 0] = False
    idx = np.nonzero(r_all > 0)[0]
    if len(idx) < 3:
        return need
    ang = np.arctan2(d[idx, 1], d[idx, 0])
    order = np.argsort(ang, kind="stable")
    idx, ang, r = idx[order], ang[order], r_all[idx[order]]
    ang = np.concatenate([ang, ang[:1] + 2 * np.pi])
    r = np.concatenate([r, r[:1]])
    gaps = np.diff(ang)  # wedge w lies between sorted beams w and w+1
    max_gap = gap_factor * float(np.median(gaps))
    jump = np.abs(r[:-1] - r[1:]) > 0.1 * np.minimum(r[:-1], r[1:]) + 2.0 * res
    small = gaps <= max_gap
    m = len(gaps)
    # beam i is covered by wedge w if the wedge is filled and, at a jump, i is the shorter
    right_ok = small & (~jump | (r[:-1] <= r[1:]))  # beam w, wedge w
    left_ok = small & (~jump | (r[1:] <= r[:-1]))  # beam w+1, wedge w
    covered = right_ok & np.roll(left_ok, 1)
    need[idx[covered[:m]]] = False

    # cells inside the scan's bounding box of (sensor, hits)
    lo = np.minimum(sensor, hits_g.min(axis=0))
    hi = np.maximum(sensor, hits_g.max(axis=0))
    ix0 = max(int(np.floor((lo[0] - x0) / res)), 0)
    ix1 = min(int(np.floor((hi[0] - x0) / res)) + 1, nx)
    iy0 = max(int(np.floor((lo[1] - y0) / res)), 0)
    iy1 = min(int(np.floor((hi[1] - y0) / res)) + 1, ny)
    if ix0 >= ix1 or iy0 >= iy1:
        return need
    cx = (x0 + (np.arange(ix0, ix1) + 0.5) * res - sensor[0]).astype(np.float32)
    cy = (y0 + (np.arange(iy0, iy1) + 0.5) * res - sensor[1]).astype(np.float32)
    CX, CY = cx[None, :], cy[:, None]
    rc = np.hypot(CX, CY)
    ac = np.arctan2(CY, CX)
    ac[ac < ang[0]] += np.float32(2 * np.pi)
    k = np.searchsorted(ang.astype(np.float32), ac, side="right")
    k -= 1
    np.clip(k, 0, m - 1, out=k)
    # per wedge: range at its first beam and slope; at a jump, the shorter range, flat
    r0 = np.where(jump, np.minimum(r[:-1], r[1:]), r[:-1]).astype(np.float32)
    dr = np.where(jump, 0.0, r[1:] - r[:-1]).astype(np.float32)
    f = ac - ang[:-1].astype(np.float32)[k]
    f /= np.maximum(gaps, 1e-12).astype(np.float32)[k]
    np.clip(f, 0.0, 1.0, out=f)
    f *= dr[k]
    f += r0[k]
    rlim = f  # range of the segment joining the two hits (linear in angle)
    inside = small[k] & (rc <= rlim)
    out.reshape(ny, nx)[iy0:iy1, ix0:ix1] |= inside
    return need


def explored_mask(points_g, valid, sensor_xy, x0, y0, res, nx, ny,
                  max_samples=4_000_000, fill=True) -> np.ndarray:
    """Boolean (ny, nx) grid (row 0 = lowest y) of observed cells.

    A cell is observed when a beam from its sensor position to its hit crosses it (beams are
    sampled every half cell), when it is a hit cell or one of its 8 neighbours, or (``fill``)
    when it lies in the fan between two angularly adjacent beams of a scan, short of the
    segment joining their hits (fills the gaps between beams far from the sensor).

    ``points_g`` (K, N, 2) global hits, ``valid`` (K, N), ``sensor_xy`` (K, 2)."""
    explored = np.zeros(ny * nx, dtype=bool)
    hits = np.zeros(ny * nx, dtype=bool)
    valid = np.asarray(valid, dtype=bool)
    sensor_xy = np.asarray(sensor_xy, dtype=np.float64)
    kk, jj = np.nonzero(valid)
    if len(kk) == 0:
        return explored.reshape(ny, nx)
    b_all = points_g[kk, jj]
    need = np.ones(len(kk), dtype=bool)
    if fill:
        pos = 0
        for k, cnt in zip(*np.unique(kk, return_counts=True)):  # kk is sorted by scan
            need[pos:pos + cnt] = _fill_wedges(explored, b_all[pos:pos + cnt], sensor_xy[k],
                                               x0, y0, res, nx, ny)
            pos += cnt

    # beams not covered by the fill: sample every half cell, in chunks of bounded size
    a = sensor_xy[kk[need]]
    b = b_all[need]
    counts = np.ceil(np.linalg.norm(b - a, axis=1) / (res / 2.0)).astype(np.int64) + 1
    csum = np.cumsum(counts)
    start = 0
    while start < len(counts):
        base = csum[start - 1] if start else 0
        stop = int(np.searchsorted(csum, base + max_samples, side="right"))
        stop = max(stop, start + 1)
        c = counts[start:stop]
        beam = np.repeat(np.arange(start, stop), c)
        first = np.repeat(np.cumsum(c) - c, c)
        i = np.arange(len(beam)) - first  # sample index within its beam
        t = i / np.maximum(np.repeat(c, c) - 1, 1)
        xy = a[beam] + t[:, None] * (b[beam] - a[beam])
        _mark(xy, explored, x0, y0, res, nx, ny)
        start = stop

    _mark(b_all, hits, x0, y0, res, nx, ny)
    hits = hits.reshape(ny, nx)
    near = hits.copy()  # hit cells and their 8 neighbours
    near[1:, :] |= hits[:-1, :]
    near[:-1, :] |= hits[1:, :]
    n2 = near.copy()
    n2[:, 1:] |= near[:, :-1]
    n2[:, :-1] |= near[:, 1:]
    return explored.reshape(ny, nx) | n2


def occupancy_image(occupancy_fn, points, valid, poses, resolution=None, chunk=65536):
    """Rasterise the M-Net occupancy.

    Returns ``(img, extent)``: ``img`` (H, W) float occupancy probabilities with NaN where
    no beam ever looked; row 0 is the lowest y (draw with ``origin="lower"``);
    ``extent = (xmin, xmax, ymin, ymax)`` in point units. ``occupancy_fn`` maps (M, 2)
    global coordinates to (M,) probabilities and is called in chunks of ``chunk`` points,
    only for explored cells.
    """
    pts, val, ps = _as_scans(points, valid, poses)
    g = register_points(pts, ps)
    x0, y0, res, nx, ny = _grid(g, val, ps, resolution)
    explored = explored_mask(g, val, ps[:, :2], x0, y0, res, nx, ny)
    iy, ix = np.nonzero(explored)
    centres = np.stack([x0 + (ix + 0.5) * res, y0 + (iy + 0.5) * res], axis=1)
    probs = np.empty(len(centres), dtype=np.float64)
    for s in range(0, len(centres), chunk):
        q = centres[s:s + chunk]
        out = np.asarray(occupancy_fn(q), dtype=np.float64).reshape(-1)
        if out.shape[0] != q.shape[0]:
            raise ValueError(f"occupancy_fn returned {out.shape[0]} values for {q.shape[0]} points")
        probs[s:s + chunk] = out
    img = np.full((ny, nx), np.nan)
    img[iy, ix] = np.clip(probs, 0.0, 1.0)
    extent = (x0, x0 + nx * res, y0, y0 + ny * res)
    return img, extent


def plot_occupancy(path, occupancy_fn, points, valid, poses, resolution=None, unit="px",
                   unit_scale=1.0, title="", invert_y=False):
    """M-Net occupancy map (paper Fig. 5): occupied black, free white, unexplored grey,
    with the estimated trajectory drawn thinly on top."""
    import matplotlib

    img, extent = occupancy_image(occupancy_fn, points, valid, poses, resolution)
    ps = _as_poses(poses)
    traj = ps[:, :2] * unit_scale
    ext = tuple(e * unit_scale for e in extent)

    h, w = img.shape
    aspect = h / max(w, 1)
    fig = new_figure((7.0, float(np.clip(5.6 * aspect + 1.6, 3.5, 10.0))))
    ax = fig.add_subplot(1, 1, 1)
    cmap = matplotlib.colormaps["gray_r"].with_extremes(bad=_GREY)
    im = ax.imshow(np.ma.masked_invalid(img), cmap=cmap, vmin=0.0, vmax=1.0, origin="lower",
                   extent=ext, interpolation="nearest")
    _draw_traj(ax, traj, color="tab:orange", label="estimated trajectory", lw=0.8, zorder=4)
    ax.plot([], [], marker="s", ms=7, mfc=_GREY, mec="none", ls="none", label="unexplored")
    cb = fig.colorbar(im, ax=ax, shrink=0.85, pad=0.02)
    cb.set_label("occupancy probability")
    ax.set_aspect("equal")
    ax.set_xlim(ext[0], ext[1])
    ax.set_ylim((ext[3], ext[2]) if invert_y else (ext[2], ext[3]))
    ax.set_xlabel("x" + unit_label(unit))
    ax.set_ylabel("y" + unit_label(unit))
    ax.set_title(title or "Occupancy map estimated by the M-Net")
    legend_below(ax)
    save_figure(fig, path)


# --------------------------------------------------------------------------- curves


def _float_list(v, n=None) -> np.ndarray:
    out = np.array([np.nan if x is None else float(x) for x in v], dtype=np.float64)
    if n is not None and len(out) != n:
        raise ValueError(f"history lists have different lengths ({len(out)} vs {n})")
    return out


def _set_log_if_positive(ax, y):
    f = y[np.isfinite(y)]
    if len(f) and np.all(f > 0):
        ax.set_yscale("log")


def plot_curves(path, history: dict):
    """Loss (and ATE, when present) versus iteration and versus wall time."""
    it = _float_list(history["iteration"])
    n = len(it)
    t = _float_list(history["time_s"], n)
    loss = _float_list(history["loss"], n)
    ate = history.get("ate")
    ate = _float_list(ate, n) if ate is not None else None
    has_ate = ate is not None and bool(np.any(np.isfinite(ate)))
    unit = history.get("unit", "") or ""

    rows = 2 if has_ate else 1
    fig = new_figure((10.0, 3.6 * rows + 0.4))
    axes = np.atleast_2d(fig.subplots(rows, 2, squeeze=False))

    def line(ax, x, y, xlabel, ylabel, title, color, marker=None):
        m = np.isfinite(x) & np.isfinite(y)
        ax.plot(x[m], y[m], color=color, lw=1.2, marker=marker, ms=3)
        _set_log_if_positive(ax, y[m])
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        ax.grid(True, which="major", lw=0.4, alpha=0.6)
        ax.grid(True, which="minor", lw=0.2, alpha=0.3)

    line(axes[0, 0], it, loss, "iteration", "loss", "Loss vs iteration", "tab:blue")
    line(axes[0, 1], t, loss, "wall time [s]", "loss", "Loss vs wall time", "tab:blue")
    if has_ate:
        lab = "ATE" + unit_label(unit)
        mk = "o" if np.isfinite(ate).sum() <= 60 else None
        line(axes[1, 0], it, ate, "iteration", lab, "ATE vs iteration", "tab:red", mk)
        line(axes[1, 1], t, ate, "wall time [s]", lab, "ATE vs wall time", "tab:red", mk)
    save_figure(fig, path)


# --------------------------------------------------------------------------- trajectories


def plot_trajectories(path, trajs: dict, gt=None, unit="px", unit_scale=1.0, title="",
                      invert_y=False):
    """Several trajectories (e.g. ICP, DeepMapping) and optionally the ground truth."""
    import matplotlib

    fig = new_figure((7.0, 6.0))
    ax = fig.add_subplot(1, 1, 1)
    colors = matplotlib.colormaps["tab10"].colors
    if gt is not None:
        g = _as_poses(gt, "gt")[:, :2] * unit_scale
        _draw_traj(ax, g, color="black", label="ground truth", ls="--", lw=1.6, zorder=2)
    for i, (name, tr) in enumerate(trajs.items()):
        xy = _as_poses(tr, str(name))[:, :2] * unit_scale
        _draw_traj(ax, xy, color=colors[i % len(colors)], label=str(name), lw=1.3, zorder=3 + i)
    ax.plot([], [], marker="o", ms=6, mfc="grey", mec="white", ls="none", label="start")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x" + unit_label(unit))
    ax.set_ylabel("y" + unit_label(unit))
    if invert_y:
        ax.invert_yaxis()
    ax.set_title(title or "Trajectories")
    ax.grid(True, lw=0.3, alpha=0.5)
    legend_below(ax)
    save_figure(fig, path)


# --------------------------------------------------------------------------- environment


def plot_environment(path, occ, poses_px=None, title=""):
    """Binary simulator map (0 = obstacle, black) in the image frame (x = column, y = row,
    origin top-left) with the trajectory and heading arrows about every 16 poses."""
    occ = np.asarray(occ)
    if occ.ndim != 2:
        raise ValueError(f"occ: expected a 2-D image, got shape {occ.shape}")
    h, w = occ.shape
    fig = new_figure((7.0, float(np.clip(6.2 * h / max(w, 1) + 1.4, 3.5, 10.0))))
    ax = fig.add_subplot(1, 1, 1)
    ax.imshow(occ, cmap="gray", vmin=0, vmax=255 if occ.max(initial=0) > 1 else 1,
              origin="upper", extent=(0, w, h, 0), interpolation="nearest")
    if poses_px is not None:
        ps = _as_poses(poses_px, "poses_px")
        _draw_traj(ax, ps[:, :2], color="tab:blue", label="trajectory", lw=1.2, zorder=3)
        idx = np.arange(0, len(ps), 16)
        L = 0.04 * max(h, w)
        ax.quiver(ps[idx, 0], ps[idx, 1], L * np.cos(ps[idx, 2]), L * np.sin(ps[idx, 2]),
                  angles="xy", scale_units="xy", scale=1.0, color="tab:red", width=0.004,
                  zorder=5, label="heading")
        ax.plot([], [], marker="o", ms=6, mfc="tab:blue", mec="white", ls="none", label="start")
        legend_below(ax)
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_aspect("equal")
    ax.set_xlabel("x = column [px]")
    ax.set_ylabel("y = row [px]")
    ax.set_title(title or f"Environment ({w}x{h} px)")
    save_figure(fig, path)
