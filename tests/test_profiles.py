"""Named profiles are files (src/deepmapping/profiles/*.yaml), resolved in one function."""

from pathlib import Path

import pytest

from deepmapping.config import PROFILE_DIR, PROFILES, load_config, profile_changes, profile_settings, resolve_profile
from deepmapping.errors import ConfigError


def test_the_profiles_are_the_files():
    names = sorted(f.stem for f in PROFILE_DIR.iterdir() if f.suffix == ".yaml")
    assert sorted(PROFILES) == names
    assert {"default", "default-3d", "paper", "paper-3d", "cold", "fast", "bunny", "relocalization", "long"} <= set(names)


@pytest.mark.parametrize("name", ["default", "default-3d", "paper", "paper-3d"])
def test_a_profile_without_base_lists_every_setting(name, monkeypatch):
    assert "base" not in PROFILES[name]
    assert load_config(name).profile == name
    broken = {k: (dict(v) if isinstance(v, dict) else v) for k, v in PROFILES[name].items()}
    del broken["optim"]["epochs"]
    monkeypatch.setitem(PROFILES, name, broken)
    with pytest.raises(ConfigError, match=f"{name}.yaml: .*missing optim.epochs"):
        profile_settings(name)


@pytest.mark.parametrize("name", [p for p in PROFILES if "base" in PROFILES[p]])
def test_a_profile_with_base_is_its_base_and_its_changes(name):
    changes = profile_changes(name)
    assert changes  # a profile that changes nothing is a second name for its base
    derived = load_config(PROFILES[name]["base"]).with_overrides(changes).model_dump()
    assert load_config(name).model_dump() | {"profile": derived["profile"]} == derived


def test_resolve_profile_picks_the_variant_for_the_data():
    assert resolve_profile("default", is_3d=False) == "default"
    assert resolve_profile("default", is_3d=True) == "default-3d"
    assert resolve_profile("paper", is_3d=True) == "paper-3d"
    assert resolve_profile("default", is_3d=False, cold=True) == "cold"
    assert resolve_profile("default", is_3d=True, cold=True) == "default-3d"  # 3D cold starts keep default-3d
    assert resolve_profile("paper", is_3d=False, cold=True) == "paper"  # a named profile stays as asked
    assert resolve_profile("bunny", is_3d=True) == "bunny"
    assert resolve_profile("default", is_3d=True, handheld=True) == "handheld"  # 6-DoF depth images
    assert resolve_profile("default", is_3d=True, cold=True, handheld=True) == "default-3d"  # measured warm only
    assert resolve_profile("paper", is_3d=True, handheld=True) == "paper-3d"
    assert resolve_profile("bunny", is_3d=True, handheld=True) == "bunny"
    with pytest.raises(ConfigError, match="'fast' is for 2D scans"):
        resolve_profile("fast", is_3d=True)
    with pytest.raises(ConfigError, match="unknown profile 'nope'"):
        resolve_profile("nope", is_3d=False)


def test_the_readme_lists_every_profile():
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    row = next(line for line in readme.splitlines() if line.startswith("| `--profile "))
    listed = row.split("`")[1].removeprefix("--profile ").split("\\|")
    assert listed == [p for p in PROFILES if not p.endswith("-3d")]


def test_settings_under_their_old_names_still_load(tmp_path):
    """The loop-closure settings moved from icp.loop_* to loop.*: overrides and config files
    (a saved run's config) with the old names load to the new ones; the others stay in icp."""
    from deepmapping.config import RENAMED

    assert RENAMED["icp.loop_radius"] == "loop.radius" and len(RENAMED) == 9
    cfg = load_config("default", overrides={"icp.loop_radius": 2.5, "loop.min_gap": 12})
    assert cfg.loop.radius == 2.5 and cfg.loop.min_gap == 12
    path = tmp_path / "old.yaml"
    path.write_text("icp:\n  loop_min_overlap: 0.5\n  max_iterations: 7\nloop:\n  radius: 3.0\n")
    cfg = load_config("default", path=path)
    assert (cfg.loop.min_overlap, cfg.loop.radius, cfg.icp.max_iterations) == (0.5, 3.0, 7)
    assert "loop_radius" not in cfg.model_dump()["icp"]
    with pytest.raises(ConfigError, match="'loop.radius'"):
        load_config("default", overrides={"icp.loop_radius": 0})
    # a checkpoint's settings as an older version dumped them match the same settings now (resume)
    from deepmapping.config import validate_config

    now = load_config("default").model_dump()
    old = now | {"icp": now["icp"] | {k.split(".")[1]: now["loop"][v.split(".")[1]] for k, v in RENAMED.items()}}
    del old["loop"]  # and settings added to loop since (max_free_conflict) get their default
    assert validate_config(old).model_dump() == now and old != now
