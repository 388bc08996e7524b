"""Faults survived, nothing lost, with real processes where the fault is a
process's fate: kill -9 then --resume, a full disk or read-only folder while writing results,
two commands on one folder, a sweep worker killed mid-run, a loss that turns NaN/inf.

Bit-identity is asserted only between runs on this machine with the same seed and threads
(resume equals an uninterrupted run by design); nothing else depends on the last bit.
"""

from __future__ import annotations

import errno
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from deepmapping.config import load_config

_SCRIPT = Path(sys.executable).parent / "deepmapping"
DM = str(_SCRIPT) if _SCRIPT.exists() else shutil.which("deepmapping")
# the runs killed in a subprocess take this process's thread count (conftest: 1, or
# DEEPMAPPING_TEST_THREADS), so that their resume here and the uninterrupted run here match bit for bit
THREADS = str(torch.get_num_threads())
ENV = dict(os.environ, OMP_NUM_THREADS=THREADS, MKL_NUM_THREADS=THREADS, PYTHONUNBUFFERED="1",
           PYTHONDONTWRITEBYTECODE="1")
needs_script = pytest.mark.skipif(DM is None, reason="the `deepmapping` console script is not installed")


@pytest.fixture(scope="module")
def scans16(indoor_map):
    """16 simulated scans of 128 beams with ground truth: training takes ~30 ms an epoch."""
    from deepmapping.sim.dataset import simulate

    return simulate(indoor_map, 16, seed=1, num_beams=128)


@pytest.fixture(scope="module")
def data16(tmp_path_factory, indoor_map, scans16) -> Path:
    """``scans16`` in the authors' layout."""
    from deepmapping.sim.dataset import write_authors_layout

    out = tmp_path_factory.mktemp("faults") / "data16"
    write_authors_layout(out, scans16, occ=indoor_map)
    return out


def cli(monkeypatch, capsys, *args) -> tuple[int, str, str]:
    """`deepmapping ARGS` in this process (cheap: torch is already imported): (exit code, stdout, stderr)."""
    from deepmapping.cli.main import main

    monkeypatch.setattr(sys, "argv", ["deepmapping", *map(str, args)])
    with pytest.raises(SystemExit) as exc:
        main()
    out, err = capsys.readouterr()
    return exc.value.code, out, err


def one_error_line(code, err: str) -> str:
    """Exit 2, no traceback, exactly one `error:` line (the last one on stderr); that line."""
    assert code == 2 and "Traceback" not in err, f"exit {code}\n{err}"
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and err.strip().splitlines()[-1] == errors[0], err
    return errors[0]


def temp_files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob("*") if p.name.endswith(".tmp") or ".tmp." in p.name)


def quick_cfg(**over):
    base = {"optim.epochs": 4, "optim.eval_every": 1, "warm_start.method": "icp-plane", "optim.mnet_warmup_epochs": 0}
    return load_config("default", overrides=base | over)


# ------------------------------------------------------------------------------------------
# 1. kill -9, then --resume: the final poses equal an uninterrupted run's, bit for bit
# ------------------------------------------------------------------------------------------
KILL_RUNS = {
    # warm start (ICP), killed between epochs
    "warm": ["--seed", "3", "--set", "optim.epochs=25", "--set", "optim.eval_every=5"],
    # cold start: killed while the curriculum places the scans (or just after)
    "cold": ["--seed", "3", "--warm-start", "none", "--set", "optim.epochs=4", "--set", "optim.eval_every=2",
             "--set", "curriculum.steps=10", "--set", "curriculum.hypotheses=8", "--set", "curriculum.log_every=1"],
    # two worker processes on one map (each worker's beam generator is in the checkpoint)
    "workers": ["--seed", "3", "--workers", "2", "--set", "optim.epochs=25", "--set", "optim.eval_every=5"],
}


def _killed_mid_run(data: Path, out: Path, args: list[str]) -> dict:
    """Start `register`, SIGKILL it (and any worker it started) once a checkpoint exists; the checkpoint it left."""
    cmd = [DM, "register", str(data), "--out", str(out), "--no-plots", "--device", "cpu",
           "--set", "optim.checkpoint_every_s=0", *args]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=ENV, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while not (out / "checkpoint.pt").exists():
            assert proc.poll() is None, f"register exited ({proc.returncode}) early:\n{proc.stderr.read().decode()}"
            assert time.monotonic() < deadline, "no checkpoint within 120 s"
            time.sleep(0.01)
        time.sleep(0.1)
        assert proc.poll() is None, "the run finished before it could be killed: make it longer"
        os.killpg(proc.pid, signal.SIGKILL)  # its own session: the process and its workers
        assert proc.wait(timeout=30) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
    assert not (out / "poses.npy").exists()
    return torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=False)


