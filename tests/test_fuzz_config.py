"""Fuzzed settings: config files (``load_config(path=...)``), dotted overrides
(``overrides=``) and ``--set`` values give a sane Config or one ConfigError line (naming the file,
or the setting); nonsense settings are refused before anything runs, on the command line too.

Hypothesis runs derandomized (the same examples on every machine, no example database).
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from deepmapping.cli.common import parse_sets
from deepmapping.config import PROFILES, Config, load_config
from deepmapping.errors import ConfigError

# no deadline per example: a fresh-clone run beside another suite on 2 cores took 6.9 s for the
# 5000-bracket example below (5 s was the deadline); the suite's own time is what CI bounds
FUZZ = settings(max_examples=50, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.filter_too_much])


def _leaves(d: dict, prefix: str = "") -> list[str]:
    out = []
    for k, v in d.items():
        out += _leaves(v, f"{prefix}{k}.") if isinstance(v, dict) else [f"{prefix}{k}"]
    return out


KEYS = _leaves(Config().model_dump())


def assert_sane(cfg: Config) -> None:
    """What no accepted configuration may hold: NaN / inf, or numbers outside their meaning."""
    assert isinstance(cfg, Config)

    def walk(v, key):
        if isinstance(v, dict):
            for k, x in v.items():
                walk(x, f"{key}.{k}")
        elif isinstance(v, list):
            for x in v:
                walk(x, key)
        elif isinstance(v, float):
            assert math.isfinite(v), f"{key} = {v} accepted"

    walk(cfg.model_dump(), "")
    o, lo, ic, ln, mn, cu = cfg.optim, cfg.loss, cfg.icp, cfg.lnet, cfg.mnet, cfg.curriculum
    assert o.lr > 0 and o.epochs >= 0 and o.batch_size >= 1 and o.eval_every >= 1
    assert o.mnet_warmup_epochs == "auto" or o.mnet_warmup_epochs >= 0
    assert o.lr_final_factor >= 0 and o.checkpoint_every_s >= 0
    assert (o.max_time_s is None or o.max_time_s >= 0) and (o.early_stop_tol is None or o.early_stop_tol >= 0)
    assert lo.free_samples >= 0 and (lo.near_hit_samples == "auto" or lo.near_hit_samples >= 0) and lo.near_hit_distance >= 0
    assert lo.chamfer_weight >= 0 and lo.chamfer_window >= 0 and (lo.beams_per_scan in (None, "auto") or lo.beams_per_scan >= 1)
    for v in (ic.voxel_size, ic.max_correspondence_distance, cfg.eval.voxel_size, cfg.eval.success_threshold):
        assert v is None or v > 0
    lc = cfg.loop
    assert ic.max_iterations >= 0 and lc.radius > 0 and lc.inlier_distance > 0 and lc.min_gap >= 1
    assert 0 <= lc.min_overlap <= 1 and all(s > 0 for s in lc.odometry_sigma)
    assert min(ln.kernel_size, ln.dilation) >= 1 and (ln.stride == "auto" or ln.stride >= 1)
    assert (ln.lr_factor == "auto" or ln.lr_factor >= 0) and mn.lr_factor >= 0
    assert all(c >= 1 for c in ln.conv_channels + ln.fc_channels + ln.point_channels + mn.hidden)
    assert min(mn.grid_levels, mn.grid_features, mn.grid_base, mn.grid_finest) >= 1 and mn.fourier_max_freq > 0
    assert 0 <= mn.coarse_to_fine <= 1 and mn.fourier_features >= 0 and ln.pose_input_freqs >= 0
    assert cu.chunk >= 1 and cu.lr > 0 and cu.hypotheses >= 1
    assert 0 <= cfg.seed < 2**64 and (cfg.threads is None or cfg.threads >= 1)


def outcome(fn, names: str):
    """fn() -> a sane Config, or None after a one-line ConfigError naming ``names``."""
    try:
        cfg = fn()
    except ConfigError as e:
        msg = str(e)
        assert names in msg, f"the message does not name {names!r}: {msg!r}"
        assert "\n" not in msg and msg.strip(), f"not one line: {msg!r}"
        return None
    assert_sane(cfg)
    return cfg


# ------------------------------------------------------------------------------------------
# nonsense settings
# ------------------------------------------------------------------------------------------
NONSENSE = [
    ("optim.epochs", -1), ("optim.lr", float("nan")), ("optim.lr", "nan"), ("optim.lr", float("inf")),
    ("optim.lr", 0.0), ("optim.lr", -1e-3), ("optim.lr", "fast"), ("optim.batch_size", 0),
    ("optim.eval_every", 0), ("optim.epochs", 2.5), ("optim.max_time_s", -5), ("optim.lr_final_factor", -1),
    ("icp.voxel_size", -0.05), ("icp.voxel_size", 0.0), ("icp.max_correspondence_distance", -1),
    ("loop.min_overlap", 1.5), ("loop.odometry_sigma", [0.1, float("nan")]), ("loop.radius", 0),
    ("eval.voxel_size", -1.0), ("eval.success_threshold", 0), ("loss.free_samples", -1),
    ("loss.chamfer_weight", -10), ("loss.beams_per_scan", 0), ("loss.near_hit_distance", float("-inf")),
    ("lnet.conv_channels", [64, 0]), ("lnet.stride", 0), ("mnet.hidden", [128, -1]), ("mnet.coarse_to_fine", 2),
    ("mnet.fourier_max_freq", 0), ("curriculum.chunk", 0), ("curriculum.lr", float("nan")),
    ("seed", -1), ("seed", 2**64), ("threads", 0), ("method", "magic"), ("device", "tpu"),
    ("optim.no_such_key", 1), ("no_such_section.lr", 1), ("optim.lr.deeper", 1), ("optim", 3),
]


@pytest.mark.parametrize("key, value", NONSENSE, ids=[f"{k}={v!r}" for k, v in NONSENSE])
def test_nonsense_setting_is_one_config_error_naming_it(key, value, tmp_path):
    with pytest.raises(ConfigError) as err:
        load_config("default", overrides={key: value})
    msg = str(err.value)
    assert key.split(".")[0] in msg and "\n" not in msg, msg
    if key.count(".") == 1 and not key.startswith("no_such"):
        assert key in msg, msg
    # the same in a config file: the message names the file too
    section, _, leaf = key.partition(".")
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump({section: {leaf: value}} if leaf else {section: value}))
    with pytest.raises(ConfigError) as err:
        load_config("default", path=path)
    assert str(path) in str(err.value) and "\n" not in str(err.value), str(err.value)


@pytest.mark.parametrize("profile", sorted(PROFILES))
def test_every_profile_is_sane(profile):
    assert_sane(load_config(profile))


# ------------------------------------------------------------------------------------------
# fuzzed overrides and --set values
# ------------------------------------------------------------------------------------------
SCALARS = (st.none() | st.booleans() | st.integers(-2**70, 2**70) | st.integers(-3, 600) | st.floats()
           | st.text(max_size=6) | st.sampled_from(["nan", ".nan", "inf", "-.inf", "-1", "0", "1e-3", "1e999", "auto"]))
VALUES = st.recursive(SCALARS, lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c, max_size=3),
                      max_leaves=8)
SET_KEYS = st.sampled_from(KEYS) | st.text(max_size=12) | st.sampled_from(["optim", "optim.", ".lr", "optim..lr"])


@FUZZ
@given(overrides=st.dictionaries(SET_KEYS, VALUES, min_size=1, max_size=3))
@example(overrides={"optim.lr": float("nan")})
@example(overrides={"optim.epochs": -1})
@example(overrides={"icp.voxel_size": -1.0})
@example(overrides={"optim.\nlr": 1})  # the key in the message on one line
def test_fuzzed_overrides(overrides):
    outcome(lambda: load_config("default", overrides=overrides), names="setting")


@FUZZ
@given(items=st.lists(st.text(max_size=20) | st.tuples(st.sampled_from(KEYS), st.text(max_size=12)).map("=".join),
                      min_size=1, max_size=3))
@example(items=["optim.lr=["])  # was a traceback (yaml ParserError)
@example(items=["optim.lr=2020-13-45"])  # was a ValueError traceback (YAML builds a date)
@example(items=["optim.lr=nan"])
@example(items=["\n"])  # was a message of two lines
def test_fuzzed_set_values(items):
    """``--set KEY=VALUE`` strings, parsed as the CLI does, then applied."""
    try:
        sets = parse_sets(items)
    except ConfigError as e:
        assert "--set" in str(e) and "\n" not in str(e), str(e)
        return
    outcome(lambda: load_config("default", overrides=sets), names="setting")


# ------------------------------------------------------------------------------------------
# fuzzed config files
# ------------------------------------------------------------------------------------------
VALID_YAML = yaml.safe_dump(load_config("default").model_dump(), sort_keys=False)
TOKENS = (st.sampled_from(["nan", ".nan", ".inf", "-.inf", "-1", "0", "1e400", "2020-13-45", "!!int x", "!!binary ?",
                           "[", "]", "{", "}", ":", "- ", "&a", "*a", "*b", "? ", "|", "'", '"', "\t", "\n", "#",
                           "null", "~", "yes", "0x1F", "0o17", "1_000", "!!python/object:os.system", "%YAML 1.1"])
          | st.text(max_size=5) | st.floats().map(repr) | st.integers(-2**70, 2**70).map(str))
NAME_CHARS = st.characters(codec="utf-8", exclude_categories=("Cc", "Cs", "Zl", "Zp"), exclude_characters="/\\")
NAMES = st.text(NAME_CHARS, min_size=1, max_size=12).filter(lambda s: s.strip() and s not in (".", ".."))


def load_file(raw: bytes, name: str = "config.yaml"):
    with tempfile.TemporaryDirectory(prefix="dm-fuzz-") as d:
        path = Path(d) / name
        path.write_bytes(raw)
        return outcome(lambda: load_config("default", path=path), names=str(path))


def replace_tokens(text: str, subs) -> str:
    import re

    parts = re.split(r"(\s+)", text)
    idx = [i for i, p in enumerate(parts) if p and not p.isspace()]
    for i, s in subs:
        parts[idx[i % len(idx)]] = s
    return "".join(parts)


def test_the_valid_file_loads():
    assert load_file(VALID_YAML.encode()) == load_config("default")


@FUZZ
@given(raw=st.binary(max_size=300))
@example(raw=b"\xff\xfe\x00")  # was UnicodeDecodeError
@example(raw=b"a: " + b"[" * 5000)  # was RecursionError
@example(raw=b"optim: 2020-13-45\n")  # was ValueError (YAML's date constructor)
def test_random_bytes_config_file(raw):
    load_file(raw)


@FUZZ
@given(cut=st.floats(0, 1, exclude_max=True))
def test_truncated_config_file(cut):
    raw = VALID_YAML.encode()
    load_file(raw[: int(cut * len(raw))])


@FUZZ
@given(subs=st.lists(st.tuples(st.integers(0, 2**16), TOKENS), min_size=1, max_size=3))
def test_garbage_tokens_in_config_file(subs):
    load_file(replace_tokens(VALID_YAML, subs).encode())


@FUZZ
@given(doc=st.dictionaries(st.sampled_from(sorted(Config.model_fields)) | st.text(max_size=6),
                           st.dictionaries(st.sampled_from(sorted({k.rsplit(".", 1)[-1] for k in KEYS}))
                                           | st.text(max_size=6), VALUES, max_size=4) | VALUES, max_size=4))
@example(doc={"optim": {"lr": float("nan")}})  # was accepted
@example(doc={"optim": {"epochs": -1}, "icp": {"voxel_size": -0.5}})  # was accepted
@example(doc={"optim": {"l\nr": 1}})
def test_fuzzed_config_documents(doc):
    load_file(yaml.safe_dump(doc).encode())


@settings(FUZZ, max_examples=15)
@given(folder=NAMES, name=NAMES)
@example(folder="réglages ✓", name="設定")
def test_config_file_under_a_unicode_path(folder, name):
    with tempfile.TemporaryDirectory(prefix="dm-fuzz-") as d:
        path = Path(d) / folder / f"{name}.yaml"
        path.parent.mkdir()
        path.write_text("optim:\n  epochs: 7\n", encoding="utf-8")
        assert outcome(lambda: load_config("default", path=path), names=str(path)).optim.epochs == 7
        path.unlink()
        assert outcome(lambda: load_config("default", path=path), names=str(path)) is None


# ------------------------------------------------------------------------------------------
# the command line: refused before any data is read, one line, no run folder
# ------------------------------------------------------------------------------------------
_SCRIPT = Path(sys.executable).parent / "deepmapping"
DM = str(_SCRIPT) if _SCRIPT.exists() else shutil.which("deepmapping")
ENV = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")


@pytest.mark.skipif(DM is None, reason="the `deepmapping` console script is not installed")
def test_cli_refuses_nonsense_settings_in_one_line(tmp_path):
    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_bytes(b"optim:\n  lr: .nan\n")
    binary_yaml = tmp_path / "binary.yaml"
    binary_yaml.write_bytes(b"\xff\xfe\x00garbage")
    cases = {  # args -> what the error line must name
        "lr-nan": (["--set", "optim.lr=nan"], "optim.lr"),
        "epochs-set": (["--set", "optim.epochs=-1"], "optim.epochs"),
        "epochs-flag": (["--epochs", "-1"], "optim.epochs"),
        "voxel": (["--set", "icp.voxel_size=-0.5"], "icp.voxel_size"),
        "unknown": (["--set", "optim.no_such_key=1"], "optim.no_such_key"),
        "bad-yaml-value": (["--set", "mnet.hidden=[64,"], "mnet.hidden"),
        "config-nan": (["--config", str(bad_yaml)], str(bad_yaml)),
        "config-binary": (["--config", str(binary_yaml)], str(binary_yaml)),
    }
    missing = tmp_path / "no_such_data"  # the settings are checked before the data is looked at

    def run(name):
        args, _ = cases[name]
        return subprocess.run([DM, "register", str(missing), "--out", str(tmp_path / name), *args],
                              capture_output=True, text=True, env=ENV, timeout=120)

    with ThreadPoolExecutor(2) as pool:
        results = dict(zip(cases, pool.map(run, cases)))
    for name, res in results.items():
        where = f"\n{name}: exit {res.returncode}\nstdout:\n{res.stdout}\nstderr:\n{res.stderr}"
        assert res.returncode == 2 and "Traceback" not in res.stdout + res.stderr, where
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: "), where
        assert cases[name][1] in lines[0], where
        assert not (tmp_path / name).exists(), where
