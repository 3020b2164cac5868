"""services.config and `lino-loc config`: defaults, files, environment overrides, every error."""

from __future__ import annotations

import argparse
import json
import tomllib
from pathlib import Path

import pytest

from drivers.dynamixel_head import HeadConfig
from drivers.serial_odometry import OdometryConfig
from services.commands import config_cmd
from services.config import (
    ConfigError,
    ServiceConfig,
    check_config,
    config_as_dict,
    load_config,
    to_toml,
)
from services.status import STATUS_PERIOD_S

ROOT = Path(__file__).resolve().parents[1]
LINO = ROOT / "config" / "lino.toml"
SIM = ROOT / "config" / "sim.toml"


@pytest.fixture(autouse=True)
def _clean_env(monkeypatch):
    import os

    for k in list(os.environ):
        if k.upper().startswith("LINO_LOC__"):
            monkeypatch.delenv(k)


def _cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    config_cmd.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.func(args)


def _write(tmp_path: Path, text: str, name: str = "c.toml") -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


# ------------------------------------------------------------------ shipped files


def test_defaults_are_the_real_robot():
    cfg = ServiceConfig()
    assert not cfg.simulated
    assert cfg.devices.camera.kind == "oakd" and (cfg.devices.camera.oakd.width, cfg.devices.camera.oakd.height) == (640, 400)
    head = cfg.devices.head
    assert (head.kind, head.baudrate, head.pan_id, head.tilt_id) == ("dynamixel", 1_000_000, 1, 2)
    assert cfg.endpoints.pub == "tcp://127.0.0.1:5556" and cfg.endpoints.rep == "tcp://127.0.0.1:5557"
    assert cfg.active_vision.method_config().n_actions == 22
    assert STATUS_PERIOD_S == 1.0


@pytest.fixture
def robot_files(tmp_path, monkeypatch):
    """The files config/lino.toml names (a map, the state folder), made in tmp_path and named
    through the environment, as they are on an installed robot."""
    (tmp_path / "map.npz").write_bytes(b"PK")
    monkeypatch.setenv("LINO_LOC__MAP__PATH", str(tmp_path / "map.npz"))
    monkeypatch.setenv("LINO_LOC__PERSISTENCE__STATE_FILE", str(tmp_path / "state" / "state.json"))


@pytest.mark.parametrize("path", [LINO, SIM])
def test_shipped_files_pass_config_check(path, capsys, robot_files):
    assert check_config(path) == []
    assert _cli(["config", "check", str(path)]) == 0
    assert capsys.readouterr().out.strip() == f"{path}: ok"


def test_lino_toml_is_the_real_robot():
    cfg = load_config(LINO)
    assert not cfg.simulated
    assert cfg.devices.head.port.startswith("/dev/") and cfg.devices.odometry.port == "/dev/ttyACM0"
    assert str(cfg.map.path).startswith("/var/lib/lino-loc/")
    assert str(cfg.persistence.state_file).startswith("/var/lib/lino-loc/")


def test_sim_toml_equals_simulated_defaults():
    cfg = load_config(SIM)
    assert cfg.simulated
    assert cfg.devices.head.port == "auto" and cfg.devices.odometry.port == "auto"
    assert cfg.map.build is not None and cfg.map.build.world == cfg.devices.camera.sim.world
    assert cfg == ServiceConfig.simulated_defaults()


def test_device_sections_are_the_driver_configs():
    from drivers.oakd import OakdConfig
    from lino_loc.localizer import LocalizerConfig

    cfg = load_config(LINO)
    assert type(cfg.devices.camera.oakd) is OakdConfig and cfg.devices.camera.oakd.fps == 30.0
    assert type(cfg.localizer) is LocalizerConfig
    head = cfg.devices.head.driver_config()
    assert type(head) is HeadConfig and head.port == cfg.devices.head.port
    odo = cfg.devices.odometry.driver_config()
    assert type(odo) is OdometryConfig and odo.track_width == pytest.approx(0.30)


# ------------------------------------------------------------------ errors


BAD = """\
[devices.head]
baudrat = 1000000
pan_id = 300

[devices.camera]
kind = "realsense"

[devices.camera.oakd]
fps = -1

[endpoints]
pub = "localhost:5556"

[active_vision]
min_interval_s = "many"

[loging]
level = "DEBUG"
"""


