"""Cold start: the cold profile, the curriculum's placements, convergence from no initial poses."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deepmapping.config import load_config
from deepmapping.errors import ConfigError
from deepmapping.geometry import se2


def _cold(**over):
    return load_config("cold", overrides={"threads": 1, **over})


def test_cold_profile_is_the_default_one_after_the_curriculum():
    cold, default = load_config("cold"), load_config("default")
    assert cold.warm_start.method == "none" and cold.curriculum.enabled == "on"
    # the networks and schedule of the default, with the step the cold start was measured with
    # (64 beams at stride 1) where the default derives it from the scans ("auto")
    assert cold.lnet == default.lnet.model_copy(update={"stride": 1}) and cold.mnet == default.mnet
    assert cold.optim == default.optim and (cold.loss.beams_per_scan, default.loss.beams_per_scan) == (64, "auto")
    assert load_config("paper").curriculum.enabled == "off"  # §4.1 unchanged
    assert load_config("paper-3d").curriculum.enabled == "off"


def test_warm_start_none_on_the_command_line_picks_the_cold_profile():
    from deepmapping.cli.register_cmd import build_config

    def build(profile, warm, init=None):
        return build_config(profile, None, "deepmapping", None, warm, init, None, None, {})

    assert build("default", "none").profile == "cold"
    assert build("default", "icp-plane").profile == "default"
    assert build("paper", "none").profile == "paper"  # the paper profile is kept as it is
    assert build("paper", "none").curriculum.enabled == "off"


def test_curriculum_refuses_what_it_cannot_do(small_scans):
    from deepmapping.api import register

    with pytest.raises(ConfigError, match="zero_init_output"):
        register(small_scans, _cold(**{"lnet.zero_init_output": False, "optim.epochs": 1}))
    with pytest.raises(ConfigError):
        load_config("cold", overrides={"curriculum.chunk": 0})


def test_a_new_scan_is_placed_at_the_turn_and_shift_the_loss_prefers():
    """Two consecutive scans: the second is placed (before any gradient step) close to its
    true pose relative to the first, from a start 20 deg and 6 px off."""
    from deepmapping.sim.dataset import simulate
    from deepmapping.sim.maps import procedural_indoor_map
    from deepmapping.solver import curriculum
    from deepmapping.solver.model import DeepMappingModel
    from deepmapping.solver.trainer import Trainer

    errors = []
    for seed in range(3):
        scans = simulate(procedural_indoor_map(seed, size=512), 2, seed=seed, num_beams=128, mean_step_px=6,
                         max_rotation_deg=25)
        true = se2.relative(scans.gt_poses[0], scans.gt_poses[1])
        cfg = _cold(seed=seed)
        pts = torch.as_tensor(scans.points, dtype=torch.float32)
        valid = torch.as_tensor(scans.valid)
        model = DeepMappingModel(cfg, pts, torch.zeros(2, 3), valid=valid)
        trainer = Trainer(cfg, model, valid, ordered=True)
        model.make_direct()
        curriculum.place_new_scan(trainer, 1)
        placed = model.direct_poses[1].detach().double().numpy()
        d = se2.relative(true, placed)
        errors.append((float(np.hypot(d[0], d[1]) * 512), float(abs(np.degrees(d[2])))))
        assert abs(np.degrees(true[2])) > 4.5  # staying where the predecessor is would be this far off
    # measured (seeds 0-5, select_bce_weight 0.1): 0.06-1.04 px and 0.08-0.84 deg (weight 1: 0.7-2.5 px)
    assert all(t < 5.0 and r < 3.0 for t, r in errors), errors


def test_refining_the_best_hypotheses_never_ends_higher():
    """curriculum.refine_top: the chosen placement's loss is at most the one of the plain
    ranking (the unrefined hypotheses stay candidates), and it is still at the true motion."""
    from deepmapping.sim.dataset import simulate
    from deepmapping.sim.maps import procedural_indoor_map
    from deepmapping.solver import curriculum
    from deepmapping.solver.model import DeepMappingModel
    from deepmapping.solver.trainer import Trainer

    scans = simulate(procedural_indoor_map(1, size=512), 2, seed=1, num_beams=128, mean_step_px=6,
                     max_rotation_deg=25)
    pts, valid = torch.as_tensor(scans.points, dtype=torch.float32), torch.as_tensor(scans.valid)
    out = {}
    for top in (0, 4):
        cfg = _cold(seed=1, **{"curriculum.refine_top": top, "curriculum.refine_steps": 10})
        torch.manual_seed(0)
        model = DeepMappingModel(cfg, pts, torch.zeros(2, 3), valid=valid)
        trainer = Trainer(cfg, model, valid, ordered=True)
        model.make_direct()
        curriculum.place_new_scan(trainer, 1)
        placed = curriculum.placement(model, 1)
        with torch.no_grad():
            prev = (curriculum.transform(model.direct_poses[:1], model.scans[:1])[0], valid[0])
            loss = curriculum.candidate_losses(model, (model.scans[1], valid[1]), 1,
                                               torch.as_tensor(placed[None], dtype=torch.float32), prev,
                                               cfg.loss.chamfer_weight)
        out[top] = (float(loss), se2.relative(se2.relative(scans.gt_poses[0], scans.gt_poses[1]), placed))
    assert out[4][0] <= out[0][0] + 1e-6, out
    d = out[4][1]
    assert np.hypot(d[0], d[1]) * 512 < 5.0 and abs(np.degrees(d[2])) < 3.0, d


def test_the_wide_search_places_a_scan_after_a_large_motion():
    """Steps of 32-44 px and turns up to 40 deg from the first scan (stride 8 of the paper's
    trajectories: 59 px, 33 deg): the rounds alone (+- 0.25 x the median range, +- 30 deg) stay
    short of the motion; with curriculum.wide_hypotheses the second scan lands close to it."""
    from deepmapping.sim.dataset import simulate
    from deepmapping.sim.maps import procedural_indoor_map
    from deepmapping.solver import curriculum
    from deepmapping.solver.model import DeepMappingModel
    from deepmapping.solver.trainer import Trainer

    errors = {0: [], 1024: []}
    for seed in range(6):
        scans = simulate(procedural_indoor_map(seed, size=512), 2, seed=seed, num_beams=128, mean_step_px=60,
                         max_rotation_deg=40)
        pts, valid = torch.as_tensor(scans.points, dtype=torch.float32), torch.as_tensor(scans.valid)
        for wide in errors:
            cfg = _cold(seed=seed, **{"curriculum.wide_hypotheses": wide, "curriculum.wide_points": 16})
            model = DeepMappingModel(cfg, pts, torch.zeros(2, 3), valid=valid)
            trainer = Trainer(cfg, model, valid, ordered=True)
            model.make_direct()
            curriculum.place_new_scan(trainer, 1)
            d = se2.relative(se2.relative(scans.gt_poses[0], scans.gt_poses[1]), curriculum.placement(model, 1))
            errors[wide].append(float(np.hypot(d[0], d[1]) * 512))
    # measured (seeds 0-5, select_bce_weight 0.1): rounds alone 16-34 px (median 27), wide 0.5-3.5 px
    # (median 0.86; with weight 1: 2.1-16 px, median 4.1)
    assert np.median(errors[0]) > 14.0 and np.median(errors[1024]) < 8.0, errors


@pytest.fixture(scope="module")
def hard_trajectory():
    """16 scans with steps of about 30 px and turns of up to 30 deg (the paper's: 8 px, 10 deg)."""
    from deepmapping.sim.dataset import simulate
    from deepmapping.sim.maps import procedural_indoor_map

    return simulate(procedural_indoor_map(0, size=512), 16, seed=2, num_beams=64, mean_step_px=30,
                    max_rotation_deg=30)


def _pairwise_point_icp_from_identity(scans) -> np.ndarray:
    from deepmapping.methods.icp import icp_2d

    rel = [icp_2d(scans.points[i + 1][scans.valid[i + 1]].astype(float), scans.points[i][scans.valid[i]].astype(float),
                  method="point")[0] for i in range(scans.num_scans - 1)]
    return se2.chain(np.array(rel))


def test_cold_deepmapping_registers_from_no_initial_poses(hard_trajectory):
    """No initial poses, no ICP: DeepMapping (cold profile) registers the trajectory, with every
    pose starting at the origin, better than point-to-point ICP chained from the identity."""
    from deepmapping.api import evaluate_poses, register
    from deepmapping.evaluation.metrics import ate

    res = register(hard_trajectory, _cold(**{"optim.epochs": 30}))
    start = evaluate_poses(hard_trajectory, res.init_poses)["ate"]
    assert start > 40.0 and np.allclose(res.init_poses, 0.0)
    # measured over 5 seeds: 0.75-1.33 px (weight 1: 1.0-1.8 px); success is 20 px
    assert res.metrics["ate"] < 5.0, res.metrics["ate"]
    icp = ate(_pairwise_point_icp_from_identity(hard_trajectory), hard_trajectory.gt_poses) * 512
    assert icp > 2 * res.metrics["ate"], icp  # measured: 12.9 px
    placed = [a for a, e in zip(res.history["ate"], res.history["epoch"]) if e == 0 and a is not None]
    assert len(placed) >= 2 and placed[-1] < 10.0  # the curriculum's placements alone are close
    assert res.history["epoch"][-1] == 30


def test_direct_cold_shares_the_curriculum(hard_trajectory):
    from deepmapping.api import register

    res = register(hard_trajectory, _cold(method="direct", **{"optim.epochs": 30}))
    assert res.metrics["ate"] < 5.0, res.metrics["ate"]  # measured over 5 seeds: 0.63-0.93 px


def test_ctrl_c_during_the_curriculum_then_resume(hard_trajectory, tmp_path):
    from deepmapping.api import register
    from deepmapping.solver.trainer import Interrupted

    cfg = _cold(**{"optim.epochs": 10, "optim.checkpoint_every_s": 0.0})
    seen = []

    def ctrl_c(placed, total):
        seen.append(placed)
        if placed == 8:
            raise KeyboardInterrupt

    with pytest.raises(Interrupted):
        register(hard_trajectory, cfg, checkpoint=tmp_path / "c.pt", on_place=ctrl_c)
    saved = torch.load(tmp_path / "c.pt", weights_only=False)
    assert 0 < saved["placed"] < 16 and saved["direct"] and saved["epoch"] == 0
    res = register(hard_trajectory, cfg, checkpoint=tmp_path / "c.pt", resume=True)
    assert res.history["epoch"][-1] == 10 and res.metrics["ate"] < 20.0
    assert torch.load(tmp_path / "c.pt", weights_only=False)["placed"] == 16
    assert seen == [4, 8]


def test_curriculum_run_is_reproducible_from_the_seed(hard_trajectory):
    from deepmapping.api import register
    from deepmapping.experiments.base import QUICK_CURRICULUM  # the same code paths, a smaller search

    cfg = _cold(**{"optim.epochs": 2, **QUICK_CURRICULUM})
    a = register(hard_trajectory, cfg).poses
    b = register(hard_trajectory, cfg).poses
    np.testing.assert_array_equal(a, b)


# -- planar 3D poses (AVD-like depth images): opt-in ---------------------------------------------


def _planar_model(pivot: str):
    from deepmapping.geometry import se3
    from deepmapping.solver.model import DeepMappingModel

    rng = np.random.default_rng(0)
    scans = torch.as_tensor(rng.uniform(-1, 1, (3, 40, 3)) + [0, 0, 2], dtype=torch.float32)
    valid = torch.ones(3, 40, dtype=torch.bool)
    init = torch.as_tensor(se3.from_planar_xz([[0.1, 0.2, 0.3], [0.0, -0.1, 1.0], [0.3, 0.3, -2.0]]),
                           dtype=torch.float32)
    cfg = load_config("default-3d", overrides={"lnet.pivot": pivot, "threads": 1})
    model = DeepMappingModel(cfg, scans, init, valid=valid, pose_dof=3)
    model.make_direct()
    return model


@pytest.mark.parametrize("pivot", ["sensor", "centroid"])
def test_planar_3d_placements_round_trip(pivot):
    """A placement written as a planar pose [z, x, heading] is read back the same, whatever the
    warm start and the pivot the model composes its corrections with."""
    from deepmapping.solver import curriculum

    model = _planar_model(pivot)
    target = np.array([0.4, -0.7, 2.5])
    curriculum.set_placement(model, range(1, 3), target)
    for j in (1, 2):
        assert np.allclose(curriculum.placement(model, j), target, atol=1e-5)
        pose = model.all_poses()[j].double().numpy()  # a turn about the vertical axis, no height change
        assert np.isclose(pose[1, 3], 0.0, atol=1e-5) and np.isclose(pose[1, 1], 1.0, atol=1e-5)
    assert not np.allclose(curriculum.placement(model, 0), target)


def test_truncated_chamfer_caps_what_the_other_view_does_not_see():
    from deepmapping.solver.curriculum import truncated_chamfer

    x = torch.rand(1, 50, 3)
    ones = torch.ones(1, 50, dtype=torch.bool)
    assert float(truncated_chamfer(x, ones, x, ones, 0.1)) < 0.05  # cdist rounding
    assert float(truncated_chamfer(x, ones, x + 10.0, ones, 0.1)) == pytest.approx(2.0)


def test_curriculum_runs_on_planar_3d_cold_starts_and_is_refused_for_6dof():
    from deepmapping.api import register
    from deepmapping.experiments.exp_avd import avd_trajectory

    scans = avd_trajectory(0, frames=6, width=16, height=12)
    cfg = load_config("default-3d", overrides={"warm_start.method": "none", "optim.epochs": 2, "threads": 1,
                                               "curriculum.steps": 3})
    c = cfg.curriculum  # the depth-image ranking: truncated Chamfer + free space, a wide search at every image
    assert c.select_truncate > 0 and c.free_space_weight > 0 and c.wide_hypotheses > 0 and c.wide_trigger == 0
    assert c.free_space_trigger == 0  # every image: AVD-like motions are large turns
    res = register(scans, cfg)  # auto: on for a cold start of planar (AVD-like) depth images
    assert res.placements is not None and np.allclose(res.placements[:, 1, 3], 0.0, atol=1e-4)
    assert np.isfinite(res.metrics["ate"])
    assert register(scans, cfg.with_overrides({"curriculum.enabled": "off"})).placements is None
    six = scans.__class__(**{**scans.__dict__, "pose_dof": 6})
    assert register(six, cfg).placements is None  # auto: 6-DoF poses start from the identity
    with pytest.raises(ConfigError, match="6-DoF"):
        register(six, cfg.with_overrides({"curriculum.enabled": "on"}))


def test_the_wide_search_scores_in_blocks_as_at_once(monkeypatch):
    """Dense scans are scored a block of hypotheses at a time (bounded memory): the same choice."""
    from deepmapping.solver import curriculum

    target = np.array([0.3, -0.2, 0.4])

    def score(c):
        return torch.as_tensor(np.abs(np.asarray(c) - target).sum(1))

    picks = []
    for block in (1 << 20, 7 * 64):
        monkeypatch.setattr(curriculum, "WIDE_BLOCK_POINTS", block)
        picks.append(curriculum.wide_search(score, np.zeros((2, 3)), 1000, 1.0, 1.0, 5,
                                            np.random.default_rng(3), points=64))
    assert np.array_equal(picks[0], picks[1])
    assert np.abs(picks[0][0] - target).sum() < 0.2


def test_a_chamfer_only_ranking_does_not_evaluate_the_mnet():
    from deepmapping.solver import curriculum

    class NoMNet:
        def mnet(self, x):
            raise AssertionError("the M-Net was evaluated")

    pts = (torch.rand(30, 2), torch.ones(30, dtype=torch.bool))
    prev = (torch.rand(40, 2), torch.ones(40, dtype=torch.bool))
    cands = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.3]])
    loss = curriculum.candidate_losses(NoMNet(), pts, 1, cands, prev, 1.0, bce_weight=0.0, truncate=0.1)
    moved = curriculum.transform(cands, pts[0][None].expand(2, -1, -1))
    want = curriculum.truncated_chamfer(moved, pts[1][None].expand(2, -1), prev[0][None].expand(2, -1, -1),
                                        prev[1][None].expand(2, -1), 0.1)
    assert torch.allclose(loss, want)


