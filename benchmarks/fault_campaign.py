"""The fault campaign: every fault the simulator can inject, against the running service.

Starts ``lino-loc sim`` and ``lino-loc run`` as two processes (:mod:`sim_service_rig`: the
office, 320 x 240 images at 15 fps by default (``--width``, ``--height``, ``--fps``), 1000
particles; fixed links and endpoints, so that a simulator started again offers the same
devices), waits until the daemon tracks, then runs one row per fault, in order:

- every fault of the simulator's fault control (:mod:`drivers.sim.fault_control`), each for
  ``--duration`` seconds: the head silent, CRC errors on the bus, the hardware-error bit
  (once), the bus adapter unplugged; CRC errors,
  garbage, dropped and split lines and the port lost on the odometry board; the camera
  stalled, unplugged and sending malformed frames;
- the lights switched (tube -> bulb, then back); then the persistent hardware error: the head
  adapter gives the servo up after 3 reboots in a minute and tries a new round of reboots
  ``GIVEN_UP_RETRY_S`` (60 s) later, so this row waits ``--retry-observe`` s (default
  ``GIVEN_UP_RETRY_S + INCIDENT_HOLD_S + --observe``) for the recovery;
- the daemon killed with SIGKILL and started again at once (it restores its saved pose);
- the simulator killed with SIGKILL while the daemon runs on, then started again at the true
  pose it had (the daemon's drivers find the devices again);
- ``lino-loc run`` with "auto" devices, whose own simulator is killed: README says the
  daemon says so and exits 1.

Before each row the service must be tracking (state ``tracking``, 3 poses within 0.5 m of the
truth); if it is not within ``--settle`` s, the row starts anyway and says so. Per row:

- ``poses_lost``: poses expected at the rate measured before the fault, minus poses received,
  from the injection to the end of the fault plus 2 s; ``dead_reckoning``: poses published
  without a camera frame in that time;
- ``longest_gap_s``: the longest time between two received poses around the fault;
- ``error_during_m`` (median / max) from the injection to the fault's end, ``error_after_m``
  (median) over the last 3 s of the row: position error against the simulator's truth;
- ``health``: the worst state each device reported in ``status`` during the row, and the
  counters that moved (the devices' and the status's own: ``appearance_changes``,
  ``update_errors``, frames dropped or out of order); ``sequence``: each device's states in
  the statuses of the row, with the seconds since the injection at which each began;
- ``reported_after_s``: from the injection to the first status that reports the fault: a
  device not ``ok``, the filter's state not ``tracking``, a status counter grown, or a restarted
  daemon (its uptime started again); ``status_said``: the first error message a device
  reported, else what else the status said (the state, the appearance changes, how a restarted
  daemon's belief started);
- ``recover_s``: from the fault's end until the status reports every device ``ok`` and 3
  poses in a row are ``tracking`` within 0.5 m of the truth, after the last pose that was not
  ``tracking`` (None: not within ``--observe``);
- ``states``: the filter states seen;
- ``verdict``: ``ridden through`` (the daemon running at the end of the row, and poses received
  after the fault's end), ``reported`` (``reported_after_s`` is not None) and ``recovered``
  (``recover_s`` is not None), or what of these is missing.

Two rows have nothing to report, and their verdict asks only that they are ridden through and
recovered: a line split in two pieces (``odometry_split``) is no fault to the receiver (a serial
line arrives in pieces whenever a read catches it half written, and the driver joins them;
nothing is lost), and the lights switched back to the map's own (``lights -> tube``) is the end
of the previous row's change (the filter watches for every view becoming less familiar at once;
these become more familiar).

Usage::

    python benchmarks/fault_campaign.py                 # table, 320 x 240 at 15 fps
    python benchmarks/fault_campaign.py --width 80 --height 60 --json --duration 3 --observe 20
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sim_service_rig import (  # noqa: E402
    ROOT,
    Rig,
    Settings,
    Stream,
    config_text,
    env,
    exit_on_sigterm,
    free_port,
    request,
    stop,
)

from drivers.dynamixel_head import GIVEN_UP_RETRY_S, INCIDENT_HOLD_S  # noqa: E402

#: A pose counts as good within this distance of the truth, m.
GOOD_M = 0.5

#: (row name, fault-control request without duration) in the order they run.
FAULT_ROWS: list[tuple[str, dict[str, Any]]] = [
    ("head_no_reply", {"fault": "head_no_reply"}),
    ("head_crc 50 %", {"fault": "head_crc", "fraction": 0.5}),
    ("head_hardware_error once", {"fault": "head_hardware_error"}),
    ("head_unplug", {"fault": "head_unplug"}),
    ("odometry_crc", {"fault": "odometry_crc"}),
    ("odometry_garbage", {"fault": "odometry_garbage"}),
    ("odometry_drop", {"fault": "odometry_drop"}),
    ("odometry_split", {"fault": "odometry_split"}),
    ("odometry_unplug", {"fault": "odometry_unplug"}),
    ("camera_stall", {"fault": "camera_stall"}),
    ("camera_unplug", {"fault": "camera_unplug"}),
    ("camera_malformed 50 %", {"fault": "camera_malformed", "fraction": 0.5}),
]
#: Faults that lose nothing and so have nothing to report (module docstring).
NOTHING_TO_REPORT = ("odometry_split", "lights -> tube")
#: Run after the lights, just before the daemon's kill -9 and restart: the head adapter gives the
#: servo up after 3 reboots in 60 s and retries GIVEN_UP_RETRY_S later (its row waits for that).
LAST_FAULT_ROW = ("head_hardware_error persistent", {"fault": "head_hardware_error", "persistent": True})


class Campaign:
    def __init__(self, rig: Rig, stream: Stream, args: argparse.Namespace) -> None:
        self.rig, self.s, self.args = rig, stream, args
        self.rows: list[dict[str, Any]] = []

    # helpers ---------------------------------------------------------------------------------
    def good_run(self, t0: float, n: int = 3) -> float | None:
        """rx time of the n-th pose of the first run of n good poses received after t0."""
        run = 0
        for p in self.s.poses_between(t0, 1e12):
            e = self.s.error(p)
            run = run + 1 if p["state"] == "tracking" and e is not None and e < GOOD_M else 0
            if run >= n:
                return float(p["_rx"])
        return None

    def settle(self) -> bool:
        t0 = time.time()
        return self.s.wait_for(lambda: self.good_run(t0), self.args.settle) is not None

    def rate_before(self, t: float, seconds: float = 3.0) -> float:
        return len(self.s.poses_between(t - seconds, t)) / seconds

    # one row -----------------------------------------------------------------------------------
    def measure(self, name: str, t_inject: float, t_end: float, settled: bool, rate: float,
                observe_until: float | None = None, note: str = "", fixed: bool = False) -> dict[str, Any]:
        """Wait until recovery (+3 s; ``fixed``: until ``observe_until`` whatever happens) or the
        observation limit, then the row's figures."""
        limit = observe_until or t_end + self.args.observe

        def recovered() -> float | None:
            # from the end of the fault, or from the last pose not `tracking` after it
            t_from = max([t_end] + [p["_rx"] for p in self.s.poses_between(t_end, 1e12) if p["state"] != "tracking"])
            ok = next((x["_rx"] for x in self.s.statuses_between(t_end, 1e12)
                       if all(d["state"] == "ok" for d in x["devices"].values())), None)
            good = self.good_run(t_from)
            return max(ok, good) if ok is not None and good is not None else None

        while time.time() < limit:
            r = recovered()
            if r is not None and time.time() > r + 3.0 and not fixed:
                break
            time.sleep(0.2)
        t_row_end = time.time()
        rec = recovered()
        return self.figures(name, t_inject, t_end, t_row_end, rec, settled, rate, note)

    def figures(self, name: str, t_inject: float, t_end: float, t_row_end: float, rec: float | None,
                settled: bool, rate: float, note: str) -> dict[str, Any]:
        s = self.s
        lost_window = s.poses_between(t_inject, t_end + 2.0)
        around = s.poses_between(t_inject - 1.0, t_row_end)
        rx = [t_inject] + [p["_rx"] for p in around if p["_rx"] >= t_inject] + [t_row_end]
        during = [e for e in (s.error(p) for p in s.poses_between(t_inject, max(t_end, t_inject + 0.5)))
                  if e is not None]
        after = [e for e in (s.error(p) for p in s.poses_between(t_row_end - 3.0, t_row_end)) if e is not None]
        statuses = s.statuses_between(t_inject, t_row_end)
        before_all = s.statuses_between(t_inject - 3.0, t_inject)
        before = before_all[-1] if before_all else None
        reported = next((x["_rx"] for x in statuses if reports(before, x)), None)
        alive = self.rig.daemon is not None and self.rig.daemon.poll() is None
        resumed = bool(s.poses_between(t_end, t_row_end))
        return {
            "fault": name,
            "settled_before": settled,
            "poses_lost": max(0, round(rate * (t_end + 2.0 - t_inject)) - len(lost_window)),
            "dead_reckoning": sum(bool(p.get("dead_reckoning")) for p in lost_window),
            "longest_gap_s": round(float(np.max(np.diff(rx))), 2),
            "error_during_m": [_r(np.median(during)), _r(np.max(during))] if during else None,
            "error_after_m": _r(np.median(after)) if after else None,
            "health": health(before, statuses),
            "sequence": sequence(statuses, t_inject),
            "reported_after_s": round(reported - t_inject, 1) if reported is not None else None,
            "status_said": said(before, statuses),
            "recover_s": round(rec - t_end, 1) if rec is not None else None,
            "states": sorted({p["state"] for p in s.poses_between(t_inject, t_row_end)}),
            "verdict": verdict(name, alive, resumed, reported is not None, rec is not None),
            "row_s": round(t_row_end - t_inject, 1),
            "note": note,
        }

    def fault_row(self, name: str, req: dict[str, Any], observe: float | None = None) -> dict[str, Any]:
        """One fault of the fault control for ``--duration`` s, then up to ``observe`` s
        (default ``--observe``) for the recovery."""
        settled = self.settle()
        t = time.time()
        rate = self.rate_before(t)
        reply = request(self.rig.faults, {"cmd": "inject", "duration_s": self.args.duration, **req})
        if not reply.get("ok"):
            return {"fault": name, "note": f"not injected: {reply.get('error')}"}
        t_end = t + self.args.duration
        return self.measure(name, t, t_end, settled, rate, t_end + (observe or self.args.observe))

    def lights_row(self, lighting: str) -> dict[str, Any]:
        """The lights switched; the fault's "end" is when the simulator has baked the new
        lighting and renders with it (its log says so), then a fixed ``--observe`` window."""
        settled = self.settle()
        t = time.time()
        rate = self.rate_before(t)
        size = self.rig.sim_log.stat().st_size
        reply = request(self.rig.faults, {"cmd": "lights", "lighting": lighting})
        if not reply.get("ok"):
            return {"fault": f"lights -> {lighting}", "note": f"not switched: {reply.get('error')}"}
        def switched() -> bool:
            with open(self.rig.sim_log, "rb") as f:
                f.seek(size)
                return f"lighting switched to {lighting}".encode() in f.read()
        self.s.wait_for(switched, 60)
        t_end = time.time()
        row = self.measure(f"lights -> {lighting}", t, t_end, settled, rate, t_end + self.args.observe, fixed=True)
        row["note"] = f"the new lighting rendered {t_end - t:.1f} s after the request"
        return row

    def daemon_kill_row(self) -> dict[str, Any]:
        settled = self.settle()
        time.sleep(1.5)  # at least one periodic save (save_period_s = 1) while tracking
        assert self.rig.daemon is not None
        t = time.time()
        rate = self.rate_before(t)
        self.rig.daemon.send_signal(signal.SIGKILL)
        self.rig.daemon.wait(10)
        self.rig.start_daemon()
        t_restart = time.time()
        first = self.s.wait_for(lambda: self.s.poses_between(t_restart, 1e12)[:1], 60)
        note = ""
        if first:
            e = self.s.error(first[0])
            note = f"first pose after the restart: {first[0]['state']}, {_r(e)} m off"
            ft = next((p for p in self.s.poses_between(t_restart, 1e12) if p["state"] == "tracking"), None)
            if ft is not None:
                note += f"; first tracking pose {_r(self.s.error(ft))} m off, {ft['_rx'] - t_restart:.1f} s after the restart"
        return self.measure("daemon kill -9 + restart", t, t_restart, settled, rate, note=note)

    def sim_death_row(self) -> dict[str, Any]:
        settled = self.settle()
        assert self.rig.sim is not None and self.rig.daemon is not None
        t = time.time()
        rate = self.rate_before(t)
        last = self.s.truths[-1]
        self.rig.sim.send_signal(signal.SIGKILL)
        self.rig.sim.wait(10)
        time.sleep(self.args.duration)
        alive = self.rig.daemon.poll() is None
        self.rig.start_sim("--fault-endpoint", self.rig.faults, f"--start={last[1]},{last[2]},{last[3]}",
                           "--seed", "1")
        t_back = time.time()
        note = (f"daemon {'kept running' if alive else f'exited {self.rig.daemon.returncode}'} while the simulator "
                f"was dead ({self.args.duration:g} s); simulator restarted at the last true pose")
        return self.measure("simulator kill -9 (explicit devices) + restart", t, t_back, settled, rate, note=note)

    def run(self) -> list[dict[str, Any]]:
        for name, req in FAULT_ROWS:
            self.rows.append(self.fault_row(name, req))
            print(f"# {_line(self.rows[-1])}", file=sys.stderr, flush=True)
        for lighting in ("bulb", "tube"):
            self.rows.append(self.lights_row(lighting))
            print(f"# {_line(self.rows[-1])}", file=sys.stderr, flush=True)
        if not self.args.only or LAST_FAULT_ROW[0].startswith(tuple(self.args.only.split(","))):
            retry = self.args.retry_observe or GIVEN_UP_RETRY_S + INCIDENT_HOLD_S + self.args.observe
            self.rows.append(self.fault_row(*LAST_FAULT_ROW, observe=retry))
            print(f"# {_line(self.rows[-1])}", file=sys.stderr, flush=True)
        for row in (self.daemon_kill_row, self.sim_death_row):
            self.rows.append(row())
            print(f"# {_line(self.rows[-1])}", file=sys.stderr, flush=True)
        return self.rows


