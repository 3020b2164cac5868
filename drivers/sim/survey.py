"""Surveys of a simulated world: render a grid of poses and write a dataset folder.

:func:`run_survey` renders the camera view at every pose of :func:`grid_poses` (positions
every ``step`` metres over the world's mapped area, headings every ``heading_step_rad``;
poses where the robot's footprint touches furniture or walls are skipped) and writes the
dataset folder (docs/datasets.md) through :class:`lino_loc.dataset.DatasetWriter`: the left
(reference) image, the camera pose and the condition (the lighting name, joined with the
scene-change names by ``+`` when there are any). With ``stereo`` (the default) the right
image of the rectified pair goes to the ``right`` column / ``images_right/`` and the pair's
disparity, computed by the product's block matcher
(:func:`lino_loc.disparity.compute_disparity`, ``stereo_config``, default
:class:`~lino_loc.disparity.StereoConfig`), to the ``disparity`` column: sparse, with no
value where the matcher's checks fail, as a stereo camera delivers it. ``dataset.json``
then says ``disparity_source: "stereo-matcher"``. The renderer's dense depth (exact at
every pixel, which no stereo camera gives) is written only with ``dense_depth``, to the
``depth`` column *instead of* the matcher's disparity (a map built from it names its
disparity channel's source ``dense-depth``). The camera's baseline is recorded whenever
stereo or depth is written.

The grid does not depend on the lighting, so surveys of the same world under different
lights line up row by row. Scene changes that block a grid pose remove that pose (the
robot cannot stand inside a box); the rows then no longer line up with the unchanged
survey.

The camera sits on the robot's vertical axis with pan 0, so the camera pose written to
the dataset equals the robot pose.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.sim.renderer import CameraModel, Renderer
from drivers.sim.world import World, grid_poses, load_world
from lino_loc.dataset import CameraInfo, DatasetMeta, DatasetWriter
from lino_loc.disparity import StereoConfig, compute_disparity
from lino_loc.errors import LinoLocError

#: ``dataset.json``'s ``disparity_source`` of a survey whose disparity is the matcher's.
STEREO_MATCHER = "stereo-matcher"

__all__ = ["SurveyResult", "condition_name", "grid_poses", "run_survey", "survey_poses"]


@dataclass(frozen=True)
class SurveyResult:
    out: Path
    rows: int
    skipped_positions: int
    condition: str
    seconds: float


def condition_name(lighting: str, scene_changes: tuple[str, ...] | list[str] = ()) -> str:
    """Condition label of a survey row: ``tube``, ``bulb+people``, ..."""
    return "+".join((lighting, *scene_changes))


def survey_poses(
    world: World,
    step: float,
    heading_step_rad: float,
    radius: float = 0.25,
    scene_changes: tuple[str, ...] | list[str] = (),
) -> tuple[np.ndarray, int]:
    """The survey's poses (N, 3) and the number of grid positions skipped as blocked."""
    poses = grid_poses(world, step, heading_step_rad, radius, scene_changes)
    xmin, xmax, ymin, ymax = world.mapped_area
    nx = int(math.floor((xmax - xmin) / step + 1e-9)) + 1
    ny = int(math.floor((ymax - ymin) / step + 1e-9)) + 1
    nh = len(np.unique(np.round(poses[:, 2], 9))) if len(poses) else 1
    return poses, nx * ny - len(poses) // max(nh, 1)


def run_survey(
    world: World | str,
    out: str | Path,
    step: float = 0.75,
    heading_step_rad: float = math.radians(15.0),
    lighting: str = "tube",
    scene_changes: tuple[str, ...] | list[str] = (),
    camera: CameraModel | None = None,
    seed: int = 0,
    stereo: bool = True,
    overwrite: bool = False,
    radius: float = 0.25,
    progress: Callable[[int, int], None] | None = None,
    *,
    dense_depth: bool = False,
    stereo_config: StereoConfig | None = None,
) -> SurveyResult:
    """Render the survey grid of ``world`` under ``lighting`` and write a dataset folder.

    Row i's sensor noise comes from ``np.random.default_rng((seed, i))``, so a survey is
    reproducible and independent of how it is split. ``stereo``: right image and sparse
    matcher disparity per row; ``dense_depth``: the renderer's exact depth per row (see the
    module docstring). LinoLocError (before anything is rendered) if ``stereo`` and the
    image is too small for ``stereo_config``'s matcher."""
    import time

    t0 = time.perf_counter()
    w = load_world(world) if isinstance(world, str) else world
    changes = w.check_changes(tuple(scene_changes))
    w.check_lighting(lighting)
    cam = camera if camera is not None else CameraModel()
    matcher = stereo_config if stereo_config is not None else StereoConfig()
    if stereo and not dense_depth and not (min(cam.width, cam.height) >= matcher.block_size
                       and cam.width > matcher.num_disparities + matcher.min_disparity):
        raise LinoLocError(f"survey: a {cam.width}x{cam.height} image is too small for the stereo matcher "
                           f"(block {matcher.block_size}, {matcher.num_disparities} disparities); use --no-stereo")
    poses, skipped = survey_poses(w, step, heading_step_rad, radius, changes)
    renderer = Renderer(w, camera=cam, lighting=lighting, scene_changes=changes, seed=seed)
    fx, fy, cx, cy = cam.intrinsics()
    cond = condition_name(lighting, changes)
    meta = DatasetMeta(
        name=f"{w.name}-{cond}",
        camera=CameraInfo(width=cam.width, height=cam.height, fx=fx, fy=fy, cx=cx, cy=cy,
                          baseline_m=cam.baseline_m if (stereo or dense_depth) and cam.baseline_m > 0 else None),
        conditions=[cond],
        disparity_source=STEREO_MATCHER if stereo and not dense_depth else "",
        source=(f"lino-loc sim world={w.name} lighting={lighting} scene_changes={','.join(changes) or 'none'} "
                f"step={step} heading_step_deg={math.degrees(heading_step_rad):g} seed={seed} "
                f"camera_height_m={cam.height_m}"),
    )
    with DatasetWriter(out, meta, overwrite=overwrite) as writer:
        for i, (x, y, th) in enumerate(poses):
            view = renderer.render(float(x), float(y), float(th), stereo=stereo,
                                   rng=np.random.default_rng((seed, i)))
            disparity = compute_disparity(view.left, view.right, matcher) if stereo and not dense_depth else None
            writer.add(image=view.grey, pose=view.camera_pose, condition=cond,
                       depth=view.depth if dense_depth else None, disparity=disparity,
                       right=view.right if stereo else None)
            if progress is not None:
                progress(i + 1, len(poses))
    return SurveyResult(out=Path(out), rows=len(poses), skipped_positions=skipped, condition=cond,
                        seconds=time.perf_counter() - t0)
