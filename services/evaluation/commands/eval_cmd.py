"""`lino-loc eval ...`: the paper's experiments, each printing a table or (--json) one object.

Sub-commands register themselves from their own modules through ``register_eval``.
"""

from __future__ import annotations

import argparse
import importlib

EVAL_MODULES: tuple[str, ...] = (
    "services.commands.illumination_eval",
    "services.commands.single_view_eval",
    "services.commands.stereo_eval",
    "services.commands.active_eval",
    "services.commands.localization_eval",
    "services.commands.sensor_model_eval",
)


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("eval", help="run an evaluation of the paper's experiments")
    eval_sub = parser.add_subparsers(dest="evaluation", metavar="EVALUATION", parser_class=type(parser))
    eval_sub.required = True
    for name in EVAL_MODULES:
        importlib.import_module(name).register_eval(eval_sub)
