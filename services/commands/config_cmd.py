"""`lino-loc config ...`: check a configuration file, show the effective configuration.

- ``lino-loc config check FILE...``: every problem, one line each, as
  ``FILE: section.field: message`` (environment overrides included); exit 2 if any, else
  ``FILE: ok`` and exit 0. A key that is no longer a setting, or was renamed
  (``services.config.RETIRED_KEYS``), is one such line naming its new key. A valid file is
  then checked against the file system (``services.config.file_problems``): a missing map,
  a state folder that cannot be created, ... are lines ``FILE: key: path: why``.
- ``lino-loc config show [--config FILE] [--json]``: the effective configuration (defaults,
  then FILE, then ``LINO_LOC__*`` variables) as TOML, or as one JSON object.
- ``lino-loc config schema``: the JSON Schema of the configuration (for editors).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from services.config import (
    ConfigError,
    ServiceConfig,
    check_config,
    config_as_dict,
    load_config,
    to_toml,
)


def _check(args: argparse.Namespace) -> int:
    results = {}
    for path in args.files:
        results[path] = check_config(path)
    bad = any(results.values())
    if args.json:
        print(json.dumps({"ok": not bad, "files": {p: {"ok": not e, "errors": e} for p, e in results.items()}}))
    else:
        for path, problems in results.items():
            if problems:
                for line in problems:
                    print(line)
            else:
                print(f"{path}: ok")
    return 2 if bad else 0


def _show(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)  # ConfigError -> exit 2 with its first line
    data = config_as_dict(cfg)
    if args.json:
        text = json.dumps(data)
    else:
        source = args.config or "defaults"
        text = f"# lino-loc effective configuration ({source} + LINO_LOC__* environment)\n" + to_toml(data)
    try:
        print(text, flush=True)
    except BrokenPipeError:  # `lino-loc config show | head`
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0


def _schema(args: argparse.Namespace) -> int:
    print(json.dumps(ServiceConfig.model_json_schema(), indent=None if args.compact else 2))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("config", help="check or show the service configuration")
    csub = parser.add_subparsers(dest="config_command", metavar="ACTION", parser_class=type(parser))
    csub.required = True

    p = csub.add_parser(
        "check",
        help="validate configuration file(s): every error as FILE: section.field: message",
    )
    p.add_argument("files", nargs="+", metavar="FILE", help="TOML configuration file")
    p.add_argument("--json", action="store_true", help="one JSON object with the errors per file")
    p.set_defaults(func=_check)

    p = csub.add_parser("show", help="print the effective configuration (TOML, or --json)")
    p.add_argument("--config", metavar="FILE", help="TOML configuration file (default: built-in defaults)")
    p.add_argument("--json", action="store_true", help="one JSON object instead of TOML")
    p.set_defaults(func=_show)

    p = csub.add_parser("schema", help="print the configuration's JSON Schema")
    p.add_argument("--compact", action="store_true", help="one line")
    p.set_defaults(func=_schema)


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry (``python -m services.commands.config_cmd``), same as ``lino-loc config``."""
    from services.cli import _ArgumentParser

    parser = _ArgumentParser(prog="lino-loc")
    register(parser.add_subparsers(dest="command", parser_class=_ArgumentParser))
    args = parser.parse_args(["config", *(sys.argv[1:] if argv is None else argv)])
    try:
        return int(args.func(args))
    except ConfigError as exc:
        print(f"lino-loc: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
