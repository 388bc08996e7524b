"""Off-screen pictures of 3D runs: the registered cloud (perspective + top view) and trajectories.

Same rules as ``output/plots.py``: matplotlib ``Figure`` rendered by Agg, one PNG written
atomically, no window. Poses are (K, 4, 4) sensor-to-world; the sensor positions (their
translations) form the trajectory. Lengths are drawn as ``coordinate * unit_scale`` in ``unit``.

``up_axis`` names the world direction that points up: "x", "y", "z", "-x", "-y" or "-z". The
default "-y" fits frames with y pointing DOWN (the RGB-D camera convention, 3DTK as loaded);
the Stanford Bunny's world has y up ("y"). The top view looks down on the plane normal to it
(x-z for a y axis) without mirroring; the 3D view draws that axis vertical.
"""

from __future__ import annotations

import numpy as np

from deepmapping.evaluation.metrics3d import align_poses_3d
from deepmapping.output.export3d import registered_cloud, scan_colors
from deepmapping.output.plots import legend_below, new_figure, save_figure, unit_label

__all__ = ["view_basis", "plot_cloud_3d", "plot_trajectories_3d"]

# display axes (right, forward, up) as signed world axes, for an up axis pointing to +axis
_BASES = {"x": ("y", "z", "x"), "y": ("x", "-z", "y"), "z": ("x", "y", "z")}


def view_basis(up_axis: str = "-y") -> tuple[np.ndarray, list[str]]:
    """(3, 3) rotation V (display = V @ world; rows right, forward, up) and the axis labels."""
    axis = up_axis.lstrip("+-")
    if axis not in _BASES or up_axis.count("-") > 1:
        raise ValueError(f"up_axis must be one of x, y, z, -x, -y, -z; got {up_axis!r}")
    sign = -1.0 if up_axis.startswith("-") else 1.0
    rows, labels = [], []
    for i, name in enumerate(_BASES[axis]):
        s = (-1.0 if name.startswith("-") else 1.0) * (sign if i else 1.0)
        rows.append(s * np.eye(3)["xyz".index(name.lstrip("-"))])
        labels.append(("-" if s < 0 else "") + name.lstrip("-"))
    return np.array(rows), labels


def _sample(pts, index, max_points: int, seed: int = 0):
    if len(pts) <= max_points:
        return pts, index
    keep = np.sort(np.random.default_rng(seed).choice(len(pts), max_points, replace=False))
    return pts[keep], index[keep]


def _equal_3d(ax, xyz) -> None:
    lo, hi = xyz.min(0), xyz.max(0)
    c, r = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-9)
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))


def plot_cloud_3d(path, points, valid, poses, gt_poses=None, title="", unit_scale=1.0, unit="m",
                  max_points=20000, up_axis="-y", show_trajectory=True):
    """Registered cloud coloured by scan (perspective and top views), the estimated trajectory
    (black) and, if given, the gt trajectory rigidly aligned onto it (dashed red).

    ``show_trajectory=False`` leaves out the sensor positions (e.g. the bunny's, ~1.3 m from
    a 0.15 m object) so that the views frame the cloud alone."""
    poses = np.asarray(poses, np.float64)
    pts, index = _sample(*registered_cloud(points, valid, poses), max_points)
    V, labels = view_basis(up_axis)
    d = pts @ V.T * unit_scale
    trajs = [(poses, "black", "-", "estimated trajectory")]
    if gt_poses is not None:
        trajs.append((align_poses_3d(gt_poses, poses), "tab:red", "--", "ground truth (aligned)"))
    trajs = [((p[:, :3, 3] @ V.T) * unit_scale, c, ls, lab) for p, c, ls, lab in trajs if show_trajectory]
    colors = scan_colors(len(poses))[index] / 255.0
    size = float(np.clip(3.0e4 / max(len(d), 1), 0.3, 6.0))

    fig = new_figure((12.0, 6.0))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax3.scatter(d[:, 0], d[:, 1], d[:, 2], c=colors, s=size, linewidths=0, depthshade=False, rasterized=True)
    ax2 = fig.add_subplot(1, 2, 2)
    ax2.scatter(d[:, 0], d[:, 1], c=colors, s=size, linewidths=0, rasterized=True, zorder=1)
    for t, c, ls, lab in trajs:
        ax3.plot(t[:, 0], t[:, 1], t[:, 2], color=c, ls=ls, lw=1.2, marker="o", ms=2)
        ax2.plot(t[:, 0], t[:, 1], color=c, ls=ls, lw=1.2, marker="o", ms=2.5, label=lab, zorder=3)
    _equal_3d(ax3, np.concatenate([d] + [t for t, *_ in trajs]))
    for set_label, name in zip((ax3.set_xlabel, ax3.set_ylabel, ax3.set_zlabel), labels):
        set_label(name + unit_label(unit))
    ax3.set_title("perspective")
    ax2.set_aspect("equal", adjustable="datalim")
    ax2.set_xlabel(labels[0] + unit_label(unit))
    ax2.set_ylabel(labels[1] + unit_label(unit))
    ax2.set_title(f"top view (up = {labels[2]})")
    ax2.grid(True, lw=0.3, alpha=0.5)
    fig.suptitle(title or f"Registered point clouds ({len(poses)} scans)")
    legend_below(ax2)
    save_figure(fig, path)


def plot_trajectories_3d(path, trajs: dict, gt=None, title="", unit_scale=1.0, unit="m", up_axis="-y",
                         align=True):
    """Top view of several trajectories (K, 4, 4) and optionally the ground truth (dashed
    black); with ``align`` each trajectory is first rigidly aligned onto the ground truth."""
    import matplotlib

    V, labels = view_basis(up_axis)
    colors = matplotlib.colormaps["tab10"].colors
    fig = new_figure((7.0, 6.0))
    ax = fig.add_subplot(1, 1, 1)
    if gt is not None:
        g = np.asarray(gt, np.float64)[:, :3, 3] @ V.T * unit_scale
        ax.plot(g[:, 0], g[:, 1], color="black", ls="--", lw=1.6, label="ground truth", zorder=2)
    for i, (name, tr) in enumerate(trajs.items()):
        tr = np.asarray(tr, np.float64)
        if align and gt is not None:
            tr = align_poses_3d(tr, gt)
        xy = tr[:, :3, 3] @ V.T * unit_scale
        ax.plot(xy[:, 0], xy[:, 1], color=colors[i % len(colors)], lw=1.3, label=str(name), zorder=3 + i)
        ax.plot(xy[0, 0], xy[0, 1], marker="o", ms=6, mfc=colors[i % len(colors)], mec="white", ls="none",
                zorder=4 + i)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(labels[0] + unit_label(unit))
    ax.set_ylabel(labels[1] + unit_label(unit))
    ax.set_title(title or f"Trajectories, top view (up = {labels[2]})")
    ax.grid(True, lw=0.3, alpha=0.5)
    legend_below(ax)
    save_figure(fig, path)
