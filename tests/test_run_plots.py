"""`lino-loc plot`: the PNGs of a tiny recording, and bad input in one line."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap")
pytest.importorskip("matplotlib")

sys.path.insert(0, str(Path(__file__).parent))
from ros2_session import write_session  # noqa: E402

from services.run_plots import read_run, truth_at  # noqa: E402


def _cli(argv: list[str]) -> int:
    from services.cli import main

    return main(argv)


def _png(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def test_it_writes_the_trajectory_and_the_timeline(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_session(tmp_path / "s.mcap")
    assert _cli(["plot", str(tmp_path / "s.mcap"), "--out", str(tmp_path / "png"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [Path(p).name for p in out["png"]] == ["trajectory.png", "timeline.png"]
    for p in out["png"]:
        w, h = _png(Path(p))
        assert w > 400 and h > 300
    run = read_run([tmp_path / "s.mcap"])
    assert run.survey is None and run.world is None  # no map file, no simulated world named
    inside, true = truth_at(run)
    assert inside.all()  # the truth at the poses' own stamps: the fixed offset of the session
    assert np.allclose(run.poses[:, :2] - true[:, :2], [0.05, -0.02], atol=1e-9)
    assert list(run.quality[:2]) == pytest.approx([0.5, 0.53])


def test_a_recording_without_truth_still_plots(tmp_path: Path) -> None:
    write_session(tmp_path / "s.mcap", frames=3, truth=False)
    assert _cli(["plot", str(tmp_path / "s.mcap"), "--out", str(tmp_path / "png")]) == 0
    assert (tmp_path / "png" / "timeline.png").is_file()


def test_the_simulated_world_and_the_survey_are_drawn_when_named(tmp_path: Path) -> None:
    from services.config import ServiceConfig
    from services.recording.recording_reader import Recording, read_recording
    from services.recording.session_file import SessionFile

    write_session(tmp_path / "s.mcap", frames=3)
    np.savez(tmp_path / "map.npz", poses=np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.5]]))
    meta = {"config": ServiceConfig.simulated_defaults().model_dump_json(), "map_path": str(tmp_path / "map.npz")}
    f = SessionFile(tmp_path / "sim.mcap", meta)
    for m in read_recording([tmp_path / "s.mcap"], Recording([tmp_path / "s.mcap"])):
        f.write(m.topic, m.log_ns, m.publish_ns, m.data)
    f.close()
    run = read_run([tmp_path / "sim.mcap"])
    assert run.world == "office" and len(run.walls) >= 4 and run.boxes
    assert run.survey is not None and run.survey.shape == (2, 3)
    assert _cli(["plot", str(tmp_path / "sim.mcap"), "--out", str(tmp_path / "png")]) == 0


def _one_line_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str], *needles: str) -> None:
    assert _cli(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("lino-loc: error: "), err
    for n in needles:
        assert n in err[0], err


def test_bad_input_gives_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    out = str(tmp_path / "png")
    _one_line_exit_2(["plot", str(tmp_path / "none.mcap"), "--out", out], capsys, "none.mcap", "no such file")
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording\n" * 10)
    _one_line_exit_2(["plot", str(text), "--out", out], capsys, "notes.mcap", "not an MCAP file")
    from mcap.writer import Writer

    other = tmp_path / "other.mcap"
    with other.open("wb") as fh:
        w = Writer(fh)
        w.start()
        cid = w.register_channel("/chatter", "json", w.register_schema("x", "jsonschema", b"{}"))
        w.add_message(cid, 1, b"{}", 1)
        w.finish()
    _one_line_exit_2(["plot", str(other), "--out", out], capsys, "/pose/estimate", "/chatter")
    write_session(tmp_path / "s.mcap", frames=2)
    _one_line_exit_2(["plot", str(tmp_path / "s.mcap"), "--out", str(text)], capsys, "not a folder")
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # as if not installed
    _one_line_exit_2(["plot", str(tmp_path / "s.mcap"), "--out", out], capsys, "lino-loc[eval]")
