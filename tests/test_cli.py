"""End-to-end tests of the `deepmapping` command, run as a subprocess (console script).

Registration runs use tiny settings (16 poses, a few epochs); independent runs are started
concurrently to keep the file fast.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import yaml

from deepmapping.io.pcd import read_pcd, write_pcd
from deepmapping.io.poses import read_gt_mat, write_gt_mat

_SCRIPT = Path(sys.executable).parent / "deepmapping"
DM = str(_SCRIPT) if _SCRIPT.exists() else shutil.which("deepmapping")
ENV = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONUNBUFFERED="1")
NUM_POSES = 16
TINY = ["--epochs", "3", "--set", "optim.eval_every=1"]
WORKERS = max(2, min(os.cpu_count() or 2, 6))

pytestmark = pytest.mark.skipif(DM is None, reason="the `deepmapping` console script is not installed")


def dm(*args, cwd=None, timeout=180) -> subprocess.CompletedProcess:
    return subprocess.run([DM, *map(str, args)], capture_output=True, text=True, env=ENV, cwd=cwd,
                          timeout=timeout)


def dm_many(jobs: dict[str, list], cwd=None) -> dict[str, subprocess.CompletedProcess]:
    """Run independent commands concurrently; {name: args} -> {name: result}."""
    with ThreadPoolExecutor(WORKERS) as pool:
        futures = {name: pool.submit(dm, *args, cwd=cwd) for name, args in jobs.items()}
        return {name: f.result() for name, f in futures.items()}


def ok(res: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert res.returncode == 0, f"exit {res.returncode}\nstdout:\n{res.stdout}\nstderr:\n{res.stderr}"
    assert "Traceback" not in res.stderr + res.stdout
    return res


def assert_one_line_error(res: subprocess.CompletedProcess, names: str, out_dir: Path | None = None) -> str:
    """Exit 2, one non-empty `error: ...` line on stderr naming `names`, no traceback, no run folder."""
    where = f"\nstdout:\n{res.stdout}\nstderr:\n{res.stderr}"
    assert res.returncode == 2, f"exit {res.returncode}, expected 2{where}"
    assert "Traceback" not in res.stderr + res.stdout, where
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got {len(lines)}{where}"
    line = lines[0]
    assert line.startswith("error: ") and len(line) > len("error: "), where
    assert names in line, f"error line does not name {names!r}: {line!r}"
    if out_dir is not None:
        assert not out_dir.exists(), f"{out_dir} was created by a failed run{where}"
    return line


# ------------------------------------------------------------------------------------------
# shared data and runs (built once per session, also under pytest-xdist)
# ------------------------------------------------------------------------------------------
def _shared(tmp_path_factory, name: str, build):
    """build(folder) -> JSON-able value, computed once: under xdist the workers share it
    through the session's common temp folder (file lock + JSON), otherwise plain."""
    if "PYTEST_XDIST_WORKER" not in os.environ:
        return build(tmp_path_factory.mktemp(name))
    import fcntl

    root = tmp_path_factory.getbasetemp().parent  # shared by the workers of this session
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        done = root / f"{name}.json"
        if not done.exists():
            folder = root / name
            folder.mkdir()
            done.write_text(json.dumps(build(folder)))
        return json.loads(done.read_text())


def _to_json(res: subprocess.CompletedProcess) -> dict:
    return {"args": [str(a) for a in res.args], "returncode": res.returncode, "stdout": res.stdout,
            "stderr": res.stderr}


def _from_json(d: dict) -> subprocess.CompletedProcess:
    return subprocess.CompletedProcess(d["args"], d["returncode"], d["stdout"], d["stderr"])


@pytest.fixture(scope="module")
def data16(tmp_path_factory) -> Path:
    def build(folder: Path) -> str:
        data = folder / "data16"
        res = ok(dm("simulate", data, "--poses", NUM_POSES, "--seed", 1))
        assert str(data) in res.stdout
        return str(data)

    return Path(_shared(tmp_path_factory, "data16", build))


