"""`lino-loc echo`: print the daemon's ZeroMQ stream (docs/zeromq.md).

A plain SUB client: connects to the PUB endpoint, subscribes to the chosen topics and
prints one line per message, ``topic json`` (the payload exactly as received). With
``--count N`` it exits after N messages; with ``--timeout S`` it exits with status 1 when
nothing arrives for S seconds. Ctrl-C ends it quietly (status 0), as does a closed pipe
(``lino-loc echo | head``). With ``--json`` it prints, at the end, one JSON object
``{"endpoint", "topics", "count", "messages": [{"topic", "payload"}, ...]}``.

A daemon with CURVE keys (``[endpoints.curve]``) is read with ``--curve-server-key FILE``
(the daemon's public ``server.key``) and ``--curve-client-key FILE`` (this client's
``NAME.key_secret``, whose public half is in the daemon's ``authorized_clients`` folder);
without them, or with a key the daemon does not know, nothing arrives (ZeroMQ drops the
handshake silently), which ``--timeout`` turns into status 1.

Late joining: a SUB socket only receives what is published after its subscription reached
the publisher (ZeroMQ's "slow joiner"), so the first few milliseconds of the stream are
never seen; that is harmless for a live stream.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any

from services.messages import TOPICS, decode

DEFAULT_ENDPOINT = "tcp://127.0.0.1:5556"


def _positive_int(text: str) -> int:
    n = int(text)
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {n}")
    return n


def _positive_float(text: str) -> float:
    x = float(text)
    if not x > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return x


def _emit(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def run_echo(args: argparse.Namespace) -> int:
    import zmq

    from services.curve_auth import CurveKeyError, set_client_keys

    topics = sorted(TOPICS) if args.all else (args.topic or ["pose"])
    wanted = {t.encode() for t in topics}
    collected: list[dict[str, Any]] = []
    warned_frames = False
    status = 0
    ctx = zmq.Context()
    sock = ctx.socket(zmq.SUB)
    sock.setsockopt(zmq.LINGER, 0)
    try:
        for t in topics:
            sock.setsockopt(zmq.SUBSCRIBE, t.encode())
        if args.curve_server_key or args.curve_client_key:
            if not (args.curve_server_key and args.curve_client_key):
                print("lino-loc echo: CURVE needs both --curve-server-key and --curve-client-key", file=sys.stderr)
                return 2
            try:
                set_client_keys(sock, args.curve_server_key, args.curve_client_key)
            except CurveKeyError as exc:
                print(f"lino-loc echo: {exc}", file=sys.stderr)
                return 2
        try:
            sock.connect(args.endpoint)
        except zmq.ZMQError as exc:
            print(f"lino-loc echo: cannot connect to {args.endpoint!r}: {exc}", file=sys.stderr)
            return 2
        received = 0
        timeout_ms = None if args.timeout is None else int(args.timeout * 1000)
        while args.count is None or received < args.count:
            if timeout_ms is not None and not sock.poll(timeout_ms):
                print(
                    f"lino-loc echo: no {'/'.join(topics)} message on {args.endpoint} within "
                    f"{args.timeout:g} s (is `lino-loc run` publishing there?)",
                    file=sys.stderr,
                )
                status = 1
                break
            frames = sock.recv_multipart()
            if len(frames) != 2:
                if not warned_frames:
                    print(f"lino-loc echo: skipping a {len(frames)}-frame message "
                          "(expected [topic, json])", file=sys.stderr)
                    warned_frames = True
                continue
            topic_b, payload_b = frames
            if topic_b not in wanted:  # SUB filters by prefix; keep exact topics only
                continue
            received += 1
            topic = topic_b.decode("ascii", errors="replace")
            payload = payload_b.decode("utf-8", errors="replace")
            if args.validate:
                try:
                    decode(frames)
                except ValueError as exc:
                    print(f"lino-loc echo: invalid message: {exc}", file=sys.stderr)
            if args.json:
                try:
                    collected.append({"topic": topic, "payload": json.loads(payload)})
                except json.JSONDecodeError:
                    collected.append({"topic": topic, "payload": payload})
            else:
                _emit(f"{topic} {payload}")
    except KeyboardInterrupt:
        status = 0  # Ctrl-C is how a stream viewer is normally stopped
    except BrokenPipeError:
        # The reader went away (`| head`): stop quietly; silence the flush at exit too.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    finally:
        sock.close(linger=0)
        ctx.term()
    if args.json:
        out: dict[str, Any] = {
            "endpoint": args.endpoint,
            "topics": topics,
            "count": len(collected),
            "messages": collected,
        }
        if status:
            out["error"] = f"no message within {args.timeout:g} s"
        print(json.dumps(out))
    return status


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--topic",
        action="append",
        choices=sorted(TOPICS),
        help="topic to print (repeatable; default: pose)",
    )
    p.add_argument("--all", action="store_true", help="every topic")
    p.add_argument(
        "--endpoint",
        default=DEFAULT_ENDPOINT,
        help=f"PUB endpoint of the daemon (default {DEFAULT_ENDPOINT})",
    )
    p.add_argument(
        "--curve-server-key", metavar="FILE",
        help="the daemon's public key file (server.key): connect with CURVE",
    )
    p.add_argument(
        "--curve-client-key", metavar="FILE",
        help="this client's key pair (NAME.key_secret), authorized by the daemon",
    )
    p.add_argument("--count", type=_positive_int, metavar="N", help="exit after N messages")
    p.add_argument(
        "--timeout",
        type=_positive_float,
        metavar="S",
        help="exit with status 1 if no message arrives for S seconds",
    )
    p.add_argument(
        "--validate", action="store_true", help="check each payload against its schema (stderr)"
    )
    p.add_argument(
        "--json", action="store_true", help="print one JSON object with all messages at the end"
    )


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "echo",
        help="print the pose/status/particles/truth stream of a running daemon",
        description="Print `topic json` lines from the daemon's ZeroMQ PUB socket.",
    )
    add_arguments(p)
    p.set_defaults(func=run_echo)


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry: ``python -m services.commands.echo [options]``."""
    p = argparse.ArgumentParser(prog="lino-loc echo")
    add_arguments(p)
    return run_echo(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