def test_the_wide_choice_needs_a_margin_and_can_keep_the_rounds_position():
    from deepmapping.solver.curriculum import prefer_wide

    best, far = np.array([1.0, 2.0, 0.1]), np.array([1.5, 2.5, 0.6])
    assert np.array_equal(prefer_wide(best, far, torch.tensor([1.0, 0.9]), 0.0, False), far)
    assert np.array_equal(prefer_wide(best, far, torch.tensor([1.0, 0.9]), 0.15, False), best)  # not by 15 %
    assert np.array_equal(prefer_wide(best, far, torch.tensor([1.0, 0.8]), 0.15, False), far)
    assert np.array_equal(prefer_wide(best, far, torch.tensor([1.0, 0.8]), 0.15, True), [1.0, 2.0, 0.6])
    assert np.array_equal(prefer_wide(best, far, torch.tensor([1.0, float("nan")]), 0.0, False), best)


def _plane_image(depth: float = 2.0):
    """An 8 x 10 depth image of a wall at ``depth`` in front of the simulator's pinhole camera."""
    from deepmapping.sim.rgbd import Intrinsics

    intr = Intrinsics.from_hfov(10, 8, 60.0)
    pts = intr.ray_directions() * depth
    return intr, torch.as_tensor(pts, dtype=torch.float64)


