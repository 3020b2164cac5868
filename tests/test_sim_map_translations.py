"""The simulated robot's map with virtual translations (``[map.build] translations``): built
from the survey's stereo disparity, lattice positions only where the floor is free, both
channels; a bad setting is a one-line configuration error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivers.sim.world import load_world
from services.config import ConfigError, ServiceConfig, load_config
from services.sim_launcher import ensure_sim_map

BUILD = {"world": "office", "step": 2.0, "heading_step_deg": 90.0, "width": 96, "height": 72, "features": 4,
         "disparity": True, "disparity_features": 3}


def _config(path: Path, build: dict) -> ServiceConfig:
    return ServiceConfig(devices={"camera": {"kind": "sim"}}, map={"path": path, "build": build})


def test_translated_sim_map_holds_the_free_lattice_of_every_cell(tmp_path: Path) -> None:
    plain, _ = ensure_sim_map(_config(tmp_path / "plain.npz", BUILD))
    amap, built = ensure_sim_map(_config(tmp_path / "t3.npz", {**BUILD, "translations": 3}))
    assert built and set(amap.channels) == {"intensity", "disparity"}
    world = load_world("office")
    survey_xy = np.unique(np.round(plain.poses[:, :2], 6), axis=0)
    xy = np.unique(np.round(amap.poses[:, :2], 6), axis=0)
    assert xy.shape[0] > survey_xy.shape[0] and len(amap) > len(plain)
    # every position is a survey position plus a lattice offset (multiples of 2/3 m, within one)
    near = np.abs(xy[:, None, :] - survey_xy[None, :, :]).max(axis=2).min(axis=1)
    assert np.all(near <= 2.0 / 3.0 + 1e-6)
    assert np.all(world.is_free(xy[:, 0], xy[:, 1]))
    xmin, xmax, ymin, ymax = world.mapped_area
    assert np.all((xy[:, 0] >= xmin) & (xy[:, 0] <= xmax) & (xy[:, 1] >= ymin) & (xy[:, 1] <= ymax))
    # every lattice position holds its survey position's headings (a product grid)
    heads = {tuple(p): set() for p in xy}
    for p in amap.poses:
        heads[tuple(np.round(p[:2], 6))].add(round(float(p[2]) % (2 * np.pi), 3))
    assert len({len(h) for h in heads.values()}) == 1
    assert not (tmp_path / ".t3.survey.t3").exists()  # the working folders are removed


@pytest.mark.parametrize(("build", "text"), [
    ({**BUILD, "translations": 2}, "translations must be odd"),
    ({**BUILD, "disparity": False, "translations": 3}, "translations need the survey's stereo disparity"),
])
def test_bad_translation_settings_are_one_line(tmp_path: Path, build: dict, text: str) -> None:
    lines = "\n".join(f"{k} = {str(v).lower() if isinstance(v, bool) else repr(v).replace(chr(39), chr(34))}"
                      for k, v in build.items())
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[devices.camera]\nkind = "sim"\n[map]\npath = "{tmp_path / "m.npz"}"\n[map.build]\n{lines}\n')
    with pytest.raises(ConfigError) as err:
        load_config(cfg)
    assert text in str(err.value) and "\n" not in str(err.value)