@needs_script
@pytest.mark.parametrize("kind", list(KILL_RUNS))
def test_kill_9_then_resume_gives_the_uninterrupted_poses_bit_for_bit(data16, tmp_path, monkeypatch, capsys, kind):
    """The run is killed in a process of its own; the resume runs here (no process start-up)."""
    from deepmapping.api import register
    from deepmapping.io.loaders import load_scans

    out = tmp_path / "run"
    saved = _killed_mid_run(data16, out, KILL_RUNS[kind])
    epochs = saved["config"]["optim"]["epochs"]
    assert saved["epoch"] < epochs and (saved["epoch"] > 0 or saved["placed"] > 0), "killed before any progress"
    code, _, err = cli(monkeypatch, capsys, "register", data16, "--out", out, "--resume", "--no-plots")
    assert code == 0, err

    # the uninterrupted run: the same config, here (same machine, one thread)
    full = register(load_scans(data16), load_config("default", out / "config.yaml"))
    resumed = np.load(out / "poses.npy")
    assert np.array_equal(resumed, full.poses), f"max difference {np.abs(resumed - full.poses).max()}"
    hist = np.genfromtxt(out / "history.csv", delimiter=",", names=True)
    for key in ("iteration", "epoch", "loss", "ate"):
        assert np.array_equal(hist[key], np.asarray(full.history[key], float), equal_nan=True), key


def test_ctrl_c_mid_epoch_saves_the_epoch_start_and_resume_is_bit_identical(scans16, tmp_path, monkeypatch):
    """Ctrl-C between two steps of an epoch: the checkpoint is the last whole epoch, not a half one."""
    from deepmapping.api import register
    from deepmapping.solver.trainer import Interrupted, Trainer

    cfg = quick_cfg(**{"optim.batch_size": 4})  # 4-5 steps per epoch
    full = register(scans16, cfg)
    step = Trainer.step

    def interrupted_step(self, idx, lr=None):
        if self.state.step == 11:  # in the third epoch
            raise KeyboardInterrupt
        return step(self, idx, lr)

    monkeypatch.setattr(Trainer, "step", interrupted_step)
    with pytest.raises(Interrupted):
        register(scans16, cfg, checkpoint=tmp_path / "c.pt")
    monkeypatch.undo()
    saved = torch.load(tmp_path / "c.pt", weights_only=False)
    assert saved["epoch"] == 2 and saved["step"] < 11
    resumed = register(scans16, cfg, checkpoint=tmp_path / "c.pt", resume=True)
    assert np.array_equal(resumed.poses, full.poses)
    assert np.array_equal(resumed.history["loss"], full.history["loss"], equal_nan=True)


def test_early_stop_after_a_resume_compares_with_the_same_poses_as_without(scans16, tmp_path, monkeypatch):
    """optim.early_stop_tol compares the poses with the last log's; a resumed run must too, not
    with the poses it resumed from (the reference is in the checkpoint)."""
    from deepmapping.api import register
    from deepmapping.solver.trainer import Trainer

    seen, log = {}, Trainer._log

    def spy(self, *args):
        seen[self.state.epoch] = poses = log(self, *args)
        return poses

    with monkeypatch.context() as m:  # how far the poses move, every epoch logged
        m.setattr(Trainer, "_log", spy)
        register(scans16, quick_cfg(**{"optim.epochs": 15}))

    def moved(a, b):
        return np.abs(seen[a][:, :2] - seen[b][:, :2]).max()

    # a tolerance the moves over 5 epochs exceed, the move over 1 epoch does not
    short, long = moved(9, 10), min(moved(0, 5), moved(5, 10))
    assert short < long, (short, long)
    cfg = quick_cfg(**{"optim.epochs": 15, "optim.eval_every": 5, "optim.early_stop_tol": float(np.sqrt(short * long))})
    full = register(scans16, cfg)

    def ctrl_c_at_9(epoch, total, loss):
        if epoch == 9:
            raise KeyboardInterrupt

    with pytest.raises(Exception, match="interrupted"):
        register(scans16, cfg, checkpoint=tmp_path / "c.pt", on_epoch=ctrl_c_at_9)
    resumed = register(scans16, cfg, checkpoint=tmp_path / "c.pt", resume=True)
    assert resumed.history["epoch"] == full.history["epoch"]
    assert np.array_equal(resumed.poses, full.poses)