def test_the_pinhole_is_fitted_from_the_depth_images():
    from deepmapping.solver.curriculum import fit_pinhole

    intr, pts = _plane_image()
    valid = torch.ones(1, 80, dtype=torch.bool)
    valid[0, :7] = False  # invalid pixels are left out (their stored points are zero)
    pts = torch.where(valid[0, :, None], pts, torch.zeros_like(pts))
    fx, cx, fy, cy = fit_pinhole(pts[None], valid, (8, 10))
    assert np.allclose([fx, cx, fy, cy], [intr.fx, intr.cx, intr.fy, intr.cy], rtol=1e-9, atol=1e-9)
    bent = pts.clone()
    bent[:, 0] = bent[:, 0] ** 3  # not a pinhole (a strongly distorting lens): no check at all
    assert fit_pinhole(bent[None], valid, (8, 10)) is None
    assert fit_pinhole(pts[None], torch.zeros_like(valid), (8, 10)) is None  # no valid point


def test_free_space_is_what_every_neighbouring_pixel_saw_beyond():
    from deepmapping.solver.curriculum import free_depth

    depth = torch.full((4, 5), 3.0)
    depth[1, 1] = 1.0  # an edge: its neighbours are surely free only up to 1
    valid = torch.ones(4, 5, dtype=torch.bool)
    valid[3, 4] = False  # no return: nothing around it is surely free
    free = free_depth(depth.flatten(), valid.flatten(), (4, 5)).reshape(4, 5)
    assert torch.all(free[:3, :3] == 1.0) and free[0, 4] == 3.0
    assert torch.all(free[2:, 3:] == 0.0) and free[3, 2] == 3.0


