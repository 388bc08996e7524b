"""`deepmapping register`: load scans, register, write the run folder."""

from __future__ import annotations

import json
import os
from pathlib import Path

from deepmapping.api import check_settings, register, resolve_device
from deepmapping.cli.common import fail
from deepmapping.cli.progress import console, progress_bar
from deepmapping.config import load_config, resolve_profile
from deepmapping.errors import Interrupted
from deepmapping.io.atomic import make_folder
from deepmapping.io.depth import DepthOptions, parse_frames, parse_image_size
from deepmapping.io.loaders import load_scans
from deepmapping.io.lock import folder_lock
from deepmapping.output.run_dir import write_config, write_json, write_run


def build_config(profile, config_file, method, epochs, warm_start, init, device, seed, sets, is_3d=False, workers=None,
                 handheld=False):
    """The effective config; 3D data gets the 3D variant of the profile (default -> default-3d, or
    handheld for 6-DoF depth images)."""
    profile = resolve_profile(profile, is_3d, cold=warm_start == "none" and init is None, handheld=handheld)

    overrides = dict(sets)
    overrides["method"] = method
    if epochs is not None:
        overrides["optim.epochs"] = epochs
    if device is not None:
        overrides["device"] = device
    if seed is not None:
        overrides["seed"] = seed
    if workers is not None:
        overrides["workers"] = workers
    if init is not None:
        overrides["warm_start.method"], overrides["warm_start.path"] = "file", str(Path(init).resolve())
    elif warm_start is not None:
        overrides["warm_start.method"] = warm_start
    return load_config(profile, config_file, overrides)


def depth_options(every, frames, pixel_stride, image_size, max_depth, intrinsics):
    """The depth-image options of the flags (io.depth.DepthOptions); ConfigError on a bad one."""
    return DepthOptions(every=every, frames=parse_frames(frames) if frames is not None else None,
                        pixel_stride=pixel_stride, image_size=parse_image_size(image_size) if image_size else None,
                        max_depth_m=max_depth, intrinsics=intrinsics)


def resume_config(out: Path):
    if not (out / "config.yaml").exists() or not (out / "checkpoint.pt").exists():
        fail(f"{out}: nothing to resume (no config.yaml and checkpoint.pt)")
    return load_config("default", out / "config.yaml")


def run_register(data: Path, out: Path, cfg, fmt, gt, resume: bool, plots: bool = True, quiet: bool = False,
                 keyframes: str | None = None, non_keyframes: str | None = None, depth=None):
    """cfg: a Config, or a function (is_3d, handheld) -> Config (the profile depends on the data); depth: the
    depth-image options (io.depth.DepthOptions), kept in run.json for `deepmapping evaluate`."""
    import time

    t_load = time.perf_counter()
    # every input problem is raised before out/ exists (the --init file and the device included),
    # and before torch is imported, so bad input fails fast
    cfg0 = cfg(False) if callable(cfg) else cfg
    init = cfg0.warm_start.path if cfg0.warm_start.method == "file" and not resume else None
    scans = load_scans(data, fmt=fmt, gt_path=gt, init_path=init, keyframes=keyframes,
                       non_keyframes=non_keyframes, depth=depth)
    for note in scans.notes if not launched_worker() else ():  # torchrun: worker 0 speaks for all
        console.print(f"note: {note}", highlight=False, soft_wrap=True)
    cfg = cfg(scans.is_3d, scans.handheld) if callable(cfg) else cfg
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:  # torchrun: the run says how many trained it
        cfg = cfg.model_copy(update={"workers": int(os.environ["WORLD_SIZE"])})
    load_s = time.perf_counter() - t_load

    check_settings(scans, cfg)
    if cfg.method in ("deepmapping", "direct"):
        resolve_device(cfg.device)
    info = {"data": str(data.resolve()), "format": fmt, "gt": str(Path(gt).resolve()) if gt else None,
            "keyframes": keyframes, "non_keyframes": non_keyframes, "notes": scans.notes}
    if depth is not None and not depth.is_default():
        info["depth"] = depth.to_dict()
    if launched_worker():  # torchrun: worker 0 writes the run; the others train with it
        return scans, register(scans, cfg, checkpoint=out / "checkpoint.pt", resume=resume)
    if not quiet:
        console.print(settings_line(scans, cfg), highlight=False, soft_wrap=True)
    with folder_lock(make_folder(out)):  # a second command on this folder refuses (FolderBusy)
        write_config(out, cfg)
        write_json(out / "run.json", {"method": cfg.method, "status": "running", **info})
        try:
            with progress_bar(not quiet) as cb:
                result = register(scans, cfg, checkpoint=out / "checkpoint.pt", resume=resume,
                                  on_log=cb.log, on_epoch=cb.epoch, on_icp_progress=cb.icp,
                                  on_place=cb.place)
            t_write = time.perf_counter()
            write_run(out, scans, result, info, plots=plots)
        except (Interrupted, KeyboardInterrupt):  # in training, or before or after it
            interrupted(data, out)
        reg = result.timings or {"registration_s": result.runtime_s}  # a baseline: one stage
        result.timings = {"load_s": load_s, **reg, "write_s": time.perf_counter() - t_write,
                          "peak_rss_mb": peak_rss_mb()}
        write_json(out / "run.json", json.loads((out / "run.json").read_text()) | {"timings": result.timings})
    return scans, result


