"""`lino-loc eval ...`: the paper's experiments, each printing a table or (--json) one object.

Sub-commands register themselves from their own modules through ``register_eval``.
"""

from __future__ import annotations

import argparse
import importlib

EVAL_MODULES: tuple[str, ...] = (
    "services.evaluation.commands.illumination_cmd",
    "services.evaluation.commands.single_view_cmd",
    "services.evaluation.commands.stereo_cmd",
    "services.evaluation.commands.active_cmd",
    "services.evaluation.commands.localization_cmd",
    "services.evaluation.commands.sensor_model_cmd",
)


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("eval", help="run an evaluation of the paper's experiments")
    eval_sub = parser.add_subparsers(dest="evaluation", metavar="EVALUATION", parser_class=type(parser))
    eval_sub.required = True
    for name in EVAL_MODULES:
        importlib.import_module(name).register_eval(eval_sub)