# ------------------------------------------------------------------------------------------
# 2. a full disk or read-only folder while writing results
# ------------------------------------------------------------------------------------------
class _FailingDisk:
    """Stands in for ``os`` and ``tempfile`` inside deepmapping.io.atomic: the temp file of
    ``target`` takes half of its first write, then the write fails with ``err``."""

    def __init__(self, target: str, err: int):
        import tempfile

        self.target, self.err, self._tempfile, self.fds = target, err, tempfile, set()

    def __getattr__(self, name):
        return getattr(os, name)

    def mkstemp(self, prefix="", **kw):
        fd, path = self._tempfile.mkstemp(prefix=prefix, **kw)
        if prefix == f".{self.target}.":
            self.fds.add(fd)
        return fd, path

    def fdopen(self, fd, mode):
        f = os.fdopen(fd, mode)
        return _FailingFile(f, self.err) if fd in self.fds else f


class _FailingFile:
    def __init__(self, f, err):
        self.f, self.err = f, err

    def write(self, data):
        self.f.write(bytes(data)[: len(data) // 2])
        self.f.flush()
        raise OSError(self.err, os.strerror(self.err))

    def __getattr__(self, name):
        return getattr(self.f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()


@pytest.fixture(scope="module")
def earlier_run(data16, tmp_path_factory) -> Path:
    """A complete icp-plane run folder (the results a failed rerun must leave intact)."""
    from deepmapping.cli.register_cmd import build_config, run_register

    out = tmp_path_factory.mktemp("earlier") / "run"
    cfg = build_config("default", None, "icp-plane", None, None, None, None, None, {})
    run_register(data16, out, cfg, None, None, resume=False, quiet=True)
    return out


def _assert_intact(before: Path, after: Path, failed: str) -> None:
    """Every earlier file still there and whole; the one that failed to write is the earlier one."""
    assert temp_files(after) == [], "a temp file was left behind"
    names = {p.name for p in before.iterdir() if not p.name.startswith(".")}
    assert names <= {p.name for p in after.iterdir()}
    assert (after / failed).read_bytes() == (before / failed).read_bytes()
    assert np.load(after / "poses.npy").shape == (16, 3)
    for name in names:
        if name.endswith(".json"):
            json.loads((after / name).read_text())


@needs_script
@pytest.mark.parametrize("target, err", [("poses.npy", errno.ENOSPC), ("metrics.json", errno.EROFS),
                                         ("map.png", errno.EACCES)])
def test_a_failed_write_is_one_error_line_and_earlier_results_stay_whole(earlier_run, data16, tmp_path, monkeypatch,
                                                                         capsys, target, err):
    from deepmapping.io import atomic

    out = tmp_path / "run"
    shutil.copytree(earlier_run, out)
    disk = _FailingDisk(target, err)
    monkeypatch.setattr(atomic, "os", disk)
    monkeypatch.setattr(atomic, "tempfile", disk)
    code, _, stderr = cli(monkeypatch, capsys, "register", data16, "--method", "icp-plane", "--out", out)
    line = one_error_line(code, stderr)
    assert line == f"error: {out / target}: cannot write ({os.strerror(err)})"
    _assert_intact(earlier_run, out, target)


@needs_script
def test_a_real_write_limit_fails_cleanly(earlier_run, data16, tmp_path):
    """A real OS limit, as root too: RLIMIT_FSIZE makes writes past 16 KiB fail (EFBIG), like a
    full disk, for map.ply (the first file that large)."""
    out = tmp_path / "run"
    shutil.copytree(earlier_run, out)

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of being killed
        resource.setrlimit(resource.RLIMIT_FSIZE, (16384, 16384))

    res = subprocess.run([DM, "register", str(data16), "--method", "icp-plane", "--out", str(out)],
                         capture_output=True, text=True, env=ENV, timeout=120, preexec_fn=limit)
    line = one_error_line(res.returncode, res.stderr)
    assert line == f"error: {out / 'map.ply'}: cannot write ({os.strerror(errno.EFBIG)})"
    _assert_intact(earlier_run, out, "map.ply")


@pytest.mark.parametrize("where, message", [("/dev/full", "exists and is not a folder"),
                                            ("FILE/run", "cannot create the folder (Not a directory)")])
def test_an_out_folder_that_cannot_be_made_is_one_error_line(data16, tmp_path, monkeypatch, capsys, where, message):
    (tmp_path / "FILE").write_text("a file, not a folder\n")
    out = Path(where) if where.startswith("/") else tmp_path / where
    if not out.parent.exists():
        pytest.skip(f"{out.parent} does not exist on this system")
    code, _, stderr = cli(monkeypatch, capsys, "register", data16, "--method", "icp-plane", "--out", out)
    assert one_error_line(code, stderr) == f"error: {out}: {message}"


def test_a_failed_checkpoint_write_keeps_the_previous_checkpoint(scans16, tmp_path, monkeypatch):
    """Disk full during training: OutputError naming checkpoint.pt; the previous one resumes."""
    from deepmapping.api import register
    from deepmapping.errors import OutputError
    from deepmapping.io import atomic
    from deepmapping.solver import checkpoint as ckpt

    cfg = quick_cfg(**{"optim.checkpoint_every_s": 0})
    path = tmp_path / "checkpoint.pt"
    write, writes = ckpt.write, []

    def write_then_fill_the_disk(p, data):
        writes.append(data["epoch"])
        if len(writes) == 3:
            disk = _FailingDisk("checkpoint.pt", errno.ENOSPC)
            monkeypatch.setattr(atomic, "os", disk)
            monkeypatch.setattr(atomic, "tempfile", disk)
        write(p, data)

    monkeypatch.setattr(ckpt, "write", write_then_fill_the_disk)
    with pytest.raises(OutputError, match=f"{path}: cannot write \\(No space left on device\\)"):
        register(scans16, cfg, checkpoint=path)
    monkeypatch.undo()
    assert temp_files(tmp_path) == []
    assert torch.load(path, weights_only=False)["epoch"] == writes[1]
    assert np.isfinite(register(scans16, cfg, checkpoint=path, resume=True).poses).all()


# ------------------------------------------------------------------------------------------
# 3. two commands on one folder: the second refuses (a lock the kernel drops with its process)
# ------------------------------------------------------------------------------------------
HOLD = ("import sys, time\nfrom deepmapping.io.lock import folder_lock\n"
        "with folder_lock(sys.argv[1]):\n    print('locked', flush=True)\n    time.sleep(120)\n")


@pytest.fixture
def held(tmp_path):
    """A folder whose lock another process holds; yields (folder, holder process)."""
    out = tmp_path / "busy"
    out.mkdir()
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdout=subprocess.PIPE, text=True, env=ENV)
    try:
        assert proc.stdout.readline().strip() == "locked"
        yield out, proc
    finally:
        proc.kill()
        proc.wait()
        proc.stdout.close()


@needs_script
def test_a_second_register_on_a_busy_folder_refuses_and_kill_9_leaves_no_stale_lock(data16, held):
    from deepmapping.io.lock import folder_lock

    out, holder = held
    res = subprocess.run([DM, "register", str(data16), "--method", "icp-plane", "--out", str(out)],
                         capture_output=True, text=True, env=ENV, timeout=120)
    line = one_error_line(res.returncode, res.stderr)
    assert line == (f"error: {out}: another deepmapping command is using this folder (pid {holder.pid}); "
                    f"wait for it to finish or choose another --out")
    assert [p.name for p in out.iterdir()] == [".deepmapping.lock"]  # nothing written
    holder.send_signal(signal.SIGKILL)
    holder.wait()
    with folder_lock(out):  # the kernel dropped the dead process's lock
        pass


def test_an_experiment_on_a_busy_folder_refuses(held):
    from deepmapping.errors import FolderBusy
    from deepmapping.experiments.runner import run_experiment

    out, holder = held
    with pytest.raises(FolderBusy, match=f"another deepmapping command is using this folder \\(pid {holder.pid}\\)"):
        run_experiment("1d", out, quick=True, workers=1)
    assert not (out / "runs").exists()


# ------------------------------------------------------------------------------------------
# 4. a sweep worker killed mid-run
# ------------------------------------------------------------------------------------------
ECHO = "deepmapping.experiments.probe:echo"


def test_a_killed_sweep_worker_fails_only_its_run_and_a_restart_redoes_only_that(tmp_path):
    """The worker running "doomed" SIGKILLs itself, on the first try and on the retry (in a fresh
    worker): "doomed" is reported; the other runs never notice; a restart runs only "doomed"."""
    from deepmapping.experiments.base import Job
    from deepmapping.experiments.sweep import result_path, run_sweep

    calls = tmp_path / "doomed.calls"
    jobs = [Job(f"run-{i}", ECHO, {"value": float(i)}) for i in range(3)]
    jobs.insert(1, Job("doomed", ECHO, {"value": 7.0, "die_times": 2, "marker": str(calls)}))
    out = tmp_path / "sweep"
    results, errors = run_sweep(jobs, out, workers=2, retries=1)
    assert sorted(results) == ["run-0", "run-1", "run-2"]
    assert errors == {"doomed": "RuntimeError: worker died (signal 9) while running doomed"}
    assert calls.read_text() == "2"
    assert "worker died (signal 9)" in json.loads(result_path(out, "doomed", failed=True).read_text())["traceback"]
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "runs").glob("run-*.json")}
    results, errors = run_sweep(jobs, out, workers=2, retries=1)  # the restart
    assert errors == {} and results["doomed"]["square"] == 49.0 and calls.read_text() == "3"
    assert {p.name: p.stat().st_mtime_ns for p in (out / "runs").glob("run-*.json")} == stamps  # not redone
    assert not result_path(out, "doomed", failed=True).exists()