def test_check_reports_every_error_with_its_field_path(tmp_path, capsys):
    path = _write(tmp_path, BAD)
    problems = check_config(path)
    expected = {
        "devices.head.baudrat": "unknown key",
        "devices.head.pan_id": "less than or equal to 252",
        "devices.camera.kind": "'oakd' or 'sim'",
        "devices.camera.oakd.fps": "greater than 0",
        "endpoints.pub": "not a ZeroMQ endpoint",
        "active_vision.min_interval_s": "valid number",
        "loging": "unknown key",
    }
    assert len(problems) == len(expected), problems
    for field, text in expected.items():
        hits = [p for p in problems if p.startswith(f"{path}: {field}: ")]
        assert len(hits) == 1 and text in hits[0], (field, problems)
    assert _cli(["config", "check", str(path)]) == 2
    out = capsys.readouterr().out.splitlines()
    assert out == problems


def test_check_json_output(tmp_path, capsys, robot_files):
    good, bad = LINO, _write(tmp_path, "[logging]\nlevel = 3\n")
    assert _cli(["config", "check", "--json", str(good), str(bad)]) == 2
    obj = json.loads(capsys.readouterr().out)
    assert obj["ok"] is False
    assert obj["files"][str(good)] == {"ok": True, "errors": []}
    assert obj["files"][str(bad)]["errors"][0].startswith(f"{bad}: logging.level: ")


def test_toml_syntax_error_names_the_line(tmp_path, capsys):
    path = _write(tmp_path, '[map]\npath = "/x"\nbuild = \n')
    problems = check_config(path)
    assert len(problems) == 1
    assert problems[0].startswith(f"{path}: TOML syntax error") and "line 3" in problems[0]
    assert _cli(["config", "check", str(path)]) == 2
    assert "line 3" in capsys.readouterr().out


def test_missing_file_is_a_one_line_error(tmp_path):
    with pytest.raises(ConfigError, match="file not found"):
        load_config(tmp_path / "nope.toml")


def test_cross_field_checks(tmp_path):
    # "auto" ports belong to the simulated robot
    p = _write(tmp_path, '[devices.head]\nport = "auto"\n')
    (msg,) = check_config(p)
    assert 'devices.head.port = "auto"' in msg
    # active vision may not ask for angles the head cannot reach
    p = _write(tmp_path, "[active_vision]\npan_max = 3.0\n", "b.toml")
    (msg,) = check_config(p)
    assert "exceeds the head's limits" in msg
    # a relative device name is refused
    p = _write(tmp_path, '[devices.odometry]\nport = "ttyACM0"\n', "c.toml")
    (msg,) = check_config(p)
    assert msg.startswith(f"{p}: devices.odometry.port: ") and "absolute path" in msg
    # the driver's own consistency checks still apply
    p = _write(tmp_path, "[devices.head]\npan_id = 2\ntilt_id = 2\n", "d.toml")
    (msg,) = check_config(p)
    assert "pan_id and tilt_id must differ" in msg


# ------------------------------------------------------------------ the files it names


def _files_config(tmp_path: Path, map_path: Path, state_file: Path, extra: str = "") -> Path:
    return _write(tmp_path, f'[map]\npath = "{map_path}"\n[persistence]\nstate_file = "{state_file}"\n{extra}')


def test_config_check_names_a_missing_map(tmp_path, capsys):
    missing = tmp_path / "maps" / "office.npz"
    path = _files_config(tmp_path, missing, tmp_path / "state" / "s.json")
    problems = check_config(path)
    assert problems == [f"{path}: map.path: {missing}: no such file"]
    assert _cli(["config", "check", str(path)]) == 2
    assert capsys.readouterr().out.splitlines() == problems
    # load_config (what `lino-loc run` reads) does not look at the file system
    assert load_config(path).map.path == missing


def test_config_check_map_that_is_a_folder_and_the_robot_default(tmp_path, monkeypatch):
    (tmp_path / "state").mkdir()
    path = _files_config(tmp_path, tmp_path, tmp_path / "state" / "s.json")
    assert check_config(path) == [f"{path}: map.path: {tmp_path}: is a folder, not a file"]
    monkeypatch.setenv("LINO_LOC__MAP__PATH", str(tmp_path / "nope.npz"))
    monkeypatch.setenv("LINO_LOC__PERSISTENCE__STATE_FILE", str(tmp_path / "state" / "s.json"))
    assert check_config(LINO) == [f"{LINO}: map.path: {tmp_path / 'nope.npz'}: no such file"]


