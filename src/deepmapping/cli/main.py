"""The `deepmapping` command: simulate, register, evaluate, relations, experiment, demo."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from deepmapping.cli.common import fail, parse_sets
from deepmapping.cli.demo_cmd import run_demo
from deepmapping.cli.evaluate_cmd import run_evaluate
from deepmapping.cli.experiment_cmd import run_experiment_cli
from deepmapping.config import PROFILES
from deepmapping.errors import ConfigError, DeepMappingError
from deepmapping.experiments import EXPERIMENTS
from deepmapping.methods.registry import METHODS as METHODS_BY_NAME
from deepmapping.output.run_dir import default_run_dir
from deepmapping.sim import dataset, maps
from deepmapping.sim.lidar import write_lidar_dataset
from deepmapping.sim.rgbd import write_rgbd_dataset

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="DeepMapping: register many 2D laser scans or 3D point clouds into one map by training an "
                       "L-Net and an M-Net.")

METHODS = " | ".join(m.label for m in METHODS_BY_NAME.values())  # the registry (methods.registry)
PROFILE_HELP = (" | ".join(p for p in PROFILES if not p.endswith("-3d"))  # the files in src/deepmapping/profiles/
                + ": default = fast path, paper = §4.1/§4.2 exactly, cold = --warm-start none, fast = 2D scans of "
                "128+ beams (1.4x less training time than default, a little less accurate), bunny = single objects "
                "scanned around; 3D data gets the -3d variant. Each is a file in deepmapping/profiles/.")


@app.command(epilog="Examples:\n\n  deepmapping simulate data/traj0 --poses 256 --seed 3\n\n"
                    "  deepmapping simulate data/custom --map mymap.png --poses 128\n\n"
                    "  deepmapping simulate data/paper --paper-dataset\n\n"
                    "  deepmapping simulate data/avd --kind rgbd --trajectories 10 --frames 16\n\n"
                    "  deepmapping simulate data/lidar --kind lidar --lidar-beams 32\n\n"
                    "  deepmapping simulate data/fhw --kind odometry --log ../shared/data/carmen/corrected/fhw-corrected.log.gz")
def simulate(
    out: Path = typer.Argument(..., help="Folder to write (2D: authors' layout 000.pcd…, gt_pose.mat, map.png; "
                                         "3D: traj_000/, traj_001/, …)."),
    kind: str = typer.Option("2d", help="2d (laser, §4.1) | rgbd (AVD-like depth images, §4.2) | lidar (3D, 6-DoF) | "
                             "odometry (a corrected CARMEN log, --log, with simulated wheel odometry: <site>.clf and "
                             "<site>.relations)."),
    log: Optional[Path] = typer.Option(None, help="odometry: the corrected log (*-corrected.log.gz) whose scans and "
                                       "poses (the reference) to use."),
    trajectories: int = typer.Option(10, help="3D: number of trajectories."),
    frames: int = typer.Option(16, help="3D: frames per trajectory (AVD: 8 or 16)."),
    lidar_beams: int = typer.Option(16, help="lidar: 16, 32 or 64 beams."),
    lidar_step: float = typer.Option(0.4, help="lidar: metres between frames (0.1: a robot at 1 m/s and 10 Hz, "
                                     "turns of about 10 deg a frame; 0.4: turns of up to 50 deg)."),
    poses: int = typer.Option(256, help="Number of poses (scans) on the trajectory."),
    beams: int = typer.Option(256, help="Beams per 360° scan."),
    seed: int = typer.Option(0, help="Trajectory seed."),
    map: Optional[str] = typer.Option(None, "--map", help="PNG map (black = obstacle); default: procedural indoor map."),
    map_seed: int = typer.Option(0, help="Seed of the procedural map."),
    max_range: Optional[float] = typer.Option(None, help="Maximum range in px (default unlimited)."),
    rotation: float = typer.Option(10.0, help="Max rotation per step (deg)."),
    step: float = typer.Option(8.16, help="Mean translation per step (px)."),
    noise: float = typer.Option(0.0, help="Range noise std (2D: px; 3D: m); 0 = ideal scanner as in the paper."),
    paper_dataset: bool = typer.Option(False, "--paper-dataset", help="Write the paper's 75 trajectories on 3 maps."),
):
    """Simulate scans with ground truth: a 2D lidar in a 1024×1024 occupancy image (§4.1), or 3D
    indoor scenes seen by an AVD-like depth camera (§4.2) or a spinning LiDAR."""
    if kind in ("rgbd", "lidar"):
        _simulate_3d(out, kind, trajectories, frames, seed, lidar_beams, noise, lidar_step)
        return
    if kind == "odometry":
        _simulate_odometry(out, log, seed)
        return
    if kind != "2d":
        raise typer.BadParameter(f"--kind must be 2d, rgbd, lidar or odometry, got {kind!r}")

    if paper_dataset:
        folders = dataset.paper_dataset(out, seed=seed)
        typer.echo(f"wrote {len(folders)} trajectories under {out}")
        return
    occ = maps.load_map_png(map) if map else maps.procedural_indoor_map(map_seed)
    scans = dataset.simulate(occ, poses, seed, num_beams=beams, max_range=max_range,
                             max_rotation_deg=rotation, mean_step_px=step, range_noise_px=noise)
    dataset.write_authors_layout(out, scans, occ=occ)
    typer.echo(f"wrote {poses} scans to {out} (picture: {out / 'map.png'})")


def _simulate_odometry(out: Path, log: Optional[Path], seed: int) -> None:
    from deepmapping.sim.odometry import simulated_log

    if log is None:
        raise ConfigError("--kind odometry needs --log CORRECTED (a corrected CARMEN log, e.g. fhw-corrected.log.gz)")
    log_path, relations_path, s = simulated_log(log, out, seed)
    typer.echo(f"wrote {log_path} ({s['scans']} scans, {s['path_m']:.0f} m, odometry {s['end_error_m']:.1f} m off at "
               f"the end{'' if s['own_timestamps'] else '; timestamps from the path at 0.5 m/s'}) and {relations_path}")


def _simulate_3d(out: Path, kind: str, trajectories: int, frames: int, seed: int, beams: int, noise: float,
                 lidar_step: float = 0.4) -> None:
    if kind == "rgbd":
        write_rgbd_dataset(out, num_trajectories=trajectories, frames=frames, seed=seed, noise_std_m=noise)
    else:
        if not lidar_step > 0:
            raise typer.BadParameter(f"--lidar-step must be > 0 metres, got {lidar_step}")
        write_lidar_dataset(out, num_trajectories=trajectories, frames=frames, seed=seed, beams=beams,
                            noise_std_m=noise, step_m=lidar_step)
    typer.echo(f"wrote {trajectories} {kind} trajectories of {frames} frames under {out}")


@app.command(epilog="Examples:\n\n  deepmapping register data/traj0 --out runs/dm\n\n"
                    "  deepmapping register data/traj0 --method icp-plane --out runs/icp\n\n"
                    "  deepmapping register data/traj0 --profile paper --set optim.epochs=500\n\n"
                    "  deepmapping register data/traj0 --out runs/dm --resume   # after Ctrl-C\n\n"
                    "  deepmapping register ../shared/data/carmen/fr079.clf.bz2 --warm-start file --keyframes motion:0.5,15\n\n"
                    "  deepmapping register ../shared/data/7scenes-redkitchen --frames 0:48 --every 3 --image-size 80x60")
def register(
    data: Path = typer.Argument(..., help="Scan folder (authors' layout, .pcd/.ply/.npy scans, depth images: rgbd, "
                                "7-Scenes, TUM RGB-D; 3DTK, KITTI) "
                                "or a CARMEN log (.clf/.log, .gz/.bz2)."),
    method: str = typer.Option("deepmapping", help=METHODS),
    out: Optional[Path] = typer.Option(None, help="Run folder (default: runs/<timestamp>_<method>)."),
    profile: str = typer.Option("default", help=PROFILE_HELP),
    config: Optional[Path] = typer.Option(None, help="YAML/JSON config file (sections as in config.yaml)."),
    set: Optional[List[str]] = typer.Option(None, "--set", help="Override a setting: --set optim.epochs=200."),
    epochs: Optional[int] = typer.Option(None, help="Number of epochs."),
    warm_start: Optional[str] = typer.Option(None, help="auto (default: icp-plane; loop-closure for logs; icp-planar "
                                             "for AVD-like depth images with planar poses; a 3D sequence's own "
                                             "recorded poses, e.g. 3DTK's .pose, held by the odometry factor) | "
                                             "icp-plane | icp-point | "
                                             "loop-closure | icp-planar | "
                                             "multiway | kiss-icp (LiDAR sequences) | file (the poses the data "
                                             "came with) | none."),
    init: Optional[Path] = typer.Option(None, help="Initial poses file (warm start), in the scans' units."),
    gt: Optional[Path] = typer.Option(None, help="Ground-truth poses (overrides the folder's own)."),
    format: Optional[str] = typer.Option(None, "--format", help="Loader name (default: picked from the path)."),
    keyframes: Optional[str] = typer.Option(None, help="Logs (CARMEN): which scans to register: all | every:K | "
                                            "motion:METRES,DEGREES | time:SECONDS (default motion:0.5,15)."),
    non_keyframes: Optional[str] = typer.Option(None, help="Logs: the other scans' poses: icp (default: odometry from the "
                                                "nearest keyframe, then matched to the keyframes around it) | odometry."),
    every: int = typer.Option(1, help="Depth images: keep every k-th frame (of the --frames range)."),
    frames: Optional[str] = typer.Option(None, help="Depth images: frames START:STOP, positions in the folder's "
                                         "frame list (0-based, STOP excluded; e.g. 0:48)."),
    pixel_stride: Optional[int] = typer.Option(None, help="Depth images: keep every s-th row and column (default: "
                                               "rgbd all; 7scenes and tum-rgbd about 80 pixels across, 80x60)."),
    image_size: Optional[str] = typer.Option(None, help="Depth images: WIDTHxHEIGHT pixels kept, e.g. 80x60 "
                                             "(instead of --pixel-stride)."),
    max_depth: Optional[float] = typer.Option(None, help="Depth images: pixels deeper than this (metres) are "
                                              "invalid, as 0 and 65535 always are."),
    intrinsics: Optional[str] = typer.Option(None, help="Depth images: the camera: a 3x3 K text file, an "
                                             "intrinsics.json, or tum | fr1 | fr2 | fr3 | 7scenes."),
    device: Optional[str] = typer.Option(None, help="auto | cpu | cuda."),
    seed: Optional[int] = typer.Option(None, help="Seed (fixes everything)."),
    workers: Optional[int] = typer.Option(None, help="Processes that train the one map together (torch.distributed: "
                                          "gloo on CPU, NCCL on GPUs; each takes a part of every batch)."),
    resume: bool = typer.Option(False, help="Continue an interrupted run in --out from its checkpoint."),
    no_plots: bool = typer.Option(False, "--no-plots", help="Skip the PNG pictures."),
):
    """Register scans with DeepMapping or a baseline and write poses, map, pictures, metrics."""
    from deepmapping.cli import register_cmd
    from deepmapping.cli.progress import console
    from deepmapping.cli.report import print_metrics

    depth = register_cmd.depth_options(every, frames, pixel_stride, image_size, max_depth, intrinsics)
    if resume:
        if out is None:
            raise typer.BadParameter("--resume needs --out RUN_DIR")
        cfg = register_cmd.resume_config(out)
    else:
        sets = parse_sets(set)
        cfg = lambda is_3d, handheld=False: register_cmd.build_config(  # noqa: E731
            profile, config, method, epochs, warm_start, init, device, seed, sets, is_3d, workers, handheld)
        cfg(False)  # a bad setting fails before any data is read
    out = out or default_run_dir(method)
    scans, result = register_cmd.run_register(data, out, cfg, format, gt, resume, plots=not no_plots,
                                              keyframes=keyframes, non_keyframes=non_keyframes, depth=depth)
    if register_cmd.launched_worker():
        return
    if result.metrics:
        print_metrics(console, {result.method: result.metrics})
    if result.history.get("rollbacks"):
        typer.echo(register_cmd.rollback_note(result.history["rollbacks"], out))
    if result.history.get("reviewed"):
        moved = result.history["reviewed"]
        typer.echo(f"cold start: the review of the placements placed {len(moved)} scan(s) again "
                   f"({', '.join(map(str, sorted(moved)))})")
    if result.history.get("odometry_sigma"):
        st, sr = result.history["odometry_sigma"]
        typer.echo(f"odometry factor: the warm start's relative motions held with sigma {st:g} (scan units) and "
                   f"{sr:g} deg (loss.odometry_sigma; --set loss.odometry_sigma=off drops it)")
    if result.history.get("stop_reason"):
        epochs = (result.history.get("epoch") or [0])[-1]
        typer.echo(f"training stopped after {epochs:g} of {result.config.optim.epochs} epochs: "
                   f"{result.history['stop_reason']}")
    if result.timings:
        typer.echo(register_cmd.timings_line(result.timings))
    typer.echo(f"results in {out}")


@app.command(epilog="Example:\n\n  deepmapping evaluate runs/20260101-120000_deepmapping")
def evaluate(
    run_dir: Path = typer.Argument(..., help="A folder written by `deepmapping register`."),
    gt: Optional[Path] = typer.Option(None, help="Ground-truth poses (default: the data's own)."),
):
    """Evaluate a run against ground truth: ATE, point distance, success; writes metrics.json."""
    from deepmapping.cli.progress import console
    from deepmapping.cli.report import print_metrics

    metrics = run_evaluate(run_dir, gt)
    print_metrics(console, {metrics["method"]: metrics}, title=str(run_dir))


@app.command(epilog="Example:\n\n  deepmapping relations ../shared/data/carmen/corrected/csail-corrected.log.gz "
                    "../shared/data/carmen/mit-csail.clf.bz2 --out mit-csail.relations\n\n"
                    "  deepmapping register ../shared/data/carmen/mit-csail.clf.bz2 --gt mit-csail.relations")
def relations(
    corrected: Path = typer.Argument(..., help="A corrected log (poses from a SLAM system, e.g. *-corrected.log.gz)."),
    log: Path = typer.Argument(..., help="The raw log of the same run (its timestamps are the relations')."),
    out: Path = typer.Option(..., help="The .relations file to write (Freiburg benchmark format)."),
    count: int = typer.Option(3000, help="Relations to draw (fewer where fewer pairs qualify)."),
    seed: int = typer.Option(0, help="Seed of the random draw."),
):
    """Relations for a log without the benchmark's file: pairs of scans at most 1 m apart in the
    corrected log, 40 % of them over 10 s apart, drawn at random; score with --gt FILE.relations."""
    from deepmapping.cli.progress import console
    from deepmapping.evaluation.relations import LONG_RELATION_S
    from deepmapping.io.relations import relations_from_corrected, write_relations

    if out.suffix != ".relations":
        raise ConfigError(f"{out}: the file name must end in .relations (what --gt reads as relations)")
    rel = relations_from_corrected(corrected, log, seed=seed, count=count)
    write_relations(out, rel)
    long = int((rel.span_s() > LONG_RELATION_S).sum())
    console.print(f"{len(rel)} relations ({long} over 10 s) written to {out}", highlight=False, soft_wrap=True)


@app.command(epilog="Examples:\n\n  deepmapping experiment 1d --out exp/1d\n\n"
                    "  deepmapping experiment 2d --quick --out exp/2d_quick\n\n"
                    "  deepmapping experiment 2d --out exp/2d --jobs 8\n\n"
                    "  deepmapping experiment 2d --out exp/2d --only 'deepmapping-cold-*'\n\n"
                    "  deepmapping experiment robustness --out exp/robustness\n\n"
                    "  deepmapping experiment avd --out exp/avd --cluster tcp://scheduler:8786")
def experiment(
    name: str = typer.Argument(..., help=" | ".join(EXPERIMENTS)),
    out: Path = typer.Option(..., help="Folder for the runs, pictures and report.md (rerun to resume)."),
    quick: bool = typer.Option(False, "--quick", help="A small size that runs in minutes on 2 CPU cores."),
    jobs: Optional[int] = typer.Option(None, help="Runs at a time on this machine (default: one per core)."),
    threads: int = typer.Option(1, help="Torch threads per run."),
    cluster: Optional[str] = typer.Option(None, help="Dask scheduler address (tcp://host:8786), or 'local' for a "
                                          "local Dask cluster; needs pip install 'deepmapping\\[cluster]'."),
    retries: int = typer.Option(1, help="Times a failed run is retried before it is reported."),
    only: Optional[str] = typer.Option(None, help="Run only the runs whose key matches this shell pattern "
                                       "(e.g. 'deepmapping-cold-*'); the report still uses every finished run."),
    data: Optional[Path] = typer.Option(None, help="The folder of real recordings an experiment on them reads "
                                        "(default: ../shared/data/<its folder>)."),
):
    """Reproduce one of the paper's experiments: independent runs in parallel, then a markdown report."""
    run_experiment_cli(name, out, quick, jobs, threads, cluster, retries, only, data)


@app.command(epilog="Example:\n\n  deepmapping demo --out demo")
def demo(
    out: Path = typer.Option(Path("demo"), help="Folder for the demo's data and runs."),
    poses: int = typer.Option(256, help="Trajectory length."),
    seed: int = typer.Option(0, help="Trajectory seed."),
):
    """Simulate a trajectory, register it with ICP and DeepMapping, evaluate, draw pictures."""
    run_demo(out, poses, seed)


def main() -> None:
    """Console entry point: user errors become one line on stderr and exit code 2."""
    try:
        app()
    except DeepMappingError as exc:
        fail(str(exc), exc.exit_code)