# ------------------------------------------------------------------------------------------
# 5. a loss that turns NaN/inf: rolled back to the last good state with a lower learning rate
# ------------------------------------------------------------------------------------------
def _poison(monkeypatch, at_steps, kind="nan"):
    """Trainer.loss returns a non-finite eq. 4 term (or a finite one with NaN gradients) at the given
    steps, the first time each is reached."""
    from deepmapping.solver.trainer import Trainer

    loss, pending = Trainer.loss, set(at_steps)

    def poisoned(self, idx, own=None):
        bce, ch, odo = loss(self, idx, own)  # (eq. 4, eq. 7, odometry factor): the step adds them
        if self.state.step in pending or at_steps == "all":
            pending.discard(self.state.step)
            if kind == "gradient":  # value unchanged, d/dx sqrt(x) at 0 = inf -> NaN gradients
                bce = bce + 0.0 * torch.sqrt(bce - bce.detach())
            else:
                bce = bce * float(kind)
        return bce, ch, odo

    monkeypatch.setattr(Trainer, "loss", poisoned)


@pytest.mark.parametrize("kind", ["nan", "inf", "gradient"])
def test_a_non_finite_step_is_rolled_back_with_half_the_learning_rate(scans16, monkeypatch, kind):
    from deepmapping.api import register

    _poison(monkeypatch, {6}, kind)
    res = register(scans16, quick_cfg(**{"optim.batch_size": 8}))  # 2-3 steps per epoch
    assert np.isfinite(res.poses).all()
    (event,) = res.history["rollbacks"]
    epoch_of_step_6 = sum(it <= 6 for it in res.history["iteration"][1:])  # epochs that ended before it
    # a NaN gradient shows in the next step's loss, or in the weights at the epoch's end
    step = 7 if kind == "gradient" else 6
    assert (event["epoch"], event["step"], event["lr_scale"]) == (epoch_of_step_6, step, 0.5)
    if kind != "gradient":
        assert event["what"] == f"loss is {kind}"
    assert res.history["epoch"] == [0, 1, 2, 3, 4]  # the epoch was redone once, logged once


