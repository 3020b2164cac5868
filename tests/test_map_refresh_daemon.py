"""The map refresh in a real daemon: `lino-loc run` on the simulated robot (it starts its own
`lino-loc sim`) with ``[map_refresh]`` on writes the views it tracks into part datasets whose
camera positions match the simulator's truth, and `lino-loc map extend` takes the parts.
Real processes and sockets, as tests/test_daemon_integration.py (whose helpers it uses)."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_daemon_integration import (  # noqa: E402
    MAP_CACHE,
    Stream,
    _free_port,
    config_text,
    start_daemon,
    stop,
)

from lino_loc.appearance_map import AppearanceMap  # noqa: E402
from lino_loc.dataset import Dataset  # noqa: E402


def _finished(folder: Path) -> list[Path]:
    return sorted(p.parent for p in folder.glob("refresh-*/part-*/dataset.json"))


def test_daemon_writes_tracked_views_for_map_extend(tmp_path: Path) -> None:
    pub, rep = f"tcp://127.0.0.1:{_free_port()}", f"tcp://127.0.0.1:{_free_port()}"
    refresh = tmp_path / "refresh"
    cfg = tmp_path / "refresh.toml"
    text = config_text(tmp_path, pub=pub, rep=rep, state=tmp_path / "state.json")
    text = text.replace("[logging]", f"""[map_refresh]
enabled = true
path = "{refresh}"
min_quality = 0.0
min_distance_m = 0.05
min_turn_deg = 5.0
condition = "bulb"
part_views = 4
part_seconds = 2.0

[logging]""")
    cfg.write_text(text)
    log = tmp_path / "run.log"
    stream = Stream(pub, None)
    proc = start_daemon(cfg, log)
    try:
        stream.wait_for(lambda: len(_finished(refresh)) >= 2, 120,
                        f"two finished refresh parts; log:\n{log.read_text()[-3000:]}")
    finally:
        code = stop(proc, signal.SIGINT)
        stream.close()
    assert code == 0, log.read_text()[-2000:]
    assert "map refresh:" in log.read_text()
    parts = _finished(refresh)
    sets = [Dataset.open(p) for p in parts]
    assert all(len(d) >= 1 for d in sets) and all(d.conditions[0] == "bulb" for d in sets)
    # every kept view was taken while tracking: its camera position is the robot's, near the truth
    errs = []
    for d in sets:
        for i in range(len(d)):
            t = stream.truth_at(float(d.stamps[i]))
            if t is not None:
                errs.append(math.hypot(d.poses[i, 0] - t[0], d.poses[i, 1] - t[1]))
    assert errs, "no truth at the stamps of the kept views"
    assert sorted(errs)[len(errs) // 2] < 0.5, errs
    # the parts extend the daemon's map as one session
    out = tmp_path / "extended.npz"
    res = subprocess.run([sys.executable, "-m", "services.cli", "map", "extend", str(MAP_CACHE),
                          *map(str, parts), "--out", str(out), "--json"], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[1], timeout=120)
    assert res.returncode == 0, res.stderr
    amap = AppearanceMap.load(out)
    sess = amap.session_list()
    assert len(sess) == 2 and sess[1].condition == "bulb"
    assert sess[1].n_entries == sum(len(d) for d in sets)
