"""`lino-loc keys generate DIR [--client NAME]`: CURVE key pairs for the daemon and a client.

Writes, with ``zmq.auth.create_certificates`` (ZeroMQ certificate files, Curve25519)::

    DIR/server.key            the daemon's public key: give it to every client
    DIR/server.key_secret     the daemon's key pair: endpoints.curve.server_secret_key
    DIR/clients/NAME.key      the client's public key; the folder is endpoints.curve.authorized_clients
    DIR/NAME.key_secret       the client's key pair: give it to that client only

(``NAME`` is ``client`` unless ``--client`` says otherwise.) Every file is readable by its
owner only (0600), the folders 0700: run it as the user the daemon runs as, or ``chown`` the
folder to it. A second client: ``lino-loc keys generate DIR --client NAME`` again adds
``DIR/clients/NAME.key`` and ``DIR/NAME.key_secret`` and keeps the server's pair. An existing
key file is never overwritten (exit 2, one line). ``--json`` prints the paths as one object.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import tempfile
from pathlib import Path

_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
SERVER_NAME = "server"


def _private_dir(path: Path) -> None:
    path.mkdir(parents=True, exist_ok=True)
    os.chmod(path, 0o700)


def _create(name: str, dest_public: Path, dest_secret: Path) -> None:
    """One key pair: the public file to ``dest_public``, the pair to ``dest_secret`` (0600)."""
    import zmq.auth  # noqa: PLC0415 - only this command needs it

    with tempfile.TemporaryDirectory(dir=dest_secret.parent) as tmp:
        os.chmod(tmp, 0o700)
        public, secret = zmq.auth.create_certificates(tmp, name)
        for src, dst in ((public, dest_public), (secret, dest_secret)):
            os.chmod(src, 0o600)
            os.replace(src, dst)


def generate(folder: Path, client: str) -> dict[str, str]:
    """Create the server pair (unless present) and the client pair in ``folder``; the paths
    by role. Raises FileExistsError when the client's files exist already."""
    clients = folder / "clients"
    paths = {
        "server_public": folder / f"{SERVER_NAME}.key",
        "server_secret": folder / f"{SERVER_NAME}.key_secret",
        "client_public": clients / f"{client}.key",
        "client_secret": folder / f"{client}.key_secret",
        "authorized_clients": clients,
    }
    for key in ("client_public", "client_secret"):
        if paths[key].exists():
            raise FileExistsError(f"{paths[key]} exists already (remove it to make a new key)")
    server_there = [paths[k].exists() for k in ("server_public", "server_secret")]
    if any(server_there) and not all(server_there):
        have = paths["server_public"] if server_there[0] else paths["server_secret"]
        raise FileExistsError(f"{have} exists without the other half of the server's pair")
    _private_dir(folder)
    _private_dir(clients)
    if not all(server_there):
        _create(SERVER_NAME, paths["server_public"], paths["server_secret"])
    _create(client, paths["client_public"], paths["client_secret"])
    return {k: str(v) for k, v in paths.items()}


def run_generate(args: argparse.Namespace) -> int:
    if not _NAME_RE.match(args.client) or args.client == SERVER_NAME:
        print(f"lino-loc keys: --client {args.client!r}: use letters, digits, '_', '.', '-' "
              f"(and not {SERVER_NAME!r})", file=sys.stderr)
        return 2
    folder = Path(args.dir).expanduser()
    if folder.exists() and not folder.is_dir():
        print(f"lino-loc keys: {folder} is not a folder", file=sys.stderr)
        return 2
    try:
        paths = generate(folder, args.client)
    except (FileExistsError, PermissionError) as exc:
        print(f"lino-loc keys: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(paths))
    else:
        print(
            f"server: {paths['server_secret']} (endpoints.curve.server_secret_key), public {paths['server_public']}\n"
            f"client {args.client}: {paths['client_secret']} (give it to the client), "
            f"public {paths['client_public']}\n"
            f"[endpoints.curve]\n"
            f"server_secret_key = {json.dumps(paths['server_secret'])}\n"
            f"authorized_clients = {json.dumps(paths['authorized_clients'])}"
        )
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "keys",
        help="CURVE keys for serving the ZeroMQ sockets off loopback",
        description="Make the CURVE key pairs the daemon and its clients need (docs/zeromq.md).",
    )
    ks = p.add_subparsers(dest="keys_command", metavar="ACTION", parser_class=type(p))
    ks.required = True
    g = ks.add_parser(
        "generate",
        help="the daemon's key pair and one client's (files readable by their owner only)",
        description=(__doc__ or "").split("\n\n", 1)[1].split("\n\n(")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    g.add_argument("dir", metavar="DIR", help="folder for the keys (created, mode 0700)")
    g.add_argument("--client", default="client", metavar="NAME", help="the client key's name (default client)")
    g.add_argument("--json", action="store_true", help="print the paths as one JSON object")
    g.set_defaults(func=run_generate)
