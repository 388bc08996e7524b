"""Named profiles are files (src/deepmapping/profiles/*.yaml), resolved in one function."""

from pathlib import Path

import pytest

from deepmapping.config import PROFILE_DIR, PROFILES, load_config, profile_changes, profile_settings, resolve_profile
from deepmapping.errors import ConfigError


def test_the_profiles_are_the_files():
    names = sorted(f.stem for f in PROFILE_DIR.iterdir() if f.suffix == ".yaml")
    assert sorted(PROFILES) == names
    assert {"default", "default-3d", "paper", "paper-3d", "cold", "fast", "bunny", "relocalization"} <= set(names)


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
    with pytest.raises(ConfigError, match="'fast' is for 2D scans"):
        resolve_profile("fast", is_3d=True)
    with pytest.raises(ConfigError, match="unknown profile 'nope'"):
        resolve_profile("nope", is_3d=False)


def test_the_readme_lists_every_profile():
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    row = next(line for line in readme.splitlines() if line.startswith("| `--profile "))
    listed = row.split("`")[1].removeprefix("--profile ").split("\\|")
    assert listed == [p for p in PROFILES if not p.endswith("-3d")]
