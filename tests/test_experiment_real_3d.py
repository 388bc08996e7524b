"""``deepmapping experiment real-3d`` on the excerpts of the bunny and 3DTK scans (tests/data)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from deepmapping.errors import ConfigError
from deepmapping.experiments import real_3d

DATA = Path(__file__).resolve().parent / "data"  # excerpts (tests/data/make_excerpts.py)


def test_jobs_cover_both_datasets_and_need_one(tmp_path):
    keys = [j.key for j in real_3d.jobs(False, str(DATA))]
    assert keys[0] == "bunny-start" and "bunny-multiway-from-identity" in keys and "bunny-direct-from-coarse" in keys
    assert [k for k in keys if k.startswith("3dtk-")] == ["3dtk-odometry"] + [f"3dtk-{m}" for m in real_3d.METHODS]
    json.dumps([j.kwargs for j in real_3d.jobs(True, str(DATA))])
    with pytest.raises(ConfigError, match=f"^{tmp_path}: neither bunny/ nor 3dtk/ in it$"):
        real_3d.jobs(False, str(tmp_path))


def test_quick_run_writes_tables_and_slam6d_frames(tmp_path):
    from deepmapping.experiments.runner import run_experiment
    from deepmapping.io.threedtk import read_frames

    res = run_experiment("real-3d", tmp_path, quick=True, workers=1, data=DATA, only="3dtk-*")
    assert res["errors"] == {}
    assert {r["method"] for r in res["results"].values()} == {"odometry", *real_3d.METHODS}
    for r in res["results"].values():
        assert len(r["scans"]) == 2 and all(np.isfinite([e["trans"], e["rot_deg"]]).all() for e in r["scans"])
    frames = read_frames(tmp_path / "3dtk_frames" / "deepmapping" / "scan002.frames")
    assert frames.shape == (1, 4, 4)
    text = (tmp_path / "report.md").read_text()
    assert "## 3DTK" in text and "| deepmapping |" in text and "## Stanford bunny" not in text
    res = run_experiment("real-3d", tmp_path, quick=True, workers=1, data=DATA, only="bunny-start")
    assert "| coarse start |" in (tmp_path / "report.md").read_text()