def health(before: dict[str, Any] | None, statuses: list[dict[str, Any]]) -> dict[str, Any]:
    """Worst state per device over ``statuses`` and the counters that grew since ``before``
    (a restarted daemon's counters start again from 0: those are not listed)."""
    rank = {"ok": 0, "degraded": 1, "failed": 2}
    worst: dict[str, str] = {}
    for st in statuses:
        for k, d in st["devices"].items():
            if rank.get(d["state"], 3) > rank.get(worst.get(k, "ok"), 0):
                worst[k] = d["state"]
    moved: dict[str, int] = {}
    if before is not None and statuses:
        last = statuses[-1]
        if last["uptime_s"] < before["uptime_s"]:
            return {"worst": worst, "counters": moved}
        for c in STATUS_COUNTERS:
            if last.get(c, 0) > before.get(c, 0):
                moved[c] = last[c] - before.get(c, 0)
        for k, d in last["devices"].items():
            old = before["devices"].get(k, {}).get("counters", {})
            for c, v in d.get("counters", {}).items():
                if c not in ("frames", "lines", "increments", "reads", "commands") and v > old.get(c, v):
                    moved[f"{k}.{c}"] = v - old.get(c, 0)
    return {"worst": worst, "counters": moved}


#: Counters of the status message itself shown in ``health`` when they grow.
STATUS_COUNTERS = ("appearance_changes", "update_errors", "dropped_frames", "out_of_order_frames")
#: Those of them whose growth reports a fault (frames are dropped whenever the loop is busy).
REPORTING_COUNTERS = ("appearance_changes", "update_errors")