RUN_SEED = 5
DM_SETS = ["--set", "loss.free_samples=2", "--set", "optim.lr=0.002"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory, data16) -> dict[str, tuple[Path, subprocess.CompletedProcess]]:
    """icp-plane, deepmapping (twice, same seed), direct: run concurrently, once."""

    def build(folder: Path) -> dict:
        reg = ["register", data16]
        dm_args = [*TINY, *DM_SETS, "--seed", RUN_SEED, "--device", "cpu"]
        jobs = {
            "icp-plane": [*reg, "--method", "icp-plane", "--out", folder / "R1"],
            "deepmapping": [*reg, "--method", "deepmapping", *dm_args, "--out", folder / "R2"],
            "deepmapping-again": [*reg, "--method", "deepmapping", *dm_args, "--no-plots", "--out", folder / "R2b"],
            "direct": [*reg, "--method", "direct", *TINY, "--out", folder / "R3"],
            "cold": [*reg, "--warm-start", "none", *TINY, "--out", folder / "R4"],
        }
        results = dm_many(jobs)
        return {name: {"out": str(jobs[name][-1]), **_to_json(res)} for name, res in results.items()}

    built = _shared(tmp_path_factory, "runs", build)
    return {name: (Path(d["out"]), _from_json(d)) for name, d in built.items()}


# ------------------------------------------------------------------------------------------
# 1. help
# ------------------------------------------------------------------------------------------
def test_app_help_lists_commands():
    res = ok(dm("--help"))
    assert "Usage" in res.stdout
    for cmd in ("simulate", "register", "evaluate", "relations", "demo"):
        assert cmd in res.stdout


@pytest.mark.parametrize("cmd", ["simulate", "register", "evaluate", "relations", "demo"])
def test_command_help_shows_an_example(cmd):
    res = ok(dm(cmd, "--help"))
    assert "Usage" in res.stdout
    assert "Example" in res.stdout
    assert f"deepmapping {cmd} " in res.stdout  # an example command line


# ------------------------------------------------------------------------------------------
# 2. smoke: simulate, register (3 methods), evaluate, devices
# ------------------------------------------------------------------------------------------
def test_simulate_writes_authors_layout(data16):
    pcds = sorted(p.name for p in data16.glob("*.pcd"))
    assert pcds == [f"{i:03d}.pcd" for i in range(NUM_POSES)]
    assert (data16 / "map.png").stat().st_size > 0
    gt = read_gt_mat(data16 / "gt_pose.mat")
    assert gt.shape == (NUM_POSES, 3)
    pts = read_pcd(data16 / "000.pcd")
    assert pts.shape == (256, 3) and np.all(pts[:, 2] == 0)


COMMON_FILES = ("poses.npy", "poses.txt", "map.ply", "map.pcd", "poses_kitti.txt", "poses_tum.txt", "map.png", "config.yaml",
                "run.json", "metrics.json")
TRAINED_FILES = ("occupancy.png", "curves.png", "checkpoint.pt", "history.csv")


@pytest.mark.parametrize("method", ["icp-plane", "deepmapping", "direct"])
def test_register_writes_run_folder(runs, method):
    out, res = runs[method]
    ok(res)
    assert str(out) in res.stdout  # "results in OUT"
    expected = COMMON_FILES + (TRAINED_FILES if method != "icp-plane" else ())
    missing = [f for f in expected if not (out / f).is_file()]
    assert not missing, f"{method}: missing {missing}; have {sorted(p.name for p in out.iterdir())}"
    poses = np.load(out / "poses.npy")
    assert poses.shape == (NUM_POSES, 3) and np.isfinite(poses).all()
    np.testing.assert_allclose(np.loadtxt(out / "poses.txt"), poses)
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("ate", "point_distance", "success"):
        assert key in metrics, f"metrics.json lacks {key}: {metrics}"
    assert np.isfinite(metrics["ate"]) and metrics["ate"] >= 0
    info = json.loads((out / "run.json").read_text())
    assert info["method"] == method and info["num_scans"] == NUM_POSES
    # where the time went, per stage, and the peak memory: in run.json and printed
    stages = ("load_s", "registration_s" if method == "icp-plane" else "training_s", "write_s", "peak_rss_mb")
    assert all(info["timings"][k] > 0 for k in stages), info["timings"]
    assert "time: loading" in res.stdout and "peak memory" in res.stdout
    assert info["stop_reason"] == ""  # ran every epoch (no stopping rule in these runs)
    assert yaml.safe_load((out / "config.yaml").read_text())["method"] == method
    assert (out / "map.ply").read_bytes().startswith(b"ply")


