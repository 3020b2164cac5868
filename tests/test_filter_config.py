"""The filter's nested settings: every old flat key fails with one line naming its successor (a
new key or a module constant), in Python and through the service's TOML."""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path

import pytest
from pydantic import ValidationError

from lino_loc.localizer import LocalizerConfig
from lino_loc.particle_filter import _CONSTANT, _GROUPS, _RENAMED, FilterConfig
from services.commands import config_cmd
from services.config import check_config


@pytest.fixture(autouse=True)
def _clean_env(monkeypatch):
    import os

    for k in list(os.environ):
        if k.upper().startswith("LINO_LOC__"):
            monkeypatch.delenv(k)


def test_renamed_key_names_the_new_one() -> None:
    with pytest.raises(ValidationError) as exc:
        LocalizerConfig(filter={"n_particles": 500, "lost_threshold": 10.0})
    (err,) = exc.value.errors()
    assert "filter.lost_threshold was renamed: use filter.lost.threshold" in err["msg"]


def test_key_that_became_a_constant_names_the_constant() -> None:
    with pytest.raises(ValidationError, match=r"filter\.lost_memory is no longer a setting "
                       r"\(the constant lino_loc\.lost_detection\.MEMORY\)"):
        FilterConfig(lost_memory=0.9)


def test_old_scalar_groups_name_their_field() -> None:
    with pytest.raises(ValidationError, match=r"filter\.recovery = 'amcl' was renamed: use "
                       r"filter\.recovery\.mode"):
        FilterConfig(recovery="amcl")
    with pytest.raises(ValidationError, match=r"use filter\.appearance_change\.enabled"):
        FilterConfig(appearance_change=False)
    cfg = FilterConfig(recovery={"mode": "amcl"}, appearance_change={"enabled": False})
    assert cfg.recovery.mode == "amcl" and not cfg.appearance_change.enabled


def test_every_successor_exists() -> None:
    cfg = FilterConfig()
    for new in list(_RENAMED.values()) + list(_GROUPS.values()):
        obj = cfg
        for part in new.split("."):
            obj = getattr(obj, part)  # the new key is a setting
    for const in _CONSTANT.values():
        module, name = const.rsplit(".", 1)
        assert hasattr(importlib.import_module(f"lino_loc.{module}"), name), const
    assert not set(_RENAMED) & set(FilterConfig.model_fields)
    assert not set(_CONSTANT) & set(FilterConfig.model_fields)


def test_config_check_prints_one_line_and_exits_2(tmp_path, capsys) -> None:
    path = tmp_path / "old.toml"
    path.write_text("[localizer.filter]\nn_particles = 500\nlost_threshold = 10.0\n")
    problems = check_config(path)
    assert problems == [
        f"{path}: localizer.filter: filter.lost_threshold was renamed: use filter.lost.threshold"
    ]
    parser = argparse.ArgumentParser()
    config_cmd.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["config", "check", str(path)])
    assert args.func(args) == 2
    assert capsys.readouterr().out.splitlines() == problems


def test_new_keys_load_from_toml(tmp_path) -> None:
    path = tmp_path / "new.toml"
    path.write_text(
        "[localizer.filter]\nn_particles = 500\n[localizer.filter.lost]\nthreshold = 10.0\n"
        "[localizer.filter.recovery]\nmode = \"amcl\"\n"
    )
    assert [p for p in check_config(path) if ": map.path: " not in p] == []  # the map is not here


def test_an_old_filter_key_from_the_environment_is_one_line(monkeypatch) -> None:
    monkeypatch.setenv("LINO_LOC__LOCALIZER__FILTER__LOST_MEMORY", "0.9")
    lino = Path(__file__).resolve().parents[1] / "config" / "lino.toml"
    assert check_config(lino) == [
        f"{lino}: localizer.filter: filter.lost_memory is no longer a setting "
        "(the constant lino_loc.lost_detection.MEMORY)"
    ]
