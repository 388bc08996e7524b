"""CARMEN logs, keyframes, a pose for every scan, and the Kümmerle et al. relations metric."""

import bz2
import gzip
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from deepmapping.cli.main import app
from deepmapping.errors import ConfigError, InputError
from deepmapping.evaluation.relations import Relations, derive_relations, read_relations, score_relations
from deepmapping.geometry import se2
from deepmapping.io.carmen import match_scans, read_carmen
from deepmapping.io.loaders import detect_format, load_scans
from deepmapping.io.poses3d import read_tum_poses, write_tum_poses
from deepmapping.io.relations import relations_from_corrected, write_relations
from deepmapping.sequence import nearest_keyframe, poses_for_all_scans, select_keyframes

CARMEN = Path(__file__).resolve().parent / "data" / "carmen"  # excerpts (tests/data/make_excerpts.py)


def _flaser(ranges, pose, t):
    r = " ".join(f"{v:.2f}" for v in ranges)
    p = " ".join(f"{v:.6f}" for v in pose)
    return f"FLASER {len(ranges)} {r} {p} {p} {t} nohost {t}"


def _log_lines(n=6, beams=5):
    lines = ["# CARMEN log", "PARAM robot_frontlaser_offset 0.0 nohost 0",
             "ODOM 0.0 0.0 0.0 0 0 0 100.000000 nohost 0.0"]
    for k in range(n):
        ranges = [1.0 + 0.1 * k] * beams
        ranges[0] = 81.9  # no return
        lines.append(_flaser(ranges, (0.3 * k, 0.0, 0.1 * k), f"{100 + k}.{k:06d}"))
    return lines


def _write(path: Path, lines):
    data = "\n".join(lines) + "\n"
    if path.suffix == ".gz":
        path.write_bytes(gzip.compress(data.encode()))
    elif path.suffix == ".bz2":
        path.write_bytes(bz2.compress(data.encode()))
    else:
        path.write_text(data)
    return path


@pytest.mark.parametrize("name", ["a.clf", "a.log.gz", "a.clf.bz2"])
def test_read_flaser_plain_and_packed(tmp_path, name):
    log = read_carmen(_write(tmp_path / name, _log_lines()))
    assert log.message == "FLASER" and log.ranges.shape == (6, 5)
    np.testing.assert_allclose(np.degrees(log.angles[0, [0, 2, 4]]), [-90, 0, 90])
    assert log.stamps[3] == "103.000003" and log.timestamps[3] == pytest.approx(103.000003)
    valid = log.valid()
    assert not valid[:, 0].any() and valid[:, 1:].all()  # a range at the maximum is no return
    pts = log.points()
    np.testing.assert_allclose(pts[0, 0], [0, 0])
    np.testing.assert_allclose(pts[1, 2], [1.1, 0.0], atol=1e-12)  # beam ahead
    np.testing.assert_allclose(log.poses[2], [0.6, 0.0, 0.2])
    assert list(log.lines[:2]) == [4, 5]
    assert detect_format(tmp_path / name) == "carmen"


def test_flaser_no_return_code_found_in_the_log(tmp_path):
    """A FLASER log whose largest reading repeats (intel writes 81.83 m for no return): those
    readings are no return too; a log without such a repeated top value keeps every reading."""
    rng = np.random.default_rng(0)
    lines = []
    for k in range(20):
        ranges = rng.uniform(0.5, 6.0, 30)
        ranges[rng.random(30) < 0.1] = 81.83
        ranges[0] = 81.83
        lines.append(_flaser(ranges, (0.1 * k, 0.0, 0.0), f"{100 + k}.000000"))
    log = read_carmen(_write(tmp_path / "code.clf", lines))
    assert log.max_range == pytest.approx(81.83)
    assert not log.valid()[log.ranges > 81].any() and log.valid()[log.ranges < 7].all()
    assert np.abs(log.points()).max() < 7
    rare = [_flaser([1.0 + 0.01 * k, 2.0, 30.0 + k], (0, 0, 0), f"{100 + k}.000000") for k in range(20)]
    assert read_carmen(_write(tmp_path / "rare.clf", rare)).valid().all()  # the top value once: a reading
    flat = [_flaser([2.0] * 5, (0, 0, 0), f"{100 + k}.000000") for k in range(20)]
    assert read_carmen(_write(tmp_path / "flat.clf", flat)).valid().all()  # every reading alike: readings


