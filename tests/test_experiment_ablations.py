"""Ablations experiment (supplementary A): the ResMLP M-Net, and the quick sweep end to end."""

import json
import math

import numpy as np
import pytest
import torch

from deepmapping.config import MNetConfig, load_config
from deepmapping.errors import ConfigError
from deepmapping.experiments import ablations
from deepmapping.solver.networks import MNet, ResidualBlock


def test_resmlp_is_the_supplementarys_stack_of_residual_blocks():
    net = MNet(MNetConfig(kind="resmlp", hidden=[64, 64, 64, 128, 128]), in_dim=2)
    blocks = [m for m in net.mlp if isinstance(m, ResidualBlock)]
    assert [b.fc2.out_features for b in blocks] == [64, 64, 64, 128, 128]
    assert all(b.fc1.out_features == b.fc2.in_features == b.fc2.out_features for b in blocks)  # RB(n): two FC(n)
    # a projection on the skip only where the width changes (input 2 -> 64, 64 -> 128)
    assert [isinstance(b.shortcut, torch.nn.Linear) for b in blocks] == [True, False, False, True, False]
    assert isinstance(net.mlp[-1], torch.nn.Linear) and net.mlp[-1].out_features == 1
    assert net(torch.zeros(7, 33, 2)).shape == (7, 33)  # logits over any leading shape
    assert MNet(MNetConfig(kind="resmlp", hidden=[32, 32]), in_dim=3)(torch.zeros(5, 3)).shape == (5,)


def test_residual_block_adds_its_input():
    block = ResidualBlock(4, 4)
    for fc in (block.fc1, block.fc2):
        torch.nn.init.zeros_(fc.weight)
        torch.nn.init.zeros_(fc.bias)
    x = torch.randn(10, 4)
    torch.testing.assert_close(block(x), torch.relu(x))  # F(x) = 0: relu(x + 0)


def test_resmlp_mnet_trains():
    """Fits the occupancy of a disk: the BCE falls well below its starting value."""
    torch.manual_seed(0)
    net = MNet(MNetConfig(kind="resmlp", hidden=[64, 64, 64, 128, 128]), in_dim=2)
    xy = torch.rand(2048, 2) * 2 - 1
    target = (xy.norm(dim=1) < 0.5).float()
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    losses = []
    for _ in range(200):
        loss = torch.nn.functional.binary_cross_entropy_with_logits(net(xy), target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]
    assert ((net(xy) > 0).float() == target).float().mean() > 0.9


def test_config_accepts_resmlp_only_as_a_known_kind():
    assert load_config("paper", overrides={"mnet.kind": "resmlp"}).mnet.kind == "resmlp"
    with pytest.raises(ConfigError):
        load_config("paper", overrides={"mnet.kind": "resnet"})


def test_jobs_cover_every_variant_of_every_group():
    for quick in (True, False):
        jobs = ablations.jobs(quick)
        s = ablations.sizes(quick)
        assert len(jobs) == len(s["trajectories"]) * len(ablations.VARIANTS)
        assert len({j.key for j in jobs}) == len(jobs)
        json.dumps([j.kwargs for j in jobs])
    used = {v for _, members in ablations.GROUPS.values() for v in members.values()}
    assert used == set(ablations.VARIANTS)
    # the variants are the paper's networks: mlp / resmlp M-Nets, no Fourier features, cold start
    for v in ablations.VARIANTS:
        cfg = load_config(ablations.PROFILE, overrides=ablations.variant_overrides(v))
        assert cfg.mnet.kind in ("mlp", "resmlp") and cfg.warm_start.method == "none"
    assert load_config("paper", overrides=ablations.variant_overrides("depth6-width64")).mnet.hidden == [64] * 6


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    from deepmapping.experiments.runner import run_experiment

    out = tmp_path_factory.mktemp("ablations")
    return out, run_experiment("ablations", out, quick=True, workers=1)


def test_quick_run_end_to_end(quick_run):
    out, res = quick_run
    s = ablations.sizes(True)
    assert res["errors"] == {}
    assert len(res["results"]) == len(ablations.jobs(True))
    for name in ["report.md", "experiment.json"] + [f"ablation_{g}.png" for g in ablations.GROUPS]:
        assert (out / name).stat().st_size > 0, name
    assert len(list((out / "runs").glob("*.json"))) == len(ablations.jobs(True))
    expected_len = 1 + math.ceil(s["epochs"] / s["eval_every"])
    for r in res["results"].values():
        assert len(r["ate"]) == len(r["iteration"]) == expected_len
        assert np.all(np.diff(r["iteration"]) > 0)
        ate = np.array(r["ate"], float)
        assert np.isfinite(ate).all() and (ate > 0).all() and (ate < 500).all()  # px, on a 1024 px map
        assert r["final_ate"] == pytest.approx(ate[-1])
    params = {v: res["results"][f"traj{s['trajectories'][0]}-{v}"]["mnet_params"] for v in ablations.VARIANTS}
    assert params["depth4-width32"] < params["depth4-width64"] < params["depth4-width128"]
    assert params["depth4-width64"] < params["depth5-width64"] < params["depth7-width64"]
    text = (out / "report.md").read_text()
    for g in ablations.GROUPS:
        assert f"(ablation_{g}.png)" in text
    for label in ("PointNet", "ResMLP", "depth 7", "width 128"):
        assert f"| {label} |" in text
    assert "profile `paper`" in text and "3000" in text


def test_report_copes_with_missing_runs(quick_run, tmp_path):
    _, res = quick_run
    some = {k: v for k, v in res["results"].items() if "width" not in k}  # the depth/width runs failed
    path = ablations.report(tmp_path, some, quick=True)
    text = path.read_text()
    assert "| width 32 | 0/1 |" in text and all((tmp_path / f"ablation_{g}.png").exists() for g in ablations.GROUPS)
    assert ablations.report(tmp_path / "none", {}, quick=True).exists()
