"""The disparity channel in the localization evaluations (``--channels intensity,disparity``),
on tiny inputs: the frames the camera delivers, the map's second channel, a fused run, and
the option's errors."""

from __future__ import annotations

import numpy as np
import pytest

from services.cli import main as cli_main
from services.evaluation import tracking
from services.evaluation.commands.localization_cmd import parse_channels
from services.evaluation.views import (
    ViewSpec,
    build_sim_maps,
    render_frames,
    render_grey,
    render_vectors,
)

SMALL = {"width": 160, "height": 120, "size": (40, 30)}
POSES = np.array([[1.0, 1.0, 0.0], [2.0, 1.5, 1.2], [6.0, 0.5, -2.0]])


def test_frames_are_the_grey_images_and_the_survey_disparity_of_the_same_pairs() -> None:
    spec = ViewSpec(world="office", lighting="bulb", width=160, height=120, size=(40, 30), seed=3, disparity=True)
    grey, disp = render_frames(spec, POSES, workers=1)
    assert disp is not None and disp.shape == (3, 30, 40) and disp.dtype == np.float32
    # the grey images are render_grey's (the left image of the pair, same noise)
    np.testing.assert_array_equal(grey, render_grey(spec, POSES, workers=1))
    # the disparity is what the map's survey vectors hold for the same views
    vec = render_vectors(ViewSpec(**{**spec.__dict__, "preprocess": ()}), POSES, workers=1)["disparity"]
    np.testing.assert_array_equal(np.isnan(disp.reshape(3, -1)), np.isnan(vec))
    np.testing.assert_allclose(np.nan_to_num(disp.reshape(3, -1)), np.nan_to_num(vec))
    valid = np.isfinite(disp).mean()
    assert 0.05 < valid < 1.0  # sparse, as a stereo matcher is
    plain, none = render_frames(ViewSpec(**{**spec.__dict__, "disparity": False}), POSES, workers=1)
    assert none is None and np.array_equal(plain, grey)


@pytest.fixture(scope="module")
def fused_map():
    return build_sim_maps("office", 1.5, 45.0, 4, ("none",), cache=False, workers=1, disparity=True,
                          **SMALL)["none"]


def test_a_survey_map_with_disparity_has_both_channels_over_the_same_poses(fused_map) -> None:
    assert set(fused_map.channels) == {"intensity", "disparity"}
    d = fused_map.channels["disparity"]
    n = fused_map.poses.shape[0]
    assert d.features.shape == (n, 4) and fused_map.channels["intensity"].features.shape == (n, 4)
    assert d.method == "em-missing" and 0.0 < d.params["valid_fraction"] < 1.0
    assert np.all(np.isfinite(d.features))


def test_a_tracking_run_fuses_the_two_channels(fused_map) -> None:
    setup = tracking.TrackingSetup(world="office", step=1.5, heading_step_deg=45.0, features=4,
                                   preprocess=("none",), lights=("tube", "bulb"), scene_changes=(),
                                   duration=2.0, rate=2.0, particles=100, workers=1,
                                   channels=("intensity", "disparity"), compare_recovery=False,
                                   global_start=False, **SMALL)
    res = tracking.run(setup, maps={"none": fused_map})
    assert res["channels"] == ["intensity", "disparity"] and res["fusion"]["mode"] == "disjunctive"
    assert res["frames"] == 5 and set(res["conditions"]) == {"tube", "bulb"}
    assert res["light_switch"]["lights"] == ["tube", "bulb"]
    assert all(np.isfinite(r["mean_error_m"]) for r in res["conditions"].values())


@pytest.mark.parametrize("bad", ["disparity", "intensity,depth", "intensity,intensity", ""])
def test_channels_option_errors_are_one_line(bad: str, capsys) -> None:
    with pytest.raises(Exception, match="--channels"):
        parse_channels(bad)
    assert cli_main(["eval", "tracking", "--channels", bad, "--duration", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--channels" in err


def test_a_global_run_fuses_the_two_channels(fused_map) -> None:
    from lino_loc.localizer import LocalizerConfig
    from services.evaluation import global_loc

    setup = global_loc.GlobalSetup(starts=2, updates=3, particles=100, workers=1, step=1.5, heading_step_deg=45.0,
                                   channels=("intensity", "disparity"), **SMALL)
    res = global_loc.run(setup, LocalizerConfig(), appearance_map=fused_map)
    assert res["channels"] == ["intensity", "disparity"] and len(res["mean_error_m"]) == 3
    assert all(np.isfinite(res["mean_error_m"]))
