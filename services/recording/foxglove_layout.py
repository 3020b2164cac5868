"""The Foxglove layout of a live view and a recording: ``docs/foxglove-layout.json``.

``python -m services.recording.foxglove_layout [FILE]`` writes it (default: the repository's
docs/foxglove-layout.json); ``tests/test_live_view.py`` keeps the committed file equal to
:func:`layout`.

The file is a layout as Foxglove exports and imports it (Layouts > Import from file):
``configById`` (panel id ``Type!name`` -> the panel's configuration), ``layout`` (the
split tree: ``first``, ``second``, ``direction``, ``splitPercentage``), ``globalVariables``,
``userNodes``, ``playbackConfig``. Each panel's configuration is built with foxglove-sdk's
layout types (``foxglove.layouts``: keyword-only dataclasses, so a misspelt setting is an
error, and their JSON keys are Foxglove's) and taken from their JSON.

Panels:

- **3D** (``3D!map``), displayed in ``map`` from above: the pose (an arrow), the 95 %
  ellipse, the particles (small arrows), the truth (simulation), the survey poses and the
  outline, the frames of ``/tf`` (``base_link``, ``camera``), a 1 m grid;
- **Image** (``Image!camera``): ``/camera/image``;
- **State transitions** (``StateTransitions!state``): ``/pose/estimate.state``;
- **Plot** (``Plot!quality``): the estimate's quality (0-1);
- **Raw messages** (``RawMessages!status``): ``/status``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from services.recording.channels import MAP_FRAME

#: Where the layout is committed.
LAYOUT_FILE = Path(__file__).resolve().parents[2] / "docs" / "foxglove-layout.json"


def _config(panel: Any) -> dict[str, Any]:
    """A panel's configuration as foxglove-sdk writes it."""
    import foxglove.layouts as fl

    return json.loads(fl.Layout(content=panel).to_json())["content"]["config"]


def _three_d() -> dict[str, Any]:
    import foxglove.layouts as fl

    topics = {
        "/pose": fl.BaseRendererPoseTopicSettings(visible=True, type="arrow", color="#1f9d3aff",
                                                  arrow_scale=(0.5, 0.1, 0.1)),
        "/pose/ellipse": fl.BaseRendererSceneUpdateTopicSettings(visible=True),
        "/particles": fl.BaseRendererPosesTopicSettings(visible=True, type="arrow",
                                                        arrow_scale=(0.12, 0.02, 0.02)),
        "/truth/pose": fl.BaseRendererPoseTopicSettings(visible=True, type="arrow", color="#7a2fc4ff",
                                                        arrow_scale=(0.5, 0.1, 0.1)),
        "/map/survey": fl.BaseRendererSceneUpdateTopicSettings(visible=True),
        "/map/outline": fl.BaseRendererSceneUpdateTopicSettings(visible=True),
    }
    grid = fl.BaseRendererGridLayerSettings(instance_id="grid", label="Grid", visible=True, frame_id=MAP_FRAME, size=20, divisions=20,
                                            line_width=0.5, color="#248eff40", position=(0.0, 0.0, -0.01))
    return _config(fl.ThreeDeePanel(config=fl.ThreeDeeConfig(
        follow_tf=MAP_FRAME, fixed_frame=MAP_FRAME, follow_mode="follow-none",
        camera_state=fl.ThreeDeeCameraState(perspective=False, distance=14.0, phi=0.0, theta_offset=90.0,
                                            target_offset=(4.0, 1.25, 0.0)),
        scene=fl.BaseRendererSceneSettings(transforms=fl.BaseRendererTransforms(show_label=True,
                                                                                 axis_size=0.3)),
        topics=topics, layers={"grid": grid},
    )))


def _panels() -> dict[str, dict[str, Any]]:
    import foxglove.layouts as fl

    return {
        "3D!map": _three_d(),
        "Image!camera": _config(fl.ImagePanel(config=fl.ImageConfig(
            image_mode=fl.ImageModeConfig(image_topic="/camera/image")))),
        "StateTransitions!state": _config(fl.StateTransitionsPanel(config=fl.StateTransitionsConfig(
            paths=[fl.StateTransitionsSeries(value="/pose/estimate.state", label="state",
                                             timestamp_method="receiveTime")]))),
        "Plot!quality": _config(fl.PlotPanel(config=fl.PlotConfig(
            paths=[fl.PlotSeries(value="/pose/estimate.quality", label="quality",
                                 timestamp_method="receiveTime")],
            show_legend=True, min_y_value=0.0, max_y_value=1.0))),
        "RawMessages!status": _config(fl.RawMessagesPanel(config=fl.RawMessagesConfig(
            topic_path="/status"))),
    }


def layout() -> dict[str, Any]:
    """The layout (module docstring), as Foxglove's exported layout files hold it."""
    return {
        "configById": _panels(),
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1},
        "layout": {
            "first": "3D!map",
            "second": {
                "first": "Image!camera",
                "second": {
                    "first": "StateTransitions!state",
                    "second": {"first": "Plot!quality", "second": "RawMessages!status",
                               "direction": "column", "splitPercentage": 50},
                    "direction": "column", "splitPercentage": 25,
                },
                "direction": "column", "splitPercentage": 40,
            },
            "direction": "row", "splitPercentage": 60,
        },
    }


def layout_text() -> str:
    return json.dumps(layout(), indent=2, sort_keys=False) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    path = Path(args[0]) if args else LAYOUT_FILE
    path.write_text(layout_text(), encoding="utf-8")
    print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