def test_points_in_front_of_what_a_camera_saw_cost_the_rest_do_not():
    from deepmapping.solver.curriculum import fit_pinhole, free_depth, seen_free

    intr, wall = _plane_image(2.0)
    valid = torch.ones(80, dtype=torch.bool)
    pinhole = fit_pinhole(wall[None], valid[None], (8, 10))
    free = free_depth(wall[:, 2], valid, (8, 10))
    cam = torch.eye(4, dtype=torch.float64)[None]
    centre = wall[4 * 10 + 5]  # where a ray through the middle of the image meets the wall
    pts = torch.stack([centre * 0.5, centre * 0.97, centre * 1.0, centre * 1.5,  # in front, within tol, on, behind
                       torch.tensor([5.0, 0.0, 1.0], dtype=torch.float64),  # outside the image
                       torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)])  # behind the camera
    each = [float(seen_free(p[None, None], torch.ones(1, dtype=torch.bool), cam, free, pinhole, (8, 10), 0.1))
            for p in pts]
    assert each == [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    away = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0], dtype=torch.float64))[None]  # the camera turned around
    assert float(seen_free(pts[:1][None], torch.ones(1, dtype=torch.bool), away, free, pinhole, (8, 10), 0.1)) == 0.0


@pytest.mark.parametrize("weight", [0.0, 3.0])
def test_the_curriculum_checks_free_space_on_depth_images_when_weighted(weight, monkeypatch):
    from deepmapping.api import register
    from deepmapping.experiments.exp_avd import avd_trajectory
    from deepmapping.solver import curriculum

    calls = []
    plain = curriculum.seen_free
    monkeypatch.setattr(curriculum, "seen_free", lambda *a, **k: calls.append(1) or plain(*a, **k))
    scans = avd_trajectory(0, frames=3, width=16, height=12)
    cfg = load_config("default-3d", overrides={"warm_start.method": "none", "optim.epochs": 1, "threads": 1,
                                               "curriculum.steps": 2, "curriculum.wide_hypotheses": 64,
                                               "curriculum.free_space_weight": weight})
    res = register(scans, cfg)
    assert res.placements is not None and np.all(np.isfinite(res.placements))
    assert (len(calls) > 0) == (weight > 0)