def test_intel_excerpt_no_return_readings_masked():
    log = read_carmen(CARMEN / "intel.clf.gz")
    far = log.ranges > 80
    assert far.sum() > 100 and not log.valid()[far].any()  # 81.83 m: the intel log's no return
    assert np.hypot(*log.points().transpose(2, 0, 1)).max() < 60


def test_read_robotlaser_with_interleaved_layouts(tmp_path):
    def line(start, n, t):
        ranges = " ".join(["2.00"] * n)
        return (f"ROBOTLASER1 0 {start} 3.141593 {3.141593 / (n - 1):.6f} 81.9 0.01 0 {n} {ranges} 2 5 6 "
                f"1.0 2.0 0.5 0.9 2.0 0.5 0 0 0.1 0.1 0 {t} host {t}")
    log = read_carmen(_write(tmp_path / "r.clf", [line(-1.570796, 5, "1.5"), line(-1.5, 4, "2.5")]))
    assert log.message == "ROBOTLASER1" and log.ranges.shape == (2, 5)
    np.testing.assert_allclose(log.poses[1], [1.0, 2.0, 0.5])
    np.testing.assert_allclose(log.odometry[1], [0.9, 2.0, 0.5])
    assert log.valid()[0].all() and log.valid()[1].tolist() == [True] * 4 + [False]  # padded beam
    assert log.stamps == ["1.5", "2.5"]


def test_bad_logs(tmp_path):
    with pytest.raises(InputError, match="missing.clf: file not found"):
        read_carmen(tmp_path / "missing.clf")
    with pytest.raises(InputError, match="no FLASER or ROBOTLASER1"):
        read_carmen(_write(tmp_path / "odom.clf", ["ODOM 0 0 0 0 0 0 1.0 h 1.0"]))
    lines = _log_lines()
    lines[5] = lines[5].replace("1.20", "x1.2")
    with pytest.raises(InputError, match=r"bad.clf:6: malformed FLASER line"):
        read_carmen(_write(tmp_path / "bad.clf", lines))
    with pytest.raises(InputError, match=r"short.clf:4: malformed FLASER"):
        read_carmen(_write(tmp_path / "short.clf", _log_lines()[:3] + ["FLASER 5 1 2 3"]))
    lines = _log_lines()
    lines[3] = lines[3].replace("0.000000 0.000000 0.000000", "nan 0.000000 0.000000", 1)
    with pytest.raises(InputError, match=r"nan.clf:4: NaN or inf"):
        read_carmen(_write(tmp_path / "nan.clf", lines))
    (tmp_path / "corrupt.clf.gz").write_bytes(b"not gzip at all")
    with pytest.raises(InputError, match="corrupt.clf.gz: cannot read log"):
        read_carmen(tmp_path / "corrupt.clf.gz")


def test_keyframe_selection():
    odom = np.array([[0.1 * k, 0.0, 0.0] for k in range(10)] + [[0.9, 0.0, np.radians(20 * k)] for k in range(1, 4)])
    t = np.arange(len(odom), dtype=float)
    assert select_keyframes("all", odom, t).tolist() == list(range(13))
    assert select_keyframes("every:4", odom, t).tolist() == [0, 4, 8, 12]
    assert select_keyframes("motion:0.35,30", odom, t).tolist() == [0, 4, 8, 11]  # 0.4 m, 0.4 m, 40 deg
    assert select_keyframes("time:5", odom, t).tolist() == [0, 5, 10]
    for bad in ("every:0", "every:1.5", "motion:1", "time", "sometimes", "time:-1"):
        with pytest.raises(ConfigError, match="keyframes must be"):
            select_keyframes(bad, odom, t)