def test_config_check_a_map_to_build_need_not_exist(tmp_path):
    text = SIM.read_text().replace("~/.cache/lino-loc/maps/", f"{tmp_path}/maps/")
    text = text.replace("~/.local/state/lino-loc/", f"{tmp_path}/state/")
    path = _write(tmp_path, text, "sim.toml")
    assert f"{tmp_path}/maps/" in text and check_config(path) == []


def test_config_check_state_folder_must_be_creatable(tmp_path):
    (tmp_path / "map.npz").write_bytes(b"PK")
    (tmp_path / "plain").write_text("a file, not a folder")
    deep = tmp_path / "a" / "b" / "s.json"  # does not exist, can be created
    assert check_config(_files_config(tmp_path, tmp_path / "map.npz", deep)) == []
    under_file = tmp_path / "plain" / "s.json"
    path = _files_config(tmp_path, tmp_path / "map.npz", under_file, )
    (msg,) = check_config(path)
    assert msg.startswith(f"{path}: persistence.state_file: {tmp_path / 'plain'}: not a folder")
    path = _files_config(tmp_path, tmp_path / "missing.npz", tmp_path / "plain" / "x" / "s.json")
    problems = check_config(path)
    assert [p.split(": ")[1] for p in problems] == ["map.path", "persistence.state_file"]


def test_load_config_raises_one_line_summary(tmp_path):
    path = _write(tmp_path, BAD)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert "\n" not in str(info.value) and "and 6 more" in str(info.value)
    assert len(info.value.problems) == 7


# ------------------------------------------------------------------ environment


def test_environment_overrides_file_field_by_field(tmp_path, monkeypatch):
    path = _write(tmp_path, '[devices.head]\nport = "/dev/ttyUSB3"\npan_id = 5\n[logging]\nlevel = "INFO"\n')
    monkeypatch.setenv("LINO_LOC__DEVICES__HEAD__PORT", "/dev/serial/by-id/usb-FTDI-x")
    monkeypatch.setenv("lino_loc__logging__level", "debug")  # case-insensitive
    monkeypatch.setenv("LINO_LOC__DEVICES__CAMERA__SIM__SCENE_CHANGES", '["boxes", "people"]')
    cfg = load_config(path)
    assert cfg.devices.head.port == "/dev/serial/by-id/usb-FTDI-x"  # env > file
    assert cfg.devices.head.pan_id == 5  # the rest of the file's table is kept
    assert cfg.logging.level == "DEBUG"
    assert cfg.devices.camera.sim.scene_changes == ["boxes", "people"]  # JSON for lists
    assert cfg.devices.head.tilt_id == 2  # defaults below the file


def test_environment_without_file(monkeypatch):
    monkeypatch.setenv("LINO_LOC__ENDPOINTS__PUB", "tcp://127.0.0.1:6000")
    assert load_config().endpoints.pub == "tcp://127.0.0.1:6000"
    # a non-loopback address needs CURVE keys (tests/test_curve_auth.py), also from the environment
    monkeypatch.setenv("LINO_LOC__ENDPOINTS__PUB", "tcp://0.0.0.0:6000")
    with pytest.raises(ConfigError, match="endpoints.curve.server_secret_key"):
        load_config()


def test_environment_errors_are_named(tmp_path, monkeypatch):
    monkeypatch.setenv("LINO_LOC__ENDPOINTS__SNDHWM", "lots")
    monkeypatch.setenv("LINO_LOC__LOGGINGG__LEVEL", "DEBUG")  # typo in the section
    monkeypatch.setenv("LINO_LOC__DEVICES__HEAD__PROT", "/dev/x")  # typo in the field
    problems = check_config(LINO)
    assert len(problems) == 3, problems
    joined = "\n".join(problems)
    assert f"{LINO}: endpoints.sndhwm: " in joined and "(from environment LINO_LOC__ENDPOINTS__SNDHWM)" in joined
    assert f"{LINO}: loggingg: unknown key (from environment LINO_LOC__LOGGINGG__LEVEL)" in joined
    assert "devices.head.prot: unknown key" in joined and "LINO_LOC__DEVICES__HEAD__PROT" in joined