def _ring_scan(n: int, radius: float, start: float, inc: float) -> torch.Tensor:
    """A 2D scan of ``n`` beams from bearing ``start`` in steps ``inc`` inside a ring of ``radius``."""
    a = start + np.arange(n) * inc
    return torch.as_tensor(np.stack([radius * np.cos(a), radius * np.sin(a)], 1))


@pytest.mark.parametrize("n, start, inc", [(180, -np.pi, 2 * np.pi / 180),  # 360 deg, counter-clockwise
                                           (50, np.pi / 4, -np.pi / 2 / 49)])  # 90 deg, clockwise
def test_the_beam_bearings_are_fitted_from_the_2d_scans(n, start, inc):
    from deepmapping.solver.curriculum import fit_polar

    scan = _ring_scan(n, 5.0, start, inc)
    valid = torch.ones(1, n, dtype=torch.bool)
    valid[0, 3:9] = False  # beams without a return are left out
    got_start, got_inc = fit_polar(scan[None], valid)
    assert abs(np.angle(np.exp(1j * (got_start - start)))) < 1e-9 and abs(got_inc - inc) < 1e-12
    shuffled = scan[torch.randperm(n, generator=torch.Generator().manual_seed(0))]
    assert fit_polar(shuffled[None], torch.ones(1, n, dtype=torch.bool)) is None  # not in bearing order
    assert fit_polar(scan[None], torch.zeros(1, n, dtype=torch.bool)) is None