def test_every_scan_gets_a_pose():
    rng = np.random.default_rng(0)
    odom = se2.chain(rng.normal([0.2, 0.0, 0.05], 0.05, (29, 3)))
    t = np.arange(30) * 0.5
    kf = np.array([0, 7, 15, 22])
    np.testing.assert_array_equal(nearest_keyframe(kf, t)[[0, 3, 4, 11, 12, 29]], [0, 0, 1, 1, 2, 3])
    # keyframe poses = the odometry moved rigidly: every scan must be that same rigid move
    g = np.array([3.0, -1.0, 0.7])
    allp = poses_for_all_scans(kf, se2.compose(g, odom[kf]), odom, t)
    np.testing.assert_allclose(allp, se2.compose(g, odom), atol=1e-12)
    # a corrected keyframe carries its correction to its neighbours only
    kp = odom[kf].copy()
    kp[1, 0] += 1.0
    allp = poses_for_all_scans(kf, kp, odom, t)
    moved = np.flatnonzero(np.abs(allp - odom).max(axis=1) > 1e-9)
    assert moved.tolist() == list(range(4, 12))


def test_relations_metric():
    rng = np.random.default_rng(1)
    poses = se2.chain(rng.normal([0.3, 0.0, 0.1], 0.1, (9, 3)))
    stamps = [f"{10 + 3 * k}.000000" for k in range(10)]
    pairs = [(0, 1), (2, 3), (0, 9), (4, 8)]
    rel = Relations([stamps[i] for i, _ in pairs], [stamps[j] for _, j in pairs],
                    np.array([se2.relative(poses[i], poses[j]) for i, j in pairs]))
    s = score_relations(rel, stamps, poses)
    assert s["unmatched"] == 0 and s["all"]["count"] == 4 and s["all"]["trans_mean_m"] < 1e-12
    assert s["short"]["count"] == 2 and s["long"]["count"] == 2  # 3 s apart vs 27 s / 12 s
    # a rigid move of the whole trajectory changes nothing; a 0.5 m jump of scan 9 shows once
    moved = se2.compose(np.array([5.0, 1.0, 2.0]), poses)
    assert score_relations(rel, stamps, moved)["all"]["trans_mean_m"] < 1e-9
    moved[9] = se2.compose(moved[9], np.array([0.5, 0.0, 0.0]))
    s = score_relations(rel, stamps, moved)
    assert s["all"]["trans_median_m"] < 1e-9 and s["long"]["trans_mean_m"] == pytest.approx(0.25)
    # exact matching: a timestamp written differently is not the same scan, and is counted
    s = score_relations(rel, [t.rstrip("0") for t in stamps], poses)
    assert s["unmatched"] == 4 and s["all"] == {"count": 0}


def test_read_relations_errors(tmp_path):
    p = tmp_path / "x.relations"
    p.write_text("1.0 2.0 0.1 0 0 0 0 0.2\n\n# note\n3.0 4.0 0.1 0 0 0 0\n")
    with pytest.raises(InputError, match=r"x.relations:4: a relation has 8 fields"):
        read_relations(p)
    p.write_text("1.0 2.0 0.1 0 0 0 0 0.2\n")
    r = read_relations(p)
    assert r.stamp_i == ["1.0"] and r.motion.tolist() == [[0.1, 0.0, 0.2]]
    with pytest.raises(InputError, match="file not found"):
        read_relations(tmp_path / "none.relations")


def test_tum_writes_log_stamps_exactly(tmp_path):
    poses = se2.to_se3(np.array([[0.1, 0.2, 0.3], [1.0, -2.0, 3.1]]))
    write_tum_poses(tmp_path / "t.txt", poses, ["976052857.337530", "976052857.537530"])
    rows = (tmp_path / "t.txt").read_text().splitlines()[1:]
    assert [r.split()[0] for r in rows] == ["976052857.337530", "976052857.537530"]
    np.testing.assert_allclose(read_tum_poses(tmp_path / "t.txt"), poses, atol=1e-15)


def test_corrected_fr079_reproduces_the_reference_score():
    """The corrected fr079 log scored on its relations (shared/README: 0.058 m / 0.70 deg on 1672
    of 1685; benchmarks/carmen.py checks that on the full log). On the excerpt (raw scans
    1000-1599, 573 of them in the corrected log): 0.049 m / 0.86 deg on 144 of 146 relations."""
    raw = read_carmen(CARMEN / "fr079.clf.gz")
    ref = read_carmen(CARMEN / "corrected" / "freiburg-079-corrected.log.gz")
    idx = match_scans(ref, raw)
    assert raw.num_scans == 600 and ref.num_scans == 573
    assert (idx >= 0).all() and len(set(idx)) == ref.num_scans
    s = score_relations(read_relations(CARMEN / "fr079.relations"), [raw.stamps[k] for k in idx], ref.poses)
    assert s["relations"] == 146 and s["unmatched"] == 2
    assert s["all"]["trans_mean_m"] == pytest.approx(0.0492, abs=0.0015)
    assert s["all"]["rot_mean_deg"] == pytest.approx(0.863, abs=0.015)
    odo = score_relations(read_relations(CARMEN / "fr079.relations"), raw.stamps, raw.poses)
    assert odo["unmatched"] == 0 and odo["all"]["trans_mean_m"] == pytest.approx(1.06, abs=0.05)  # raw odometry


