"""The speed benchmark script: its time-to-accuracy rule, and a smoke run at toy size."""

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "speed_2d.py"
DATA = SCRIPT.parents[1] / "tests" / "data"  # excerpts of ../shared/data (tests/data/make_excerpts.py)


@pytest.fixture(scope="module")
def speed_2d():
    spec = importlib.util.spec_from_file_location("speed_2d", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_time_to_reach_counts_only_from_where_the_ate_stays_below(speed_2d):
    curve = [(1.0, 12.0), (2.0, 4.0), (3.0, 7.0), (4.0, 5.0), (5.0, 2.5), (6.0, 2.9)]
    assert speed_2d.time_to_reach(curve, 20.0) == 1.0
    assert speed_2d.time_to_reach(curve, 5.7) == 4.0  # dipped at 2 s, came back above at 3 s
    assert speed_2d.time_to_reach(curve, 3.0) == 5.0
    assert speed_2d.time_to_reach(curve, 1.0) is None
    assert speed_2d.time_to_reach(curve + [(7.0, 3.5)], 3.0) is None  # not below at the end


def test_summary_reports_median_worst_and_misses(speed_2d):
    runs = [{"ate": a, "point_distance": a, "wall_s": 10.0, "peak_rss_mb": 100.0 + a, "steps": 10, "epochs": 5,
             "train_s": 5.0, "curve": [(1.0, 30.0), (9.0, a)]} for a in (2.0, 4.0, 25.0)]
    s = speed_2d.summarize(runs)
    assert s["ate"] == (4.0, 25.0) and s["peak_rss_mb"] == (104.0, 125.0)
    assert s["t20"][2] == 2 and s["t20"][1] is None  # one trajectory never reached 20 px
    assert s["steps_per_s"] == 2.0 and s["epochs_per_min"] == 60.0
    assert speed_2d.fmt_time(s["t20"], 3) == "9.0 / never (2/3)"


def test_benchmark_smoke_run_writes_its_tables_and_figure(tmp_path):
    out = tmp_path / "bench"
    cmd = [sys.executable, str(SCRIPT), "--trajectories", "1", "--poses", "12", "--no-scaling", "--threads", "1",
           "--methods", "icp-plane", "deepmapping (default)", "--set", "optim.epochs=3", "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    data = json.loads((out / "results.json").read_text())
    dm = data["results"]["deepmapping (default)"][0]
    assert dm["num_scans"] == 12 and dm["epochs"] == 3 and dm["peak_rss_mb"] > 50
    assert len(dm["curve"]) >= 2 and all(t2 >= t1 for (t1, _), (t2, _) in zip(dm["curve"], dm["curve"][1:]))
    md = (out / "results.md").read_text()
    assert "| icp-plane |" in md and "| deepmapping (default) |" in md
    assert (out / "ate_vs_time.png").stat().st_size > 10_000
    assert (out / "runs" / "traj0" / "deepmapping_default" / "poses.npy").exists()


def test_avd_3d_benchmark_smoke_run(tmp_path):
    """benchmarks/avd_3d.py end to end at toy size: tables with the identity reference row."""
    script = SCRIPT.parent / "avd_3d.py"
    cmd = [sys.executable, str(script), "--trajectories", "1", "--frames", "4", "--jobs", "1",
           "--methods", "multiway,deepmapping", "--set", "optim.epochs=2", "--out", str(tmp_path)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    data = json.loads((tmp_path / "results.json").read_text())
    assert set(data["summary"]) == {"identity", "multiway", "deepmapping"}
    assert data["runs"]["deepmapping"][0]["num_scans"] == 4
    assert "| deepmapping |" in (tmp_path / "results.md").read_text()


def test_real_3d_benchmark_smoke_run(tmp_path):
    """benchmarks/real_3d.py on the 3DTK excerpt at toy size writes slam6D .frames per method."""
    cmd = [sys.executable, str(SCRIPT.parent / "real_3d.py"), "--only", "3dtk", "--max-points", "60", "--threads", "1",
           "--set", "optim.epochs=2", "--data", str(DATA), "--out", str(tmp_path)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads((tmp_path / "results.json").read_text())["3dtk"]
    assert set(report) == {"odometry", "icp-plane", "multiway", "deepmapping", "direct"}
    assert (tmp_path / "3dtk_frames" / "deepmapping" / "scan002.frames").is_file()


def test_carmen_benchmark_smoke_run(tmp_path):
    """benchmarks/carmen.py on the fr079 excerpt at toy density: the relations table, the reference
    reproduced (the excerpt's score, as in test_carmen; the full log's is 0.058 m)."""
    cmd = [sys.executable, str(SCRIPT.parent / "carmen.py"), "--logs", "fr079", "--methods",
           "reference,odometry,dm-odometry", "--keyframes", "every:60", "--threads", "1",
           "--set", "optim.epochs=2", "--data", str(DATA / "carmen"), "--out", str(tmp_path)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = json.loads((tmp_path / "results.json").read_text())["fr079"]
    assert set(rows) == {"reference", "odometry", "dm-odometry"}
    assert abs(rows["reference"]["relations"]["all"]["trans_mean_m"] - 0.0492) < 0.0015
    assert rows["odometry"]["relations"]["unmatched"] == 0 and rows["odometry"]["keyframes"] == 10
    assert rows["dm-odometry"]["peak_rss_mb"] > 0 and rows["dm-odometry"]["wall_s"] > 0
    assert "| dm-odometry | 10 |" in (tmp_path / "results.md").read_text()