# ------------------------------------------------------------------ show


@pytest.mark.parametrize("path", [LINO, SIM])
def test_show_toml_round_trips(path, capsys):
    assert _cli(["config", "show", "--config", str(path)]) == 0
    out = capsys.readouterr().out
    again = ServiceConfig(**tomllib.loads(out))
    assert again == load_config(path)


def test_show_json_is_one_object_with_env_applied(monkeypatch, capsys):
    monkeypatch.setenv("LINO_LOC__ACTIVE_VISION__ENABLED", "false")
    assert _cli(["config", "show", "--json", "--config", str(LINO)]) == 0
    out = capsys.readouterr().out
    obj = json.loads(out)
    assert out.count("\n") == 1
    assert obj["active_vision"]["enabled"] is False
    assert list(obj["devices"]["head"])[0] == "kind"


def test_show_bad_file_raises_user_error(tmp_path):
    with pytest.raises(ConfigError):
        _cli(["config", "show", "--config", str(_write(tmp_path, BAD))])


def test_to_toml_writes_scalars_lists_and_unset():
    text = to_toml({"a": 1, "b": {"c": "x\"y", "d": [1.5, 2.0], "e": None, "f": {"g": True}}})
    assert tomllib.loads(text) == {"a": 1, "b": {"c": 'x"y', "d": [1.5, 2.0], "f": {"g": True}}}
    assert "# e = (unset)" in text


def test_schema_command_prints_the_config_schema(capsys):
    assert _cli(["config", "schema"]) == 0
    schema = json.loads(capsys.readouterr().out)
    assert set(schema["properties"]) == set(config_as_dict(ServiceConfig()))


# ------------------------------------------------------------------ retired keys


@pytest.mark.parametrize(
    ("text", "key", "says"),
    [
        ("[active_vision]\nn_actions = 22\n", "active_vision.n_actions", "no longer a setting"),
        ("[active_vision]\ntrigger_doubt = 0.5\n", "active_vision.trigger_doubt",
         "lino_loc.active_vision.ActiveVisionConfig.trigger_doubt"),
        ("[publish]\nstatus_period_s = 1.0\n", "publish.status_period_s", "STATUS_PERIOD_S"),
    ],
)
def test_a_retired_key_fails_with_one_line(tmp_path, capsys, text, key, says):
    path = _write(tmp_path, text)
    (line,) = check_config(path)
    assert line.startswith(f"{path}: {key}: ") and says in line
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(info.value) == line
    assert _cli(["config", "check", str(path)]) == 2
    assert capsys.readouterr().out.splitlines() == [line]


def test_run_with_a_retired_key_exits_2_with_one_line(tmp_path, capsys):
    from services.cli import main

    path = _write(tmp_path, "[active_vision]\nmax_particles = 150\n")
    assert main(["run", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"lino-loc: error: {path}: active_vision.max_particles: no longer a setting: the "
                   "active-vision method's own default (lino_loc.active_vision.ActiveVisionConfig.max_particles)"]


def test_a_retired_key_from_the_environment_is_one_line(monkeypatch):
    monkeypatch.setenv("LINO_LOC__ACTIVE_VISION__MOVE_COST", "0.1")
    (line,) = check_config(LINO)
    assert line == (f"{LINO}: active_vision.move_cost: no longer a setting: the active-vision method's own "
                    "default (lino_loc.active_vision.ActiveVisionConfig.move_cost) "
                    "(from environment LINO_LOC__ACTIVE_VISION__MOVE_COST)")


def test_a_renamed_key_names_the_new_one(tmp_path, monkeypatch):
    from services import config as config_module

    monkeypatch.setitem(config_module.RETIRED_KEYS, "persistence.file", "persistence.state_file")
    (line,) = check_config(_write(tmp_path, '[persistence]\nfile = "/x"\n'))
    assert line.endswith("persistence.file: renamed to persistence.state_file")


def test_retired_keys_are_not_settings():
    from services.config import RETIRED_KEYS

    def leaves(model, prefix=""):
        from services.config import _model_of

        out = set()
        for name, f in model.model_fields.items():
            m = _model_of(f.annotation)
            out |= leaves(m, f"{prefix}{name}.") if m is not None else {prefix + name}
        return out

    assert not set(RETIRED_KEYS) & leaves(ServiceConfig)
