"""Checks every simulated world must pass, shared by the per-world tests: its lights render
views that differ from each other, and each named scene change moves geometry and shows in
a view."""

from __future__ import annotations

import numpy as np

from drivers.sim.renderer import CameraModel, Renderer
from drivers.sim.world import World


def grey_view(r: Renderer, x: float, y: float, theta: float) -> np.ndarray:
    """The noiseless grey view at robot pose (x, y, theta), as float64."""
    return r.render(x, y, theta, noise=False, stereo=False).grey.astype(np.float64)


def assert_lights_differ(world: World, pose: tuple[float, float, float]) -> None:
    """Under every light the 48 x 36 view at ``pose`` has texture (std > 2 grey levels), and
    any two lights differ by more than 3 grey levels on average."""
    views = {}
    for light in world.lighting_names:
        r = Renderer(world, CameraModel(width=48, height=36), lighting=light)
        views[light] = grey_view(r, *pose)
        assert views[light].shape == (36, 48) and views[light].std() > 2.0
    for a, b in (("tube", "bulb"), ("tube", "natural"), ("bulb", "natural")):
        assert np.abs(views[a] - views[b]).mean() > 3.0, (a, b)


def assert_change_shows(world: World, r: Renderer, change: str, pose: tuple[float, float, float]) -> None:
    """The scene change ``change`` moves some geometry, and the view at ``pose`` through ``r``
    differs by more than 1 grey level on average with it; ``r`` is left without changes."""
    base = {(b.owner, round(b.cx, 3), round(b.cy, 3)) for b in world.geometry().boxes}
    changed = {(b.owner, round(b.cx, 3), round(b.cy, 3)) for b in world.geometry((change,)).boxes}
    assert base != changed
    r.set_scene_changes(())
    before = grey_view(r, *pose)
    r.set_scene_changes((change,))
    after = grey_view(r, *pose)
    r.set_scene_changes(())
    assert np.abs(before - after).mean() > 1.0