def test_points_in_front_of_what_a_2d_scan_saw_cost_the_rest_do_not():
    from deepmapping.solver.curriculum import fit_polar, free_depth, seen_free_2d

    n = 50
    scan = _ring_scan(n, 3.0, np.pi / 4, -np.pi / 2 / 49)  # 90 deg ahead, clockwise, a wall at 3
    valid = torch.ones(n, dtype=torch.bool)
    polar = fit_polar(scan[None], valid[None])
    free = free_depth(scan.norm(dim=1), valid, (n,))
    pts = torch.tensor([[2.0, 0.0], [2.95, 0.0], [3.5, 0.0], [-2.0, 0.0], [1.0, 0.9]], dtype=torch.float64)
    one = torch.ones(1, dtype=torch.bool)
    here = torch.zeros(1, 3, dtype=torch.float64)
    each = [float(seen_free_2d(p[None, None], one, here, free, polar, 0.1)) for p in pts]
    assert each == [1.0, 0.0, 0.0, 0.0, 1.0]  # in front, within tol, behind, outside the beams, in front
    turned = torch.tensor([[1.0, 0.0, np.pi / 2]], dtype=torch.float64)  # at (1, 0), looking along +y
    assert float(seen_free_2d(torch.tensor([[[1.0, 2.0]]], dtype=torch.float64), one, turned, free, polar, 0.1)) == 1.0
    assert float(seen_free_2d(torch.tensor([[[3.0, 0.0]]], dtype=torch.float64), one, turned, free, polar, 0.1)) == 0.0