def test_a_non_finite_step_in_the_cold_start_curriculum_is_rolled_back(scans16, monkeypatch):
    from deepmapping.api import register

    cfg = quick_cfg(**{"warm_start.method": "none", "curriculum.enabled": "on", "curriculum.chunk": 8,
                       "curriculum.steps": 4, "curriculum.hypotheses": 4, "curriculum.rounds": 1,
                       "optim.epochs": 1})
    _poison(monkeypatch, {5})  # the second stage
    res = register(scans16, cfg)
    assert np.isfinite(res.poses).all()
    assert [(e["epoch"], e["step"]) for e in res.history["rollbacks"]] == [(0, 5)]


def test_a_loss_that_stays_nan_fails_with_one_clear_error(scans16, monkeypatch):
    from deepmapping.api import register
    from deepmapping.errors import TrainingError
    from deepmapping.solver.trainer import MAX_ROLLBACKS

    _poison(monkeypatch, "all")
    with pytest.raises(TrainingError, match=f"training diverged: the loss is nan at epoch 0 .* after {MAX_ROLLBACKS} "
                                            "rollbacks") as exc:
        register(scans16, quick_cfg())
    assert "\n" not in str(exc.value) and "lower optim.lr" in str(exc.value)


def test_the_cli_reports_a_rollback_in_its_final_message_and_run_json(data16, tmp_path, monkeypatch, capsys):
    _poison(monkeypatch, {2})
    out = tmp_path / "run"
    code, stdout, stderr = cli(monkeypatch, capsys, "register", data16, "--out", out, "--epochs", "3",
                               "--set", "optim.batch_size=8", "--no-plots")
    assert code == 0, stderr
    assert "note: the loss is nan at epoch " in stdout and "(step 2)" in stdout
    assert "1 rollback(s), now 0.5 x the set ones" in stdout
    assert [e["step"] for e in json.loads((out / "run.json").read_text())["rollbacks"]] == [2]
    assert np.isfinite(np.load(out / "poses.npy")).all()
