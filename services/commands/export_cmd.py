"""`lino-loc export ros2 RECORDING [RECORDING ...] --out BAG [--json]`.

Writes a recording, or a replay's output, as a rosbag2 folder (MCAP storage) with ROS 2
message types (:mod:`services.ros2_export`): ``/amcl_pose``, ``/particle_cloud``, ``/tf``,
``/odom``, ``/camera/image_raw/compressed`` and, in simulation, ``/truth`` (and the truth as
TUM beside the bag, ``BAG-truth.tum``). Several RECORDINGs are the parts of one rotated
recording, in order. Prints one line (``--json``: one JSON object).

Exit status 2 with one line for a missing file, a file that is not MCAP, a recording without
a pose, an existing BAG, or without the ``ros2`` extra (rosbags) or the ``viz`` extra (mcap).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from lino_loc.errors import LinoLocError


def run_export_ros2(args: argparse.Namespace) -> int:
    from services.recording.channels import require_viz
    from services.ros2_export import require_rosbags

    require_viz("lino-loc export ros2")
    require_rosbags("lino-loc export ros2")
    from services.ros2_export import export_ros2

    files = [Path(f) for f in args.files]
    for f in files:
        if not f.is_file():
            raise LinoLocError(f"{f}: no such file")
    r = export_ros2(files, Path(args.out))
    summary = {"bag": str(r.bag), "messages": r.messages, "bytes": r.bytes, "span_s": round(r.span_s, 3),
               "wall_s": round(r.wall_s, 3), "truth_tum": str(r.truth_tum) if r.truth_tum else None,
               "truncated": r.truncated}
    if args.json:
        print(json.dumps(summary))
    else:
        counts = ", ".join(f"{n} {t}" for t, n in r.messages.items() if n)
        print(f"wrote {r.bag} ({r.bytes / 1e6:.1f} MB, {r.span_s:.1f} s of recording in {r.wall_s:.1f} s): "
              f"{counts}" + (f"; truth as TUM: {r.truth_tum}" if r.truth_tum else "")
              + (f"; {r.truncated}" if r.truncated else ""))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="write a recording in another format (ros2: a rosbag2)",
                       description="Export a recording or a replay's output.")
    formats = p.add_subparsers(dest="format", metavar="FORMAT", parser_class=type(p))
    formats.required = True
    r = formats.add_parser(
        "ros2", help="a rosbag2 (MCAP storage) with ROS 2 message types, for ros2 bag, evo, Foxglove",
        description="Write a rosbag2 folder: /amcl_pose (PoseWithCovarianceStamped), /particle_cloud "
        "(PoseArray), /tf (map->odom, odom->base_link, base_link->camera), /odom (Odometry), "
        "/camera/image_raw/compressed (CompressedImage) and, in simulation, /truth (PoseStamped) "
        "with BAG-truth.tum beside it.")
    r.add_argument("files", nargs="+", metavar="RECORDING", help="the recording (its parts in order) or a replay's OUT.mcap")
    r.add_argument("--out", required=True, metavar="BAG", help="the bag folder to create")
    r.add_argument("--json", action="store_true", help="one JSON object on stdout")
    r.set_defaults(func=run_export_ros2)
