"""The simulated service's cached map is keyed by the disparity channel's source."""

from __future__ import annotations

from drivers.sim.code_fingerprint import CACHE_CODE
from services.config import MapBuildConfig
from services.sim_launcher import _build_record


def test_build_record_changes_with_the_disparity_source() -> None:
    sparse = _build_record(MapBuildConfig(disparity=True), "world-fp")
    dense = _build_record(MapBuildConfig(disparity=True, disparity_source="dense-depth"), "world-fp")
    assert sparse["build"]["disparity_source"] == "stereo-matcher"
    assert sparse != dense
    # the survey's code (which decides where the disparity comes from) keys the cache too
    assert "drivers.sim.survey" in CACHE_CODE and "lino_loc.pca_missing" in CACHE_CODE


def test_build_record_keys_the_disparity_features_only_when_set() -> None:
    import pytest
    from pydantic import ValidationError

    plain = _build_record(MapBuildConfig(disparity=True, features=20), "world-fp")
    assert "disparity_features" not in plain["build"]  # maps cached before the setting existed stay valid
    fewer = _build_record(MapBuildConfig(disparity=True, features=20, disparity_features=5), "world-fp")
    assert fewer["build"]["disparity_features"] == 5 and fewer != plain
    with pytest.raises(ValidationError, match="disparity_features"):
        MapBuildConfig(disparity=True, disparity_features=0)
