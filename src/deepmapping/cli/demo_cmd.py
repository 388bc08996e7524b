"""`deepmapping demo`: simulate, register with ICP and DeepMapping, evaluate, draw."""

from __future__ import annotations

from pathlib import Path

import typer

from deepmapping.geometry.alignment import align_poses_2d
from deepmapping.output.plots import plot_trajectories
from deepmapping.sim import dataset, maps


def run_demo(out: Path, poses: int, seed: int) -> None:
    from deepmapping.cli.progress import console
    from deepmapping.cli.register_cmd import build_config, run_register
    from deepmapping.cli.report import metrics_table

    data = out / "data"
    console.print(f"[bold]1/3[/] simulating {poses} scans on a procedural indoor map (seed {seed}) -> {data}")
    occ = maps.procedural_indoor_map(seed)
    dataset.write_authors_layout(data, dataset.simulate(occ, poses, seed), occ=occ)
    rows, trajs, scans = {}, {}, None
    for i, method in enumerate(("icp-plane", "deepmapping"), start=2):
        console.print(f"[bold]{i}/3[/] registering with {method}")
        cfg = build_config("default", None, method, None, None, None, None, seed, {})
        scans, result = run_register(data, out / method, cfg, None, None, resume=False)
        rows[method], trajs[method] = result.metrics, result.poses * scans.unit_scale

    gt = scans.gt_poses * [scans.unit_scale, scans.unit_scale, 1]
    trajs = {k: align_poses_2d(v * [1, 1, 1], gt) for k, v in trajs.items()}
    plot_trajectories(out / "trajectories.png", {k: v for k, v in trajs.items()}, gt=gt, unit="px",
                      title="Aligned trajectories vs ground truth", invert_y=True)
    console.print(metrics_table(rows, title="Demo: ATE against ground truth"))
    typer.echo(f"pictures: {out / 'data' / 'map.png'}, {out / 'deepmapping' / 'map.png'}, "
               f"{out / 'deepmapping' / 'occupancy.png'}, {out / 'trajectories.png'}")
