"""A recording of the simulated service, real processes: `lino-loc run --record` with "auto"
devices (it starts its own `lino-loc sim` and relays the truth), the tests' office map (80 x
60 images, the 50 cm survey, cached in the temp folder as tests/test_daemon_integration.py
does), 10 fps.

Two sessions: one stopped with SIGTERM after ~12 s of poses (a finished file: summary and
footer), one killed with SIGKILL after ~6 s (a cut file). The first is read back with the
``mcap`` reader, every channel and schema named, its protobuf messages decoded with
mcap-protobuf-support's decoder; it is replayed twice (identical poses, and the service's own
poses bit for bit), and its TUM file parsed. The second reads up to the last second before
the kill.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap")
pytest.importorskip("foxglove")
pytest.importorskip("mcap_protobuf")

from test_daemon_integration import MAP_CACHE, ROOT, _env, _free_port, config_text, stop  # noqa: E402

pytestmark = pytest.mark.slow

#: Seconds of service recorded by the clean session and by the killed one.
CLEAN_S = 12.0
KILLED_S = 6.0


@dataclass
class Session:
    recording: Path
    log: Path
    code: int | None = None
    kill_time: float | None = None


def _run(tmp: Path, name: str, seconds: float, sig: int) -> Session:
    pub, rep = f"tcp://127.0.0.1:{_free_port()}", f"tcp://127.0.0.1:{_free_port()}"
    cfg = tmp / f"{name}.toml"
    text = config_text(tmp, pub=pub, rep=rep, state=tmp / f"{name}-state.json").replace("fps = 5.0", "fps = 10.0")
    cfg.write_text(text)
    s = Session(recording=tmp / f"{name}.mcap", log=tmp / f"{name}.log")
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "run", "--config", str(cfg), "--record", str(s.recording)],
        stdout=subprocess.DEVNULL, stderr=open(s.log, "ab"), env=_env(), cwd=ROOT,
    )
    try:
        deadline = time.time() + 90
        while "lino-loc is running" not in s.log.read_text() and time.time() < deadline:
            assert proc.poll() is None, s.log.read_text()[-3000:]
            time.sleep(0.2)
        time.sleep(seconds)
        if sig == signal.SIGKILL:
            proc.kill()
            s.kill_time = time.time()
            proc.wait(10)
    finally:
        s.code = stop(proc, signal.SIGTERM)
    return s


@pytest.fixture(scope="module")
def sessions(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Session]]:
    from services.config import load_config
    from services.sim_launcher import ensure_sim_map

    tmp = tmp_path_factory.mktemp("recording")
    cfg = tmp / "map.toml"
    cfg.write_text(config_text(tmp, pub="tcp://127.0.0.1:1", rep="tcp://127.0.0.1:2", state=tmp / "s.json"))
    MAP_CACHE.parent.mkdir(parents=True, exist_ok=True)
    ensure_sim_map(load_config(cfg))  # built once, cached across runs
    yield {"clean": _run(tmp, "clean", CLEAN_S, signal.SIGTERM), "killed": _run(tmp, "killed", KILLED_S, signal.SIGKILL)}


def _replay(*argv: str) -> dict:
    out = subprocess.run([sys.executable, "-m", "services.cli", "replay", *argv, "--json"],
                         capture_output=True, text=True, env=_env(), cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout)


def test_the_recording_reads_back_with_every_channel_and_schema_named(sessions: dict[str, Session]) -> None:
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    from services.recording.channels import TOPICS

    s = sessions["clean"]
    assert s.code == 0, s.log.read_text()[-3000:]
    with s.recording.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        named = {c.topic: (summary.schemas[c.schema_id].name, c.message_encoding) for c in summary.channels.values()}
        assert named == {t.topic: (t.schema_name, t.encoding) for t in TOPICS.values()}
        counts = {summary.channels[i].topic: n for i, n in summary.statistics.channel_message_counts.items()}
        # the tests' map has no disparity channel: the camera computes none
        for topic in set(TOPICS) - {"/camera/disparity"}:
            assert counts.get(topic, 0) > 0, (topic, counts)
        assert summary.chunk_indexes and len(summary.chunk_indexes) >= CLEAN_S / 0.5 / 2
        first: dict[str, object] = {}
        for _schema, channel, _msg, decoded in reader.iter_decoded_messages(
                topics=["/pose", "/particles", "/camera/image", "/tf", "/truth/pose", "/pose/ellipse"]):
            first.setdefault(channel.topic, decoded)
        statuses = [json.loads(m.data) for _s, _c, m in reader.iter_messages(topics=["/status"])]
    assert first["/pose"].frame_id == "map"
    assert len(first["/particles"].poses) == 500  # 1000 particles, every 2nd
    assert first["/camera/image"].format == "png"
    import cv2

    img = cv2.imdecode(np.frombuffer(first["/camera/image"].data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img.shape == (60, 80)
    assert first["/tf"].parent_frame_id in ("map", "base_link")
    assert first["/truth/pose"].frame_id == "map"
    assert first["/pose/ellipse"].entities[0].id == "pose_ellipse"
    rec = statuses[-1]["recording"]
    assert rec["file"] == str(s.recording) and rec["error"] is None and rec["dropped"] == 0
    assert rec["messages"] > 0


def test_replay_twice_is_identical_and_gives_the_services_poses(sessions: dict[str, Session], tmp_path: Path) -> None:
    s = sessions["clean"]
    a = _replay(str(s.recording), "--out", str(tmp_path / "a.mcap"))
    _replay(str(s.recording), "--out", str(tmp_path / "b.mcap"))
    assert a["poses"] > 50 and a["errors"] == 0
    assert (tmp_path / "a.tum").read_bytes() == (tmp_path / "b.tum").read_bytes()
    assert a["service"]["bit_identical"], a["service"]
    assert a["service"]["max_m"] == 0.0
    # another seed: the same inputs, other poses
    c = _replay(str(s.recording), "--out", str(tmp_path / "c.mcap"), "--seed", "12345")
    assert c["seed"] == 12345 and c["poses"] == a["poses"]
    assert (tmp_path / "c.tum").read_bytes() != (tmp_path / "a.tum").read_bytes()
    # recomposed from the raw odometry and head streams
    r = _replay(str(s.recording), "--out", str(tmp_path / "r.mcap"), "--recompose")
    assert r["service"]["matched"] == a["service"]["matched"]
    print("recompose vs service:", r["service"])
    # the TUM trajectory: timestamp x y z qx qy qz qw, as evo reads it
    from lino_loc.tum_import import read_groundtruth

    rows = np.loadtxt(tmp_path / "a.tum")
    assert rows.shape == (a["poses"], 8)
    assert np.all(np.diff(rows[:, 0]) > 0)
    assert np.allclose(np.linalg.norm(rows[:, 4:], axis=1), 1.0)
    stamps, positions, _rot = read_groundtruth(tmp_path / "a.tum")
    assert len(stamps) == a["poses"] and np.allclose(positions[:, 2], 0.0)
    # the replay's output is itself a recording: it replays to the same poses
    again = _replay(str(tmp_path / "a.mcap"), "--out", str(tmp_path / "a2.mcap"))
    assert (tmp_path / "a2.tum").read_bytes() == (tmp_path / "a.tum").read_bytes()
    assert again["service"]["bit_identical"]


def test_a_kill_9_leaves_a_file_that_reads_up_to_the_last_second(sessions: dict[str, Session], tmp_path: Path) -> None:
    from services.recording.recording_reader import Recording, read_recording

    s = sessions["killed"]
    assert s.kill_time is not None and s.recording.is_file()
    rec = Recording([s.recording])
    msgs = list(read_recording([s.recording], rec))
    assert rec.metadata.get("seed") is not None
    last = max(m.log_ns for m in msgs) / 1e9
    assert s.kill_time - 1.0 <= last <= s.kill_time + 0.1, (s.kill_time, last, rec.truncated)
    out = _replay(str(s.recording), "--out", str(tmp_path / "k.mcap"))
    assert out["poses"] > 0 and out["service"]["bit_identical"], out


def test_another_configuration_replays_the_same_inputs(sessions: dict[str, Session], tmp_path: Path) -> None:
    """300 particles instead of 1000, the same frames: as many updates, other poses, and the
    output's particle sets have the new size."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    s = sessions["clean"]
    base = _replay(str(s.recording), "--out", str(tmp_path / "base.mcap"))
    cfg = tmp_path / "few.toml"
    text = config_text(tmp_path, pub="tcp://127.0.0.1:1", rep="tcp://127.0.0.1:2", state=tmp_path / "s.json")
    cfg.write_text(text.replace("n_particles = 1000", "n_particles = 300\nseed = 11"))
    few = _replay(str(s.recording), "--config", str(cfg), "--out", str(tmp_path / "few.mcap"))
    assert few["seed"] == 11 and few["updates"] == base["updates"] and few["poses"] == base["poses"]
    assert not few["service"]["bit_identical"]
    with (tmp_path / "few.mcap").open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        sizes = {len(m.poses) for _s, _c, _r, m in reader.iter_decoded_messages(topics=["/particles"])}
    assert sizes == {300}
