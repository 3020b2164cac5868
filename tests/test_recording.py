"""The recording's parts without the service: codecs, the MCAP file, the recorder's queue,
the configuration, and the replay command's bad inputs.

Protobuf messages are decoded with mcap-protobuf-support's decoder from the schema stored
in the file, never with the encoder that wrote them.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("mcap")
pytest.importorskip("foxglove")
pytest.importorskip("mcap_protobuf")

from mcap.reader import make_reader  # noqa: E402
from mcap_protobuf.decoder import DecoderFactory  # noqa: E402

from lino_loc.errors import LinoLocError  # noqa: E402
from services.recording import recorder as recorder_mod  # noqa: E402
from services.recording.channels import TOPICS, require_viz  # noqa: E402
from services.recording.image_codec import (  # noqa: E402
    DISPARITY_SCALE,
    decode_disparity,
    decode_png,
    encode_disparity,
)
from services.recording.recorder import Recorder, RecordingConfig  # noqa: E402
from services.recording.recording_reader import Recording, read_recording  # noqa: E402
from services.recording.session_file import SessionFile, part_path  # noqa: E402
from services.recording.topic_messages import frame_messages, pose_messages  # noqa: E402


def _cli(argv: list[str]) -> int:
    from services.cli import main

    return main(argv)


# --------------------------------------------------------------------------------------------
# codecs
# --------------------------------------------------------------------------------------------


def test_png_and_disparity_round_trip_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    left = rng.integers(0, 256, (60, 80), dtype=np.uint8)
    [(_, _, img)] = frame_messages(1.5, left, None)
    # the disparity of the block matcher: 1/16-pixel steps, NaN = none
    disp = (rng.integers(1, 64 * 16, (60, 80)) / 16.0).astype(np.float32)
    disp[rng.random((60, 80)) < 0.4] = np.nan
    enc, step, data = encode_disparity(disp)
    assert enc == "16UC1" and step == 160
    back = decode_disparity(enc, 80, 60, data)
    assert np.array_equal(np.isnan(back), np.isnan(disp))
    assert np.array_equal(back[~np.isnan(back)], disp[~np.isnan(disp)])
    raw = np.frombuffer(data, dtype="<u2").reshape(60, 80)
    assert raw[~np.isnan(disp)][0] == disp[~np.isnan(disp)][0] * DISPARITY_SCALE
    # the PNG inside the CompressedImage, read by an independent protobuf decoder
    schema = SimpleNamespace(id=1, name="foxglove.CompressedImage", encoding="protobuf",
                             data=_schema("foxglove.CompressedImage"))
    msg = DecoderFactory().decoder_for("protobuf", schema)(img)
    assert msg.format == "png" and msg.frame_id == "camera"
    assert np.array_equal(decode_png(msg.data), left)


def _schema(name: str) -> bytes:
    import foxglove.messages as fm

    return bytes(getattr(fm, name.split(".")[1]).get_schema().data)


@pytest.mark.parametrize("value", [0.0, -2.0, 1.0 / 64, 4000.0])
def test_a_disparity_16_bits_cannot_hold_is_kept_as_float32(value: float) -> None:
    disp = np.full((4, 5), np.nan, dtype=np.float32)
    disp[1, 2] = value
    disp[2, 3] = 3.5
    enc, step, data = encode_disparity(disp)
    assert enc == "32FC1" and step == 20
    back = decode_disparity(enc, 5, 4, data)
    assert back[1, 2] == np.float32(value) and back[2, 3] == 3.5 and np.isnan(back[0, 0])


# --------------------------------------------------------------------------------------------
# the MCAP file
# --------------------------------------------------------------------------------------------


def _pose_msg(stamp: float) -> tuple[bytes, dict]:
    from services.messages import Pose2D, PoseMessage

    m = PoseMessage(stamp=stamp, seq=1, pose=Pose2D(x=1.0, y=2.0, theta=0.5),
                    covariance=[0.04, 0.01, 0, 0.01, 0.09, 0, 0, 0, 0.01], state="tracking",
                    pan=0.2, n_particles=10, latency_ms=1.0)
    return m.model_dump_json().encode(), m.model_dump()


def _write(f: SessionFile, n: int, t0: float = 1_700_000_000.0) -> None:
    left = np.zeros((60, 80), dtype=np.uint8)
    for i in range(n):
        stamp = t0 + i / 15
        for topic, t, data in frame_messages(stamp, left, None) + pose_messages(*_pose_msg(stamp)):
            f.write(topic, t, t, data, i)


def test_the_file_names_every_channel_and_schema_and_decodes_independently(tmp_path: Path) -> None:
    path = tmp_path / "s.mcap"
    f = SessionFile(path, {"seed": "7"})
    _write(f, 5)
    f.close()
    with path.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None
        assert {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()} == {
            t.topic: t.schema_name for t in TOPICS.values()}
        assert reader.get_header().profile == "lino-loc"
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta["lino-loc"]["seed"] == "7"
        decoded = {}
        for _schema, channel, _msg, proto in reader.iter_decoded_messages(
                topics=["/pose", "/pose/ellipse", "/tf"]):
            decoded.setdefault(channel.topic, proto)
    pose = decoded["/pose"]
    assert pose.frame_id == "map" and pose.pose.position.x == 1.0 and pose.pose.position.y == 2.0
    assert pose.pose.orientation.z == pytest.approx(np.sin(0.25))
    sphere = decoded["/pose/ellipse"].entities[0].spheres[0]
    # 95 % ellipse of the position block: semi-axes sqrt(5.991 * eigenvalues)
    lam = np.linalg.eigvalsh(np.array([[0.04, 0.01], [0.01, 0.09]]))
    assert sphere.size.x == pytest.approx(2 * np.sqrt(5.991464547 * lam[1]), rel=1e-6)
    assert sphere.size.y == pytest.approx(2 * np.sqrt(5.991464547 * lam[0]), rel=1e-6)
    assert decoded["/tf"].parent_frame_id == "map" and decoded["/tf"].child_frame_id == "base_link"


def test_a_cut_file_reads_up_to_its_last_flushed_chunk(tmp_path: Path) -> None:
    path = tmp_path / "cut.mcap"
    f = SessionFile(path, {})
    _write(f, 20)
    f.flush()
    flushed = path.stat().st_size
    _write(f, 20, t0=1_700_000_100.0)
    f.flush()
    data = path.read_bytes()  # a kill -9 in the middle of the second chunk:
    cut = tmp_path / "cut2.mcap"
    cut.write_bytes(data[: flushed + 200])
    rec = Recording([cut])
    msgs = list(read_recording([cut], rec))
    assert rec.truncated is not None and "cut short" in rec.truncated
    images = [m for m in msgs if m.topic == "/camera/image"]
    assert len(images) == 20
    assert max(m.log_ns for m in msgs) < 1_700_000_100 * 10**9


def test_rotation_starts_a_new_complete_part(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    f = SessionFile(path, {"seed": "1"}, rotate_mb=0.001)
    for k in range(3):
        _write(f, 3, t0=1_700_000_000.0 + k)
        f.flush()
    f.close()
    assert f.files == [part_path(path, i) for i in range(4)]  # every flush passed 1 kB
    for p in f.files:
        with p.open("rb") as fh:
            reader = make_reader(fh)
            assert len(reader.get_summary().channels) == len(TOPICS)
            assert json.loads(next(iter(reader.iter_metadata())).metadata["part"]) == f.files.index(p)
    assert part_path(path, 2).name == "r-002.mcap"


# --------------------------------------------------------------------------------------------
# the recorder
# --------------------------------------------------------------------------------------------


def test_the_hand_over_never_waits_and_counts_what_it_drops(tmp_path: Path) -> None:
    rec = Recorder(RecordingConfig(path=tmp_path / "q.mcap"))  # its writer not started
    left = np.zeros((60, 80), dtype=np.uint8)
    t = time.perf_counter()
    for i in range(recorder_mod.MAX_QUEUED_FRAMES + 10):
        rec.frame(1.0 + i, left, None, delta=[0.0, 0.0, 0.0], pan=0.0, moving=False, image=True,
                  disparity=False)
    assert time.perf_counter() - t < 0.5
    assert rec.dropped == 10
    rec.start()
    rec.close()
    info = rec.info()
    assert info is not None and info.dropped == 10 and info.error is None
    msgs = list(read_recording([tmp_path / "q.mcap"], Recording([tmp_path / "q.mcap"])))
    inputs = [json.loads(m.data) for m in msgs if m.topic == "/localizer/input"]
    assert [r["seq"] for r in inputs] == list(range(recorder_mod.MAX_QUEUED_FRAMES))


def test_a_bad_path_is_reported_and_nothing_raises(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    rec = Recorder(RecordingConfig(path=blocker / "sub" / "x.mcap"))
    rec.start()
    rec.pose(None)
    rec.call("start_global", cause="start")
    deadline = time.time() + 5
    while rec.error is None and time.time() < deadline:
        time.sleep(0.02)
    rec.call("start_global", cause="control")
    rec.close()
    info = rec.info()
    assert info is not None and info.error is not None and str(blocker) in info.error
    assert info.dropped >= 1


def test_recording_settings_bad_values_give_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[recording]\nrotate_mb = -5\n")
    assert _cli(["config", "check", str(cfg)]) == 2
    err = capsys.readouterr()
    text = err.out + err.err
    assert "recording.rotate_mb" in text
    assert RecordingConfig(path=Path("/tmp/d")).session_path(0.0).name == "lino-19700101-000000.mcap"
    assert RecordingConfig(path=Path("/tmp/x.mcap")).session_path() == Path("/tmp/x.mcap")


# --------------------------------------------------------------------------------------------
# the commands' bad inputs
# --------------------------------------------------------------------------------------------


def _one_line_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str], *needles: str) -> None:
    assert _cli(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("lino-loc: error: "), err
    for n in needles:
        assert n in err[0], err


def test_replay_bad_inputs_give_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _one_line_exit_2(["replay", str(tmp_path / "none.mcap")], capsys, "none.mcap", "no such file")
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording\n" * 10)
    _one_line_exit_2(["replay", str(text)], capsys, "notes.mcap", "not an MCAP file")
    other = tmp_path / "other.mcap"  # an MCAP file of someone else: no camera channel
    from mcap.writer import Writer

    with other.open("wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        cid = w.register_channel("/chatter", "json", sid)
        w.add_message(cid, 1, b"{}", 1)
        w.finish()
    _one_line_exit_2(["replay", str(other)], capsys, "other.mcap", "/camera/image", "/chatter")
    _one_line_exit_2(["replay", str(other), "--out", str(other)], capsys, "overwrite")


def test_without_the_extra_the_commands_name_it(monkeypatch: pytest.MonkeyPatch,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "mcap", None)  # as if not installed: import raises
    with pytest.raises(LinoLocError, match=r"pip install 'lino-loc\[viz\]'"):
        require_viz("lino-loc replay")
    _one_line_exit_2(["replay", "x.mcap"], capsys, "lino-loc[viz]")
    from services.commands.run import recording_config
    from services.config import ServiceConfig

    with pytest.raises(LinoLocError, match=r"lino-loc\[viz\]"):
        recording_config(ServiceConfig.simulated_defaults(), "session.mcap")
    with pytest.raises(LinoLocError, match=r"\.mcap"):
        recording_config(ServiceConfig.simulated_defaults(), "session.bag")


def test_a_full_disk_stops_recording_says_why_and_nothing_raises(tmp_path: Path) -> None:
    """The file is a link to /dev/full: every write fails with ENOSPC, as on a full disk."""
    path = tmp_path / "full.mcap"
    path.symlink_to("/dev/full")
    rec = Recorder(RecordingConfig(path=path))
    rec.start()
    left = np.zeros((60, 80), dtype=np.uint8)
    deadline = time.time() + 10
    i = 0
    while rec.error is None and time.time() < deadline:
        rec.frame(1.0 + i, left, None, delta=[0.0, 0.0, 0.0], pan=0.0, moving=False, image=True,
                  disparity=False)
        i += 1
        time.sleep(0.01)
    rec.close()
    info = rec.info()
    assert info is not None and info.error is not None and "No space left" in info.error
    rec.frame(99.0, left, None, delta=[0.0, 0.0, 0.0], pan=0.0)  # after the failure: counted, no raise
    assert rec.info().dropped >= 1


def test_a_foxglove_sdk_channel_takes_the_same_topic_and_schema() -> None:
    import foxglove

    from services.recording.channels import sdk_channel_args

    for topic in ("/pose", "/pose/estimate"):
        args = sdk_channel_args(topic)
        ch = foxglove.Channel(**args)
        assert ch.topic() == topic and ch.schema_name() == TOPICS[topic].schema_name
        ch.close()