def restarted(before: dict[str, Any] | None, st: dict[str, Any]) -> bool:
    return before is not None and st["uptime_s"] < before["uptime_s"]


def reports(before: dict[str, Any] | None, st: dict[str, Any]) -> bool:
    """Does the status ``st`` report a fault that began after the status ``before``?"""
    if any(d["state"] != "ok" for d in st["devices"].values()) or st["state"] != "tracking":
        return True
    if before is None:
        return False
    return restarted(before, st) or any(st.get(c, 0) > before.get(c, 0) for c in REPORTING_COUNTERS)


def said(before: dict[str, Any] | None, statuses: list[dict[str, Any]]) -> str | None:
    """The first device error in ``statuses``, else the first other report (:func:`reports`)."""
    for st in statuses:
        for k, d in st["devices"].items():
            if d["state"] != "ok" and d.get("error"):
                return f"{k} {d['state']}: {d['error']}"[:160]
    for st in statuses:
        if restarted(before, st):
            belief = (st.get("persistence") or {}).get("initial_belief")
            return f"restarted ({st['uptime_s']:.0f} s up), state {st['state']}: {belief}"[:160]
        grown = [f"{c} {st.get(c, 0)}" for c in REPORTING_COUNTERS
                 if before is not None and st.get(c, 0) > before.get(c, 0)]
        if grown or st["state"] != "tracking":
            return ", ".join([f"state {st['state']}", *grown])[:160]
    return None