def test_register_warm_start_none_is_the_cold_profile_with_its_curriculum(runs):
    out, res = runs["cold"]
    ok(res)
    missing = [f for f in COMMON_FILES + TRAINED_FILES if not (out / f).is_file()]
    assert not missing, missing
    cfg = yaml.safe_load((out / "config.yaml").read_text())
    assert cfg["profile"] == "cold" and cfg["warm_start"]["method"] == "none"
    assert cfg["curriculum"]["enabled"] == "on"
    history = np.genfromtxt(out / "history.csv", delimiter=",", names=True)
    assert (history["epoch"] == 0).sum() >= 2  # the curriculum's logs come before the first epoch
    assert np.all(np.diff(history["iteration"]) > 0)
    assert np.isfinite(json.loads((out / "metrics.json").read_text())["ate"])
    reviewed = json.loads((out / "run.json").read_text())["reviewed"]  # the scans the review moved
    assert isinstance(reviewed, list) and all(0 < i < NUM_POSES - 1 for i in reviewed)
    assert ("the review of the placements placed" in res.stdout) == bool(reviewed)


def test_register_no_plots_skips_pictures(runs):
    out, res = runs["deepmapping-again"]
    ok(res)
    assert (out / "poses.npy").is_file()
    assert not list(out.glob("*.png"))


def test_evaluate_prints_table_and_rewrites_metrics(runs, tmp_path):
    src, res = runs["icp-plane"]
    ok(res)
    out = tmp_path / "R1copy"  # a copy: other tests read the original run folder
    shutil.copytree(src, out)
    before = json.loads((out / "metrics.json").read_text())
    (out / "metrics.json").write_text("{}\n")
    ev = ok(dm("evaluate", out))
    assert "ATE" in ev.stdout + ev.stderr
    assert "icp-plane" in ev.stdout + ev.stderr
    after = json.loads((out / "metrics.json").read_text())
    for key in ("ate", "point_distance", "success"):
        assert key in after
    assert after["ate"] == pytest.approx(before["ate"], rel=1e-9, abs=1e-12)


def test_evaluate_not_a_run_folder(data16):
    assert_one_line_error(dm("evaluate", data16), str(data16))


