"""`lino-loc`: the one console script.

Each command group lives in its own module under ``services.commands`` and exposes
``register(subparsers)``, which adds its sub-parser(s) and sets ``func`` on them. ``func``
receives the parsed arguments and returns the exit status.

Exit status: 0 success, 2 bad usage or bad input (one line on stderr, no traceback),
1 internal failure. With ``--json`` a command prints exactly one JSON object on stdout;
logs go to stderr.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from collections.abc import Sequence

# One BLAS/OpenMP thread, set before numpy loads: the products here are small and a threaded
# BLAS costs more than it gains on a small robot computer (docs/results.md).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from lino_loc.errors import LinoLocError  # noqa: E402

# Order here is the order in `lino-loc --help`.
COMMAND_MODULES: tuple[str, ...] = (
    "services.commands.survey_cmd",
    "services.commands.map",
    "services.evaluation.commands.eval_cmd",
    "services.commands.dataset_cmd",
    "services.evaluation.commands.bench_cmd",
    "services.commands.config_cmd",
    "services.commands.echo",
    "services.commands.keys_cmd",
    "services.commands.run",
    "services.commands.replay_cmd",
    "services.commands.export_cmd",
    "services.commands.plot_cmd",
    "services.commands.sim",
)

log = logging.getLogger("lino_loc")


class _ArgumentParser(argparse.ArgumentParser):
    """argparse that exits with status 2 and a one-line message (it already does; keep it)."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _ArgumentParser(
        prog="lino-loc",
        description="Appearance-based visual localization for indoor service robots.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output on stderr")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_ArgumentParser)
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    os.environ.setdefault("DEPTHAI_LEVEL", "error")
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2) if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        return int(args.func(args) or 0)
    except LinoLocError as exc:
        print(f"lino-loc: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("lino-loc: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
