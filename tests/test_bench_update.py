"""`lino-loc bench update` machinery on a tiny map: the JSON has the promised keys and sane values."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from drivers.sim.drive import DriveConfig, plan_drive
from drivers.sim.world import load_world
from services.evaluation import machine, update_cost
from services.evaluation.commands import bench_cmd
from services.evaluation.views import ViewSpec, build_sim_maps, render_grey


@pytest.fixture(scope="module")
def tiny():
    amap = build_sim_maps("office", 1.5, 45.0, 4, ("none",), width=80, height=60, size=(40, 30),
                          cache=False, workers=1)["none"]
    plan = plan_drive(load_world("office"), DriveConfig(duration=2.0, camera_rate=5.0), seed=1)
    images = render_grey(ViewSpec(world="office", width=80, height=60, size=(40, 30)), plan.truth, workers=1)
    return amap, (images, plan.increments, plan.truth)


def test_bench_json_has_the_keys(tiny) -> None:
    amap, frames = tiny
    n = len(amap)
    res = update_cost.run_update_bench(repeats=6, particles=(50, 200), map_sizes=(n // 2, 4 * n), amap=amap, frames=frames)
    assert set(res["update_ms"]) == {"50", "200"}
    for r in res["update_ms"].values():
        assert 0.0 < r["min"] <= r["median"] <= r["p99"]
        assert r["updates"] >= 6
    small, big = res["map_scaling"][str(n // 2)], res["map_scaling"][str(4 * n)]
    assert small["entries"] == n // 2 and not small["synthetic"]
    assert big["entries"] == 4 * n and big["synthetic"]
    assert small["search_median_ms"] > 0.0
    m = res["machine"]
    assert {"platform", "cpu_count", "load_average", "cpu"} <= set(m)
    assert res["image"] == [80, 60]
    assert res["target"]["median_ms_max"] == 2.0
    st = res["standing_ms"]  # the tiny map is a lattice (1.5 m x 45 deg): the match keeps its views
    # one view per pan on the map's 45 deg heading lattice: 7 of the 8 pans are distinct there
    assert st["lattice"] and st["views_kept"] == 7 and st["particles"] == 1000
    assert st["matches"] >= 1  # the match acted: its cost is in the "on" times
    for arm in ("on", "off"):
        assert 0.0 < st[arm]["min"] <= st[arm]["median"] <= st[arm]["p99"]


def test_resized_map_keeps_features_consistent(tiny) -> None:
    amap, _ = tiny
    rng = np.random.default_rng(0)
    sub, syn = update_cost._resized_map(amap, 10, rng)
    assert not syn and len(sub) == 10 and sub.channels["intensity"].features.shape == (10, 4)
    big, syn = update_cost._resized_map(amap, 3 * len(amap) + 1, rng)
    assert syn and big.poses.shape == (3 * len(amap) + 1, 3)
    assert big.channels["intensity"].features.shape[0] == big.poses.shape[0]


def test_bench_group_registers_update_and_is_extensible() -> None:
    assert isinstance(bench_cmd.BENCH_MODULES, tuple)
    parser = argparse.ArgumentParser()
    bench_cmd.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["bench", "update", "--json", "--repeats", "7"])
    assert args.repeats == 7 and args.json and args.func is bench_cmd._update


def test_single_threaded_needs_every_variable(monkeypatch) -> None:
    for v in machine.THREAD_VARS:
        monkeypatch.setenv(v, "1")
    assert machine.single_threaded()
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    assert not machine.single_threaded()