@pytest.mark.parametrize("weight", [0.0, 1.0])
def test_the_curriculum_checks_free_space_on_2d_scans_when_weighted(weight, hard_trajectory, monkeypatch):
    from deepmapping.api import register
    from deepmapping.solver import curriculum

    calls = []
    plain = curriculum.seen_free_2d
    monkeypatch.setattr(curriculum, "seen_free_2d", lambda *a, **k: calls.append(1) or plain(*a, **k))
    res = register(hard_trajectory, _cold(**{"optim.epochs": 1, "curriculum.steps": 2, "curriculum.wide_hypotheses": 64,
                                   "curriculum.free_space_weight": weight}))
    assert res.placements is not None and np.all(np.isfinite(res.placements))
    assert (len(calls) > 0) == (weight > 0)


@pytest.mark.parametrize("trigger", [0.0, 1e6])
def test_slow_sequences_skip_the_free_space_check(trigger, hard_trajectory, monkeypatch):
    from deepmapping.api import register
    from deepmapping.solver import curriculum

    checked = []
    plain = curriculum.free_space_check
    monkeypatch.setattr(curriculum, "free_space_check", lambda t, j, *a: checked.append(j) or plain(t, j, *a))
    register(hard_trajectory, _cold(**{"optim.epochs": 1, "curriculum.steps": 2, "curriculum.wide_hypotheses": 64,
                                       "curriculum.free_space_trigger": trigger, "curriculum.free_space_weight": 1.0}))
    n = len(hard_trajectory.points)
    assert checked == (list(range(1, n)) if trigger == 0 else [1])  # motions below the trigger: the second scan only


def test_the_free_space_charge_rises_over_the_ramp():
    from deepmapping.solver.curriculum import fit_polar, free_depth, seen_free_2d

    scan = _ring_scan(50, 3.0, np.pi / 4, -np.pi / 2 / 49)
    valid = torch.ones(50, dtype=torch.bool)
    polar, free = fit_polar(scan[None], valid[None]), free_depth(scan.norm(dim=1), valid, (50,))
    p = torch.tensor([[[2.85, 0.0]]], dtype=torch.float64)  # 0.15 in front of the wall: tolerance 0.1 + 0.05
    one, here = torch.ones(1, dtype=torch.bool), torch.zeros(1, 3, dtype=torch.float64)
    for ramp, want in ((1.0, 0.5), (10.0, 0.05), (0.25, 1.0)):
        assert float(seen_free_2d(p, one, here, free, polar, 0.1, ramp)) == pytest.approx(want, rel=1e-6)


@pytest.mark.parametrize("small", [0, 48])
def test_the_wide_search_runs_smaller_where_the_free_space_check_does_not(small, hard_trajectory, monkeypatch):
    """The full wide search where the free-space check runs too (the larger motions; here the
    second scan only), the small one elsewhere; small_wide_hypotheses 0: the full one everywhere."""
    from deepmapping.api import register
    from deepmapping.solver import curriculum

    sizes = []
    plain = curriculum.wide_search
    monkeypatch.setattr(curriculum, "wide_search",
                        lambda s, c, h, radius, turn, keep, *a, **k: sizes.append((h, keep)) or
                        plain(s, c, h, radius, turn, keep, *a, **k))
    register(hard_trajectory, _cold(**{"optim.epochs": 1, "curriculum.steps": 2, "curriculum.wide_hypotheses": 64,
                                       "curriculum.wide_keep": 8, "curriculum.wide_trigger": 0.0,
                                       "curriculum.free_space_trigger": 1e6, "curriculum.small_wide_hypotheses": small,
                                       "curriculum.small_wide_keep": 4}))
    n = len(hard_trajectory.points)
    assert sizes == [(64, 8)] + [(64, 8) if small == 0 else (48, 4)] * (n - 2)


def test_the_3d_profile_keeps_one_wide_search_size():
    from deepmapping.solver.curriculum import wide_size

    cfg = load_config("default-3d").curriculum
    assert wide_size(cfg, False) == wide_size(cfg, True) == (cfg.wide_hypotheses, cfg.wide_shift, cfg.wide_turn_deg,
                                                              cfg.wide_keep, cfg.wide_refine)
    two = load_config("cold").curriculum
    assert wide_size(two, False)[0] == two.small_wide_hypotheses < wide_size(two, True)[0]


