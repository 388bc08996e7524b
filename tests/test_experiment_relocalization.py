"""Result.localize (the trained L-Net on new scans) and the re-localization experiment (§4.1, Fig. 7)."""

import json

import numpy as np
import pytest

from deepmapping.config import load_config


@pytest.fixture(scope="module")
def tiny_scans():
    from deepmapping.sim.dataset import simulate
    from deepmapping.sim.maps import procedural_indoor_map

    return simulate(procedural_indoor_map(2, 256), 12, seed=3, num_beams=64)


@pytest.mark.parametrize("warm", ["icp-plane", "none", "curriculum"])
def test_localize_on_the_training_scans_returns_the_registered_poses(tiny_scans, warm):
    from deepmapping.api import register

    s = tiny_scans
    over = {"warm_start.method": "none" if warm == "curriculum" else warm, "optim.epochs": 3, "threads": 1,
            "curriculum.enabled": "on" if warm == "curriculum" else "off"}
    result = register(s, load_config("default", overrides=over))
    assert result.localize is not None
    assert (result.placements is not None) == (warm == "curriculum")
    # a plain cold start's prior is the identity; a curriculum run's, the placements
    prior = {"icp-plane": result.init_poses, "none": None, "curriculum": result.placements}[warm]
    got = result.localize(s.points, s.valid, prior)
    assert got.shape == result.poses.shape
    np.testing.assert_allclose(got[:, :2], result.poses[:, :2], atol=1e-5)
    np.testing.assert_allclose(np.angle(np.exp(1j * (got[:, 2] - result.poses[:, 2]))), 0.0, atol=1e-5)
    # one scan at a time (another batch size) gives the same poses; invalid beams' values are ignored
    pts = np.where(s.valid[..., None], s.points, 123.0)
    one = np.concatenate([result.localize(pts[i : i + 1], s.valid[i : i + 1],
                                          None if prior is None else prior[i : i + 1]) for i in range(3)])
    np.testing.assert_allclose(one, got[:3], atol=1e-5)
    if warm != "none":  # the prior matters: another prior, another pose
        assert not np.allclose(result.localize(s.points, s.valid), got, atol=1e-3)


def test_localize_is_none_for_direct_optimization(tiny_scans):
    from deepmapping.api import register

    cfg = load_config("default", overrides={"method": "direct", "optim.epochs": 1, "threads": 1})
    assert register(tiny_scans, cfg).localize is None


def test_localize_3d_with_a_centroid_pivot(tmp_path):
    from deepmapping.api import register
    from deepmapping.io.lidar import load_lidar
    from deepmapping.sim.lidar import write_lidar_dataset

    write_lidar_dataset(tmp_path, num_trajectories=1, frames=3, seed=3)
    s = load_lidar(tmp_path / "traj_000", max_points=200)
    cfg = load_config("default-3d", overrides={"lnet.pivot": "centroid", "optim.epochs": 2, "threads": 1})
    result = register(s, cfg)
    got = result.localize(s.points, s.valid, result.init_poses)
    assert got.shape == (3, 4, 4)
    np.testing.assert_allclose(got, result.poses, atol=1e-4)


def test_quick_relocalization_experiment_end_to_end(tmp_path):
    from deepmapping.experiments.relocalization import jobs
    from deepmapping.experiments.runner import run_experiment

    out = run_experiment("relocalization", tmp_path, quick=True, workers=1)
    assert not out["errors"]
    keys = [j.key for j in jobs(True)]
    for name in ["report.md", "experiment.json", *(f"runs/{k}.json" for k in keys),
                 *(f"{k}_error_map.png" for k in keys)]:
        assert (tmp_path / name).is_file(), name
    text = (tmp_path / "report.md").read_text()
    for k in keys:
        assert f"{k}_error_map.png" in text
    for k in keys:
        r = json.loads((tmp_path / "runs" / f"{k}.json").read_text())
        assert np.isfinite(r["ate_px"]) and 0 <= r["ate_px"] < r["map_size"]
        for mode in r["headings"]:
            err = np.array(r["grid"][mode]["translation_px"], dtype=float)  # null (nan) = not a free cell
            rot = np.array(r["grid"][mode]["rotation_deg"], dtype=float)
            assert err.shape == rot.shape == tuple(r["grid"]["shape"])
            free = np.isfinite(err)
            assert free.sum() >= 20 and np.array_equal(free, np.isfinite(rot))
            assert (err[free] >= 0).all() and (rot[free] >= 0).all() and (rot[free] <= 180).all()
        # the training poses themselves relocalize to the registered poses (the L-Net is a function of the scan)
        assert r["training_scans_px"]["median"] < 1.0


def test_relocalization_report_copes_with_missing_runs(tmp_path):
    from deepmapping.experiments import relocalization

    path = relocalization.report(tmp_path, {}, quick=True)
    assert path.is_file() and "no finished runs" in path.read_text().lower()
    path = relocalization.report(tmp_path, {"broken": {"map_seed": 1, "map_size": 256}}, quick=True)
    assert "`broken`: unreadable result" in path.read_text()