@pytest.fixture(scope="module")
def intel_excerpt():
    """120 scans of the intel log (scans 300-419, 7 m of motion; gzip) and the relations between them."""
    path = CARMEN / "intel.clf.gz"
    return path, len(read_relations(CARMEN / "intel.relations").stamp_i)


def test_loader_keyframes_and_relations(intel_excerpt):
    path, nrel = intel_excerpt
    assert nrel > 5
    scans = load_scans(path, keyframes="every:10")
    assert scans.num_scans == 12 and scans.points.shape == (12, 180, 2) and scans.unit == "m"
    assert scans.sequence.keyframes.tolist() == list(range(0, 120, 10))
    assert scans.sequence.relations_path.endswith("intel.relations") and len(scans.sequence.stamps) == 120
    np.testing.assert_allclose(scans.init_poses, scans.sequence.odometry[::10])
    with pytest.raises(ConfigError, match="keyframes apply to log formats"):
        load_scans(CARMEN.parent / "bunny", keyframes="every:2")
    with pytest.raises(ConfigError, match="carries its own poses"):
        load_scans(path, gt_path=path)


def test_cli_register_log_writes_every_scan(intel_excerpt, tmp_path):
    path, nrel = intel_excerpt
    out = tmp_path / "run"
    res = CliRunner().invoke(app, ["register", str(path), "--method", "icp-point", "--warm-start", "file",
                                   "--keyframes", "motion:0.2,10", "--out", str(out), "--no-plots"])
    assert res.exit_code == 0, res.output
    assert "Relations" in res.output
    tum = (out / "all_scans_tum.txt").read_text().splitlines()[1:]
    assert len(tum) == 120 and tum[0].split()[0] == read_carmen(path).stamps[0]
    kf = [int(v) for v in (out / "keyframes.txt").read_text().split()]
    assert kf[0] == 0 and len(kf) == len(np.load(out / "poses.npy"))
    m = json.loads((out / "metrics.json").read_text())["relations"]
    assert m["relations"] == nrel and m["unmatched"] == 0 and m["all"]["trans_median_m"] < 0.2
    res = CliRunner().invoke(app, ["evaluate", str(out)])
    assert res.exit_code == 0, res.output
    assert json.loads((out / "metrics.json").read_text())["relations"] == m


def test_derive_relations_like_the_benchmark():
    """Pairs at most near_m apart, 40 % of them over 10 s when there are enough, sorted in time;
    the trajectory they come from scores 0 on them, a moved scan does not."""
    rng = np.random.default_rng(3)
    t = np.arange(400) * 0.5  # a loop of 200 s driven twice: positions repeat after 100 s
    ang = 2 * np.pi * t / 100.0
    poses = np.c_[5 * np.cos(ang), 5 * np.sin(ang), ang + np.pi / 2] + rng.normal(0, 0.01, (400, 3))
    stamps = [f"{v:.6f}" for v in 1000.0 + t]
    rel = derive_relations(stamps, poses, near_m=1.0, count=500, seed=0)
    assert len(rel) == 500 and (rel.span_s() > 10).sum() == 200
    i = np.array([stamps.index(s) for s in rel.stamp_i])
    j = np.array([stamps.index(s) for s in rel.stamp_j])
    assert (t[j] >= t[i]).all() and (np.linalg.norm(poses[i, :2] - poses[j, :2], axis=1) <= 1.0).all()
    assert score_relations(rel, stamps, poses)["all"]["trans_mean_m"] < 1e-9
    moved = poses.copy()
    moved[250:, 0] += 0.3
    s = score_relations(rel, stamps, moved)
    assert s["long"]["trans_mean_m"] > 0.05 and s["unmatched"] == 0
    again = derive_relations(stamps, poses, near_m=1.0, count=500, seed=0)
    assert again.stamp_i == rel.stamp_i and again.stamp_j == rel.stamp_j
    few = derive_relations(stamps[:30], poses[:30], near_m=1.0, count=500)  # 15 s: few long pairs, all kept
    assert 0 < len(few) < 500
    with pytest.raises(InputError, match="timestamps for"):
        derive_relations(stamps[:3], poses[:2])