def settings_line(scans, cfg) -> str:
    """What the run uses where the data chose it: 'settings: profile handheld, warm start icp-plane
    (auto), 200 epochs' (the whole config goes to config.yaml)."""
    from deepmapping.api import BASELINES, auto_warm_start, start_settings

    line = f"settings: profile {cfg.profile}"
    if cfg.method in BASELINES:  # a classical method: no warm start, no epochs
        return f"{line}, method {cfg.method}"
    ws = cfg.warm_start.method
    line = f"{line}, warm start {auto_warm_start(scans) + ' (auto)' if ws == 'auto' else ws}, {cfg.optim.epochs} epochs"
    derived = start_settings(scans, cfg)
    warmup = derived.get("optim.mnet_warmup_epochs")
    line += f", the first {warmup} M-Net only" if warmup else ""
    line += ", grid M-Net" if derived.get("mnet.kind") == "grid" else ""
    near = derived.get("loss.near_hit_samples")
    line += f", {near} free-space samples near each hit" if near else ""
    return line + (", batches of scans drawn at random" if derived.get("optim.batch_order") == "random" else "")


def interrupted(data: Path, out: Path) -> None:
    """Ctrl-C: say how to go on from the checkpoint (training writes one when interrupted, and one
    at its end, so Ctrl-C while the results are written resumes to writing them); exit 130."""
    if (out / "checkpoint.pt").exists():
        console.print(f"[yellow]interrupted:[/] checkpoint saved; continue with "
                      f"`deepmapping register {data} --out {out} --resume`", soft_wrap=True)  # one line: copyable
    else:
        console.print(f"[yellow]interrupted:[/] no checkpoint yet in {out}; run the command again", soft_wrap=True)
    raise SystemExit(130) from None


def launched_worker() -> bool:
    """Whether a launcher (torchrun) started this process as a worker other than the first."""
    return int(os.environ.get("WORLD_SIZE", "1")) > 1 and os.environ.get("RANK", "0") != "0"


def peak_rss_mb() -> float:
    """This process's peak resident memory (MB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def timings_line(t: dict) -> str:
    """'time: loading 0.4 s, warm start 2.8 s, ... ; peak memory 800 MB' from Result.timings."""
    names = {"load_s": "loading", "warm_start_s": "warm start", "curriculum_s": "cold-start placements",
             "training_s": "training", "registration_s": "registration", "write_s": "results and pictures"}
    parts = [f"{names[k]} {t[k]:.1f} s" for k in names if k in t and (t[k] or k != "curriculum_s")]
    return "time: " + ", ".join(parts) + (f"; peak memory {t['peak_rss_mb']:.0f} MB" if "peak_rss_mb" in t else "")


def rollback_note(rollbacks: list[dict], out: Path) -> str:
    """The final message's line about NaN/inf steps that training rolled back from."""
    first = rollbacks[0]
    return (f"note: the {first['what']} at epoch {first['epoch']} (step {first['step']}); training went back "
            f"to its last good state with lower learning rates ({len(rollbacks)} rollback(s), now "
            f"{rollbacks[-1]['lr_scale']:g} x the set ones); see {out / 'run.json'}")