def sequence(statuses: list[dict[str, Any]], t0: float) -> dict[str, list[tuple[str, float]]]:
    """Per device that was not always ``ok``: its states in ``statuses``, each with the seconds
    since ``t0`` of the first status that said it."""
    seq: dict[str, list[tuple[str, float]]] = {}
    for st in statuses:
        for k, d in st["devices"].items():
            runs = seq.setdefault(k, [])
            if not runs or runs[-1][0] != d["state"]:
                runs.append((d["state"], round(st["_rx"] - t0, 1)))
    return {k: v for k, v in seq.items() if any(state != "ok" for state, _ in v)}


def verdict(name: str, alive: bool, resumed: bool, reported: bool, recovered: bool) -> str:
    """``ridden through, reported, recovered``, or what of it is missing (module docstring)."""
    quiet = name in NOTHING_TO_REPORT
    parts = ["ridden through" if alive and resumed else
             "NOT ridden through (" + ", ".join(w for w, ok in (("daemon dead", alive), ("no pose after", resumed))
                                             if not ok) + ")"]
    parts.append(("reported" if reported else "nothing to report") if quiet
                 else ("reported" if reported else "NOT reported"))
    parts.append("recovered" if recovered else "NOT recovered")
    return ", ".join(parts)


def _r(v: Any) -> float | None:
    return None if v is None or not np.isfinite(v) else round(float(v), 2)