def test_device_cuda_without_cuda_is_a_one_line_error(data16, tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("torch.cuda.is_available() is True: `--device cuda` is valid on this machine")
    out = tmp_path / "Rcuda"
    res = dm("register", data16, *TINY, "--device", "cuda", "--out", out)
    assert_one_line_error(res, "cuda", out)


def test_a_2d_only_map_on_3d_scans_is_a_one_line_error(data16, tmp_path):
    folder = tmp_path / "clouds"
    folder.mkdir()
    for i in range(3):  # the 2D excerpt lifted to 3D clouds (z = 0.1 i)
        xy = read_pcd(data16 / f"{i:03d}.pcd")[:, :2]
        np.save(folder / f"{i:03d}.npy", np.c_[xy, np.full(len(xy), 0.1 * i)].astype(np.float32))
    out = tmp_path / "Rgrid"
    res = dm("register", folder, *TINY, "--set", "mnet.kind=grid", "--out", out)
    assert_one_line_error(res, "mnet.kind", out)


# ------------------------------------------------------------------------------------------
# 3. reproducibility and saved config
# ------------------------------------------------------------------------------------------
def test_same_seed_gives_identical_poses(runs):
    (a, ra), (b, rb) = runs["deepmapping"], runs["deepmapping-again"]
    ok(ra), ok(rb)
    pa, pb = np.load(a / "poses.npy"), np.load(b / "poses.npy")
    assert np.array_equal(pa, pb), f"max difference {np.abs(pa - pb).max()}"


def test_config_yaml_reflects_overrides(runs):
    out, res = runs["deepmapping"]
    ok(res)
    cfg = yaml.safe_load((out / "config.yaml").read_text())
    assert cfg["method"] == "deepmapping"
    assert cfg["seed"] == RUN_SEED
    assert cfg["device"] == "cpu"
    assert cfg["optim"]["epochs"] == 3
    assert cfg["optim"]["eval_every"] == 1
    assert cfg["optim"]["lr"] == 0.002
    assert cfg["loss"]["free_samples"] == 2
    history = np.genfromtxt(out / "history.csv", delimiter=",", names=True)
    assert history["epoch"][-1] == 3


# ------------------------------------------------------------------------------------------
# 4. bad input: exit 2, one line naming the culprit, no traceback, no --out folder
# ------------------------------------------------------------------------------------------
def _authors_folder(src: Path, dst: Path, k: int = 4, gt_rows: int | None = None) -> Path:
    dst.mkdir(parents=True)
    for i in range(k):
        shutil.copy(src / f"{i:03d}.pcd", dst / f"{i:03d}.pcd")
    gt = read_gt_mat(src / "gt_pose.mat")
    write_gt_mat(dst / "gt_pose.mat", gt[: k if gt_rows is None else gt_rows])
    return dst


def _npy_folder(src: Path, dst: Path, k: int = 3) -> Path:
    dst.mkdir(parents=True)
    for i in range(k):
        np.save(dst / f"{i:03d}.npy", read_pcd(src / f"{i:03d}.pcd")[:, :2])
    return dst


def _build_bad_cases(src: Path, root: Path) -> dict[str, tuple[list, str]]:
    """{case: (register arguments without --out, text the error line must contain)}."""
    cases: dict[str, tuple[list, str]] = {}

    cases["missing-folder"] = ([root / "no_such_folder"], "no_such_folder")

    a_file = root / "lonely.pcd"
    shutil.copy(src / "000.pcd", a_file)
    cases["file-not-folder"] = ([a_file], "lonely.pcd")

    (root / "empty_dir").mkdir()
    cases["empty-folder"] = ([root / "empty_dir"], "empty_dir")

    unrelated = root / "unrelated_dir"
    unrelated.mkdir()
    (unrelated / "notes.txt").write_text("hello\n")
    (unrelated / "picture.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    (unrelated / "sub").mkdir()
    cases["unrelated-files"] = ([unrelated], "unrelated_dir")

    d = _authors_folder(src, root / "corrupt_pcd")
    (d / "002.pcd").write_bytes(bytes(range(256)) * 8)
    cases["corrupt-pcd"] = ([d], "002.pcd")

    d = _authors_folder(src, root / "truncated_pcd")
    raw = (d / "002.pcd").read_bytes()
    (d / "002.pcd").write_bytes(raw[: len(raw) - 500])
    cases["truncated-pcd"] = ([d], "002.pcd")

    d = _authors_folder(src, root / "all_zero")
    write_pcd(d / "001.pcd", np.zeros((256, 3), np.float32))
    cases["all-zero-scan"] = ([d], "001.pcd")

    d = _authors_folder(src, root / "nan_pcd")
    pts = read_pcd(d / "003.pcd")
    pts[10, 0] = np.nan
    write_pcd(d / "003.pcd", pts)
    cases["nan-pcd"] = ([d], "003.pcd")

    d = _npy_folder(src, root / "nan_npy")
    arr = np.load(d / "001.npy")
    arr[7, 1] = np.nan
    np.save(d / "001.npy", arr)
    cases["nan-npy"] = ([d], "001.npy")

    d = _npy_folder(src, root / "mixed_dims", k=2)
    xy = np.load(d / "001.npy")
    np.save(d / "001.npy", np.column_stack([xy, np.full(len(xy), 0.25, np.float32)]))
    cases["mixed-dimensions"] = ([d], "001.npy")

    d = _authors_folder(src, root / "count_mismatch", k=4, gt_rows=3)
    cases["pose-count-mismatch"] = ([d], "gt_pose.mat")

    d = _authors_folder(src, root / "one_scan", k=1)
    cases["one-scan"] = ([d], "one_scan")

    d = _authors_folder(src, root / "corrupt_mat")
    (d / "gt_pose.mat").write_bytes(b"MATLAB 5.0 MAT-file garbage" + bytes(range(200)))
    cases["corrupt-gt-mat"] = ([d], "gt_pose.mat")

    cases["unknown-method"] = ([src, "--method", "sgd-magic"], "method")
    cases["unknown-set-key"] = ([src, "--set", "optim.no_such_key=1"], "optim.no_such_key")

    init = root / "init_short.txt"
    np.savetxt(init, np.zeros((NUM_POSES - 1, 3)))
    cases["init-wrong-count"] = ([src, "--init", init, *TINY], "init_short.txt")
    return cases


BAD_CASES = [
    "missing-folder", "file-not-folder", "empty-folder", "unrelated-files", "corrupt-pcd", "truncated-pcd",
    "all-zero-scan", "nan-pcd", "nan-npy", "mixed-dimensions", "pose-count-mismatch", "one-scan",
    "corrupt-gt-mat", "unknown-method", "unknown-set-key", "init-wrong-count",
]


@pytest.fixture(scope="module")
def bad_results(tmp_path_factory, data16):
    def build(root: Path) -> dict:
        cases = _build_bad_cases(data16, root)
        assert sorted(cases) == sorted(BAD_CASES)
        outs = {name: root / f"out_{name}" for name in cases}
        results = dm_many({name: ["register", *args, "--out", outs[name]] for name, (args, _) in cases.items()})
        return {name: {"names": cases[name][1], "out": str(outs[name]), **_to_json(results[name])}
                for name in cases}

    built = _shared(tmp_path_factory, "bad", build)
    return {name: (_from_json(d), d["names"], Path(d["out"])) for name, d in built.items()}


@pytest.mark.parametrize("case", BAD_CASES)
def test_bad_input_is_a_one_line_error(bad_results, case):
    res, names, out = bad_results[case]
    assert_one_line_error(res, names, out)


# ------------------------------------------------------------------------------------------
# 5. Ctrl-C: checkpoint, exit 130, --resume finishes the run
# ------------------------------------------------------------------------------------------
CTRL_C_EPOCHS = 200  # ~3 s of training on one CPU thread for 16 scans
# a checkpoint every epoch: its first appearance says training has begun, and Ctrl-C is sent then


def test_ctrl_c_saves_checkpoint_and_resume_finishes(data16, tmp_path):
    out = tmp_path / "R"
    log_out, log_err = tmp_path / "stdout.txt", tmp_path / "stderr.txt"
    args = [DM, "register", str(data16), "--method", "deepmapping", "--seed", "3",
            "--set", f"optim.epochs={CTRL_C_EPOCHS}", "--set", "optim.eval_every=1",
            "--set", "optim.checkpoint_every_s=0", "--no-plots", "--out", str(out)]
    with open(log_out, "w") as fo, open(log_err, "w") as fe:
        t0 = time.monotonic()
        # SIGINT back to its default in the child: a test run started as a background job of a
        # non-interactive shell inherits SIGINT ignored, and Python then never raises KeyboardInterrupt
        proc = subprocess.Popen(args, stdout=fo, stderr=fe, env=ENV,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        try:
            deadline = t0 + 60
            while not (out / "checkpoint.pt").exists():
                assert proc.poll() is None, f"register exited ({proc.returncode}) before its first checkpoint:\n" \
                                            f"{log_err.read_text()}"
                assert time.monotonic() < deadline, "no checkpoint within 60 s"
                time.sleep(0.02)
            if proc.poll() is not None:
                pytest.fail(f"the run finished (exit {proc.returncode}) before Ctrl-C could be sent; "
                            f"raise CTRL_C_EPOCHS (now {CTRL_C_EPOCHS}) so the run takes longer")
            proc.send_signal(signal.SIGINT)
            rc = proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    err = log_err.read_text()
    assert rc == 130, f"exit {rc} after SIGINT, expected 130 (too early: before training?)\nstderr:\n{err}"
    assert "Traceback" not in err + log_out.read_text()
    assert "--resume" in err  # tells how to continue
    assert (out / "checkpoint.pt").is_file()
    assert not (out / "poses.npy").exists()

    import torch

    saved = torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=False)
    stopped_at = saved["epoch"]
    print(f"interrupted at epoch {stopped_at}")
    assert 0 < stopped_at < CTRL_C_EPOCHS, f"checkpoint at epoch {stopped_at}"

    res = ok(dm("register", data16, "--out", out, "--resume", "--no-plots"))
    assert str(out) in res.stdout
    poses = np.load(out / "poses.npy")
    assert poses.shape == (NUM_POSES, 3) and np.isfinite(poses).all()
    assert (out / "metrics.json").is_file()
    history = np.genfromtxt(out / "history.csv", delimiter=",", names=True)
    epochs = history["epoch"]
    assert epochs[0] == 0 and epochs[-1] == CTRL_C_EPOCHS
    assert np.all(np.diff(epochs) > 0), f"history does not continue: epochs {epochs.tolist()}"
    assert np.any((epochs > 0) & (epochs <= stopped_at)), "history lost the epochs before Ctrl-C"
    assert np.any(epochs > stopped_at)
    assert yaml.safe_load((out / "config.yaml").read_text())["optim"]["epochs"] == CTRL_C_EPOCHS


def test_ctrl_c_while_the_results_are_written_resumes_to_writing_them(data16, tmp_path, monkeypatch, capsys):
    from deepmapping.cli import register_cmd

    out = tmp_path / "R"
    cfg = register_cmd.build_config("default", None, "deepmapping", 5, None, None, None, 3, {})

    def ctrl_c(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(register_cmd, "write_run", ctrl_c)
    with pytest.raises(SystemExit) as exc:
        register_cmd.run_register(data16, out, cfg, None, None, resume=False, plots=False, quiet=True)
    assert exc.value.code == 130
    err = capsys.readouterr().err
    assert f"--out {out} --resume" in err, err  # on one line however long the path: copyable
    assert (out / "checkpoint.pt").is_file() and not (out / "poses.npy").exists()
    monkeypatch.undo()

    ok(dm("register", data16, "--out", out, "--resume", "--no-plots"))
    assert np.load(out / "poses.npy").shape == (NUM_POSES, 3)
    history = np.genfromtxt(out / "history.csv", delimiter=",", names=True)
    assert history["epoch"][-1] == 5


def test_experiment_command_runs_resumes_and_refuses_unknown_names(tmp_path):
    out = tmp_path / "exp1d"
    res = ok(dm("experiment", "1d", "--quick", "--out", out, "--jobs", "1", timeout=300))
    assert "report:" in res.stdout
    report = (out / "report.md").read_text()
    assert "![" in report and (out / "experiment.json").exists() and list((out / "runs").glob("*.json"))
    first = {p.name: p.stat().st_mtime_ns for p in (out / "runs").glob("*.json")}
    ok(dm("experiment", "1d", "--quick", "--out", out, "--jobs", "1", timeout=300))  # resumed: nothing redone
    assert {p.name: p.stat().st_mtime_ns for p in (out / "runs").glob("*.json")} == first
    bad = dm("experiment", "nope", "--out", tmp_path / "nope")
    assert_one_line_error(bad, "nope")
    assert not (tmp_path / "nope").exists()
    bad = dm("experiment", "1d", "--data", tmp_path, "--out", tmp_path / "nope")  # 1d simulates its data
    assert_one_line_error(bad, "reads no data folder")
    assert not (tmp_path / "nope").exists()
