"""The single-image ambiguity evaluation on a small office map."""

import numpy as np

from services.evaluation.single_view import SingleViewSetup, off_grid_poses, run


def test_off_grid_poses_are_off_the_grid_and_free():
    grid = np.array([[1.0, 1.0, 0.0], [2.0, 1.0, 0.0]])
    poses = off_grid_poses("office", grid, 50, 0.3, seed=3)
    assert poses.shape == (50, 3)
    d = np.min(np.hypot(poses[:, None, 0] - grid[None, :, 0], poses[:, None, 1] - grid[None, :, 1]), axis=1)
    assert np.all(d >= 0.3)


def test_single_view_small_run(tmp_path, monkeypatch):
    monkeypatch.setenv("LINO_LOC_CACHE", str(tmp_path))
    setup = SingleViewSetup(step=1.5, heading_step_deg=45.0, views=24, width=80, height=60, workers=1)
    r = run(setup)
    assert r["views"] == 24 and r["J"] == 10
    for key in ("top1_success", "success_within_J", "chance_success", "top1_success_pose", "success_within_J_pose"):
        assert 0.0 <= r[key] <= 1.0
    # The J nearest include the nearest, and the appearance beats chance by a wide margin.
    assert r["success_within_J"] >= r["top1_success"]
    assert r["success_within_J"] > r["chance_success"] + 0.2