def _line(row: dict[str, Any]) -> str:
    return json.dumps(row)


def auto_sim_death(args: argparse.Namespace, tmp: Path) -> dict[str, Any]:
    """`lino-loc run` with "auto" devices; its own simulator killed with SIGKILL."""
    pub, rep = f"tcp://127.0.0.1:{free_port()}", f"tcp://127.0.0.1:{free_port()}"
    tmp = tmp / "auto"
    tmp.mkdir()
    cfg = tmp / "auto.toml"
    cfg.write_text(config_text(Settings(width=args.width, height=args.height, fps=args.fps), tmp, head="auto", odometry="auto", camera="auto", pub=pub, rep=rep))
    log = tmp / "auto.log"
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", "--config", str(cfg)],
                            stdout=subprocess.DEVNULL, stderr=open(log, "wb"), env=env(), cwd=ROOT)
    stream = Stream(pub, "tcp://127.0.0.1:1")  # no truth: the daemon's own simulator
    try:
        if not stream.wait_for(lambda: len(stream.poses_between(0, 1e12)) >= 3, args.settle + 60):
            return {"fault": "simulator kill -9 (auto devices)", "note": f"no pose: {log.read_text()[-300:]}"}
        text = log.read_text()
        sim_pid = int(text.split("simulator  pid ")[1].split(":")[0])
        t = time.time()
        os.kill(sim_pid, signal.SIGKILL)
        try:
            code: int | None = proc.wait(30)
        except subprocess.TimeoutExpired:
            code = None
        t_exit = time.time()
    finally:
        if proc.poll() is None:
            stop(proc)
        stream.close()
    text = log.read_text()
    line = next((ln for ln in text.splitlines() if "simulated robot" in ln and "exited" in ln), None)
    last = stream.poses_between(0, 1e12)
    return {
        "fault": "simulator kill -9 (auto devices)",
        "daemon_exit_status": code,
        "exit_after_s": round(t_exit - t, 1) if code is not None else None,
        "poses_after_kill": len([p for p in last if p["_rx"] > t]),
        "status_said": line.split(": ", 1)[-1][:160] if line else None,
        "tracebacks": text.count("Traceback"),
    }


COLUMNS = ["fault", "poses_lost", "dead_reckoning", "longest_gap_s", "error_during_m", "error_after_m",
           "health", "sequence", "reported_after_s", "recover_s", "states", "status_said", "verdict"]