def test_relations_from_a_corrected_log_scored_with_gt(tmp_path):
    """The fr079 excerpt's corrected log: relations at the raw log's timestamps, written in the
    benchmark's format, read back, and taken by register/evaluate as --gt FILE.relations."""
    rel = relations_from_corrected(CARMEN / "corrected" / "freiburg-079-corrected.log.gz", CARMEN / "fr079.clf.gz")
    raw = read_carmen(CARMEN / "fr079.clf.gz")
    assert 1000 <= len(rel) <= 3000 and set(rel.stamp_i) <= set(raw.stamps)
    path = tmp_path / "fr079-derived.relations"
    write_relations(path, rel)
    back = read_relations(path)
    assert back.stamp_i == rel.stamp_i and np.abs(back.motion - rel.motion).max() < 1e-6
    odo = score_relations(back, raw.stamps, raw.poses)
    assert odo["unmatched"] == 0 and odo["all"]["trans_mean_m"] > 0.1  # raw odometry is off on them
    scans = load_scans(CARMEN / "fr079.clf.gz", gt_path=path, keyframes="every:20")
    assert scans.sequence.relations_path == str(path)
    with pytest.raises(InputError, match="none.relations: file not found"):
        load_scans(CARMEN / "fr079.clf.gz", gt_path=tmp_path / "none.relations")
    with pytest.raises(InputError, match="scans found in"):
        relations_from_corrected(CARMEN / "corrected" / "freiburg-079-corrected.log.gz", CARMEN / "intel.clf.gz")


def test_cli_relations_then_register_scores_on_them(tmp_path):
    corrected, log = CARMEN / "corrected" / "freiburg-079-corrected.log.gz", CARMEN / "fr079.clf.gz"
    rel = tmp_path / "fr079-derived.relations"
    res = CliRunner().invoke(app, ["relations", str(corrected), str(log), "--out", str(rel), "--count", "500"])
    assert res.exit_code == 0, res.output
    assert f"500 relations (200 over 10 s) written to {rel}" in " ".join(res.output.split())
    out = tmp_path / "run"
    res = CliRunner().invoke(app, ["register", str(log), "--gt", str(rel), "--method", "icp-point", "--warm-start",
                                   "file", "--keyframes", "every:20", "--out", str(out), "--no-plots"])
    assert res.exit_code == 0, res.output
    m = json.loads((out / "metrics.json").read_text())
    assert m["relations"]["relations"] == 500 and m["relations"]["unmatched"] == 0
    assert m["relations_file"] == str(rel)
    bad = CliRunner().invoke(app, ["relations", str(corrected), str(CARMEN / "intel.clf.gz"), "--out",
                                   str(tmp_path / "x.relations")])
    # (the console script prints InputError as one line, exit 2: tests/test_cli.py)
    assert isinstance(bad.exception, InputError) and "scans found in" in str(bad.exception)
    assert not (tmp_path / "x.relations").exists()


def test_a_classical_method_on_a_log_starts_from_its_odometry():
    """``register LOG --method loop-closure`` (or icp-*) starts from the log's odometry, as the experiment's
    rows (warm start "file") and the warm start do; ``--warm-start none`` from the identity."""
    from deepmapping.api import register
    from deepmapping.config import load_config

    scans = load_scans(CARMEN / "fr079.clf.gz", keyframes="motion:1.5,45")  # 41 keyframes
    run = {m: register(scans, load_config("default", overrides={"method": "icp-point", "threads": 1,
                                                                    "warm_start": {"method": m}}))
           for m in ("auto", "file", "none")}
    np.testing.assert_array_equal(run["auto"].poses, run["file"].poses)
    assert np.abs(run["none"].poses - run["file"].poses).max() > 1e-3
