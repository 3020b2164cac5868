"""How long the running service takes to notice that the lights were switched.

Runs the simulated service as real processes (:mod:`benchmarks.sim_service_rig`: ``lino-loc
sim --switch-lighting bulb`` plus ``lino-loc run``; by default the integration tests' office
map, 80 x 60 images at 5 fps, as ``tests/test_light_switch_service.py``). Per session: once
the daemon has published ``--poses`` poses under the mapping light, SIGUSR2 switches the
simulator's lights to bulb; the delay is the time from the signal to the daemon's
``appearance_changes`` count (its ``status`` on the control socket, polled every 0.2 s)
rising, or ``null`` when it does not within ``--window`` seconds. Later reports within the
window (a second change under the same light) are counted. The sessions differ only in
timing: where the robot drives when the lights switch.

Prints one JSON object: the delays, their median and maximum, the share found within 30 s and
within the window, the load average before and after.

Usage::

    python benchmarks/bench_light_switch_delay.py                  # 5 sessions, 60 s window
    python benchmarks/bench_light_switch_delay.py --sessions 2 --window 30   # quick
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.sim_service_rig import Rig, Settings, Stream, exit_on_sigterm, request  # noqa: E402


def _changes(rig: Rig) -> int:
    reply = request(rig.rep, {"cmd": "status"})
    return int(reply["status"]["appearance_changes"]) if reply.get("ok") else -1


def one_session(tmp: Path, settings: Settings, args: argparse.Namespace) -> dict[str, Any]:
    """One simulator and daemon; the switch; the delays of the reports after it."""
    rig = Rig(tmp, settings)
    rig.start_sim("--switch-lighting", "bulb")
    stream = Stream(rig.pub, rig.truth)
    rig.start_daemon()
    try:
        if not stream.wait_for(lambda: len(stream.poses) >= args.poses, 120):
            raise SystemExit(f"no poses: {rig.daemon_log.read_text()[-2000:]}")
        before = _changes(rig)
        assert rig.sim is not None
        rig.sim.send_signal(signal.SIGUSR2)
        t_switch, seen, reports = time.time(), before, []
        while time.time() < t_switch + args.window:
            time.sleep(0.2)
            n = _changes(rig)
            if n > seen:
                reports += [round(time.time() - t_switch, 1)] * (n - seen)
                seen = n
    finally:
        rig.close()
        stream.close()
    return {"delay_s": reports[0] if reports else None, "reports_s": reports}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=5)
    ap.add_argument("--window", type=float, default=60.0, help="seconds after the switch to wait for a report")
    ap.add_argument("--poses", type=int, default=150, help="poses under the mapping light before the switch "
                    "(150: 30 s at 5 fps, as tests/test_light_switch_service.py; 40: a switch 8 s after the start)")
    ap.add_argument("--fps", type=float, default=5.0)
    args = ap.parse_args()
    exit_on_sigterm()
    settings = Settings(fps=args.fps)
    load0 = os.getloadavg()
    sessions = []
    for k in range(args.sessions):
        with tempfile.TemporaryDirectory(prefix=f"lino-loc-switch-{k}-") as d:
            sessions.append(one_session(Path(d), settings, args))
    found = [s["delay_s"] for s in sessions if s["delay_s"] is not None]
    print(json.dumps({
        "sessions": sessions,
        "found": f"{len(found)} of {len(sessions)}",
        "median_s": statistics.median(found) if found else None,
        "max_s": max(found) if found else None,
        "within_30_s_share": sum(d <= 30.0 for d in found) / len(sessions),
        "within_window_share": len(found) / len(sessions),
        "window_s": args.window,
        "loadavg": {"before": load0, "after": os.getloadavg()},
    }, indent=2))


if __name__ == "__main__":
    main()