def table(rows: list[dict[str, Any]], auto: dict[str, Any] | None) -> str:
    def cell(row: dict[str, Any], c: str) -> str:
        v = row.get(c)
        if c == "health" and isinstance(v, dict):
            w = ", ".join(f"{k} {s}" for k, s in v["worst"].items() if s != "ok") or "all ok"
            moved = ", ".join(f"{k} +{n}" for k, n in list(v["counters"].items())[:5])
            return w + (f" ({moved})" if moved else "")
        if c == "sequence" and isinstance(v, dict):
            return "; ".join(f"{k} " + " -> ".join(f"{st} {t:g}" for st, t in runs) for k, runs in v.items()) or "-"
        if c == "error_during_m" and isinstance(v, list):
            return f"{v[0]} / {v[1]}"
        if c == "states" and isinstance(v, list):
            return ", ".join(v)
        return "-" if v is None else str(v).replace("|", "/")

    out = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    out += ["| " + " | ".join(cell(r, c) for c in COLUMNS) + " |" for r in rows]
    notes = [f"- {r['fault']}: {r['note']}" for r in rows if r.get("note")]
    notes += [f"- {r['fault']}: did not start from tracking" for r in rows if r.get("settled_before") is False]
    if auto is not None:
        notes.append(f"- {auto['fault']}: exit status {auto.get('daemon_exit_status')} "
                     f"{auto.get('exit_after_s')} s after the kill, {auto.get('poses_after_kill')} poses after it, "
                     f"tracebacks {auto.get('tracebacks')}; the log said: {auto.get('status_said')}")
    return "\n".join(out + [""] + notes)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--width", type=int, default=320, help="camera image width, px (default 320)")
    p.add_argument("--height", type=int, default=240, help="camera image height, px (default 240)")
    p.add_argument("--fps", type=float, default=15.0, help="camera frame rate (default 15)")
    p.add_argument("--duration", type=float, default=3.0, help="s each fault lasts (default 3)")
    p.add_argument("--observe", type=float, default=20.0, help="s after a fault's end to wait for recovery")
    p.add_argument("--retry-observe", type=float, default=None,
                   help="s after the persistent hardware error's end to wait for recovery "
                        f"(default {GIVEN_UP_RETRY_S:g} + {INCIDENT_HOLD_S:g} + --observe: the servo is retried "
                        f"{GIVEN_UP_RETRY_S:g} s after it was given up)")
    p.add_argument("--settle", type=float, default=60.0, help="s to wait for tracking before each row")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--only", metavar="A,B", help="only the fault-control rows whose names start with these")
    p.add_argument("--no-auto", action="store_true", help="skip the auto-devices simulator death")
    p.add_argument("--keep-logs", metavar="DIR", help="copy the daemon's and the simulator's logs here")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    exit_on_sigterm()
    t_start = time.time()
    if args.only:
        keep = tuple(x.strip() for x in args.only.split(","))
        FAULT_ROWS[:] = [r for r in FAULT_ROWS if r[0].startswith(keep)]
    with tempfile.TemporaryDirectory(prefix="lino-faults-") as td:
        tmp = Path(td)
        settings = Settings(width=args.width, height=args.height, fps=args.fps)
        rig = Rig(tmp, settings)
        rig.start_sim("--fault-endpoint", rig.faults, "--seed", str(args.seed))
        stream = Stream(rig.pub, rig.truth)
        try:
            rig.start_daemon()
            if not stream.wait_for(lambda: stream.poses_between(0, 1e12), 300):
                raise SystemExit(f"no pose: {rig.daemon_log.read_text()[-2000:]}")
            rows = Campaign(rig, stream, args).run()
        finally:
            rig.close()
            stream.close()
        tracebacks = rig.daemon_log.read_text().count("Traceback") + rig.sim_log.read_text().count("Traceback")
        if args.keep_logs:
            Path(args.keep_logs).mkdir(parents=True, exist_ok=True)
            for f in (rig.daemon_log, rig.sim_log):
                (Path(args.keep_logs) / f.name).write_bytes(f.read_bytes())
        auto = None if args.no_auto else auto_sim_death(args, tmp)
    if args.json:
        print(json.dumps({"rows": rows, "auto_sim_death": auto, "tracebacks_in_logs": tracebacks,
                          "config": {"width": args.width, "height": args.height, "fps": args.fps,
                                     "duration_s": args.duration, "observe_s": args.observe,
                                     "retry_observe_s": args.retry_observe, "seed": args.seed},
                          "total_s": round(time.time() - t_start, 1)}))
    else:
        print(table(rows, auto))
        print(f"- tracebacks in the daemon's and the simulator's logs: {tracebacks}")
        print(f"- {args.width} x {args.height} at {args.fps:g} fps; the campaign took {time.time() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