@pytest.mark.parametrize("prior", [0.0, 0.3, None])
def test_the_turn_prior_stops_a_scan_turned_round_onto_its_predecessor(prior, hard_trajectory, monkeypatch):
    """A ranking that prefers the second scan turned 180 deg (a corridor folded back onto its
    predecessor) places it so; with curriculum.turn_prior (charged where the free-space check
    runs: the second scan; None: the cold profile's default, which has it on) the unturned
    placement wins."""
    from deepmapping.solver import curriculum
    from deepmapping.solver.model import DeepMappingModel
    from deepmapping.solver.trainer import Trainer

    monkeypatch.setattr(curriculum, "free_space_check", lambda *a: None)
    monkeypatch.setattr(curriculum, "candidate_losses",
                        lambda model, pts, j, cams, *a, **k: 0.1 * (1 + torch.cos(cams[:, 2])) / 2)
    scans = hard_trajectory
    pts, valid = torch.as_tensor(scans.points[:2], dtype=torch.float32), torch.as_tensor(scans.valid[:2])
    over = {"curriculum.wide_hypotheses": 256} | ({} if prior is None else {"curriculum.turn_prior": prior})
    cfg = _cold(**over)
    model = DeepMappingModel(cfg, pts, torch.zeros(2, 3), valid=valid)
    trainer = Trainer(cfg, model, valid, ordered=True)
    model.make_direct()
    curriculum.place_new_scan(trainer, 1)
    turn = abs(np.degrees(se2.relative(curriculum.placement(model, 0), curriculum.placement(model, 1))[2]))
    assert (turn < 20.0) if prior != 0 else (turn > 100.0), turn


def test_the_review_places_again_a_scan_left_apart_from_both_neighbours():
    """Every scan placed at its true pose but one, shifted by 15 px and turned by 5 deg (what the
    curriculum left on trajectory 1 of the Fig. 1 experiment): the review moves it back; with none
    displaced it moves nothing far. No M-Net training: the ranking's Chamfer term does it."""
    from deepmapping.sim.dataset import simulate
    from deepmapping.sim.maps import procedural_indoor_map
    from deepmapping.solver import curriculum
    from deepmapping.solver.model import DeepMappingModel
    from deepmapping.solver.trainer import Trainer

    back, still = [], []
    for scene, seed in [(0, 3), (0, 5), (1, 4), (1, 6), (2, 7)]:
        scans = simulate(procedural_indoor_map(scene, size=512), 12, seed=seed, num_beams=128)
        pts, valid = torch.as_tensor(scans.points, dtype=torch.float32), torch.as_tensor(scans.valid)
        cfg = _cold()
        for displaced in (True, False):
            model = DeepMappingModel(cfg, pts, torch.zeros(12, 3), valid=valid)
            trainer = Trainer(cfg, model, valid, ordered=True)
            model.make_direct()
            start = scans.gt_poses.copy()
            if displaced:
                start[6] = se2.compose(start[6], np.array([15 / 512, -4 / 512, np.radians(5)]))
            with torch.no_grad():
                model.direct_poses.copy_(torch.as_tensor(start, dtype=torch.float32))
            moved = curriculum.review_placements(trainer)
            err = se2.relative(scans.gt_poses, curriculum.placements(model, 12))
            px, deg = float(np.hypot(err[:, 0], err[:, 1]).max() * 512), float(np.degrees(np.abs(err[:, 2])).max())
            (back if displaced else still).append((moved, round(px, 2), round(deg, 2)))
    # measured (15 scene/seed pairs): 14 moved back to 0-2.9 px and 0-1.6 deg (one, whose ratio is
    # 1.47, not reviewed); undisplaced, 14 of 15 untouched and one moved 0.74 px
    assert sum(m == [6] and px < 4.0 and deg < 2.0 for m, px, deg in back) >= 4, back
    assert all(px < 1.5 and deg < 1.0 for _, px, deg in still), still
