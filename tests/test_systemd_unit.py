"""systemd/lino-loc.service passes `systemd-analyze verify` with nothing on stderr.

`verify` checks that ExecStart's binary exists and is executable. The unit names the
installed path (/opt/lino-loc/.venv/bin/lino-loc, docs/install.md); the test copies the
unit to a temporary folder with *only* that path prefix replaced by this environment's
real `lino-loc` console script, and checks that nothing else differs. `verify` does not
look up users or groups, so the `lino-loc` user need not exist here; the shipped
sysusers.d file that creates it is exercised with `systemd-sysusers --root`.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
UNIT = ROOT / "systemd" / "lino-loc.service"
SYSUSERS = ROOT / "systemd" / "lino-loc.sysusers.conf"
INSTALLED_BIN = "/opt/lino-loc/.venv/bin/lino-loc"
EXEC_START = f"{INSTALLED_BIN} run --config /etc/lino-loc/lino.toml"

ANALYZE = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(
    ANALYZE is None, reason="systemd-analyze not installed (.ci/run installs the systemd package)"
)


def _entries(text: str) -> list[tuple[str, str, str]]:
    """(section, key, value) for every assignment, in order (keys may repeat)."""
    out, section = [], ""
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
            continue
        key, _, value = line.partition("=")
        out.append((section, key.strip(), value.strip()))
    return out


def _values(entries, section: str, key: str) -> list[str]:
    return [v for s, k, v in entries if s == section and k == key]


def _real_binary() -> Path:
    exe = Path(sys.executable).parent / "lino-loc"
    if not exe.exists():
        found = shutil.which("lino-loc")
        assert found, "the lino-loc console script is not installed (pip install -e .)"
        exe = Path(found)
    return exe


def _verify(unit: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "SYSTEMD_LOG_LEVEL": "info", "SYSTEMD_LOG_COLOR": "0", "SYSTEMD_PAGER": ""}
    return subprocess.run(
        [ANALYZE, "verify", str(unit)], capture_output=True, text=True, env=env, timeout=60, cwd=unit.parent
    )


def test_unit_contents():
    e = _entries(UNIT.read_text(encoding="utf-8"))
    svc = "Service"
    assert _values(e, svc, "Type") == ["notify"]
    assert _values(e, svc, "ExecStart") == [EXEC_START]
    assert _values(e, svc, "WatchdogSec") == ["5"]
    assert _values(e, svc, "Restart") == ["on-failure"]
    assert _values(e, svc, "RestartSec")
    assert _values(e, svc, "User") == ["lino-loc"]
    assert set(_values(e, svc, "SupplementaryGroups")[0].split()) == {"dialout", "plugdev"}
    assert _values(e, svc, "StateDirectory") == ["lino-loc"]
    assert _values(e, svc, "ConfigurationDirectory") == ["lino-loc"]
    for key in ("NoNewPrivileges", "ProtectHome", "PrivateTmp"):
        assert _values(e, svc, key) == ["yes"], key
    assert _values(e, svc, "ProtectSystem") == ["strict"]
    assert _values(e, svc, "DevicePolicy") == ["closed"]
    allowed = {v.split()[0] for v in _values(e, svc, "DeviceAllow")}
    assert allowed == {"char-ttyUSB", "char-ttyACM", "char-usb_device"}
    assert _values(e, svc, "PrivateDevices") in ([], ["no"])  # would hide the devices
    assert set(_values(e, svc, "RestrictAddressFamilies")[0].split()) == {
        "AF_UNIX", "AF_INET", "AF_INET6", "AF_NETLINK"
    }
    assert _values(e, "Install", "WantedBy") == ["multi-user.target"]


def _bytes(v: str) -> int:
    units = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}
    return int(v[:-1]) * units[v[-1]] if v[-1] in units else int(v)


def test_memory_is_capped_above_the_measured_footprint():
    """The daemon's measured peak (~152 MB on the simulated robot, ~270 MB expected with
    depthai on the robot: the unit's comment) plus the pose relay at its memory limit fits
    under MemoryHigh, MemoryHigh under MemoryMax, and swap cannot stretch the cap."""
    from services.relay_publisher import RelayConfig

    e = _entries(UNIT.read_text(encoding="utf-8"))
    high, cap = _values(e, "Service", "MemoryHigh"), _values(e, "Service", "MemoryMax")
    assert len(high) == 1 and len(cap) == 1
    expected = (270 << 20) + RelayConfig().max_resident_mb * 1e6
    assert expected <= _bytes(high[0]) < _bytes(cap[0]) <= 1 << 30
    assert _values(e, "Service", "MemorySwapMax") == ["0"]


def test_hardening_the_daemon_lives_with():
    e = _entries(UNIT.read_text(encoding="utf-8"))
    svc = "Service"
    for key, value in {
        "PrivateMounts": "yes", "ProtectProc": "invisible", "MemoryDenyWriteExecute": "yes",
        "UMask": "0077", "IPAddressDeny": "any", "IPAddressAllow": "localhost",
        "RestrictSUIDSGID": "yes", "LockPersonality": "yes", "ProtectClock": "yes",
    }.items():
        assert _values(e, svc, key) == [value], key
    filters = _values(e, svc, "SystemCallFilter")
    assert filters[0] == "@system-service"
    assert set(filters[1].lstrip("~").split()) == {"@privileged", "@resources"} and filters[1].startswith("~")
    assert _values(e, svc, "CapabilityBoundingSet") == [""]
    # what it needs stays: its groups, its devices, no user namespace that would drop them
    assert _values(e, svc, "PrivateUsers") == [] and _values(e, svc, "PrivateNetwork") == []
    assert _values(e, svc, "ProcSubset") == []


@needs_analyze
def test_security_exposure_stays_low():
    """`systemd-analyze security --offline=yes`: 2.1 before the memory caps and the added
    hardening, 1.3 after; the rest is what the daemon needs (devices, network, groups)."""
    res = subprocess.run(
        [ANALYZE, "security", "--offline=yes", "--no-pager", str(UNIT)],
        capture_output=True, text=True, timeout=60, env={**os.environ, "SYSTEMD_COLORS": "0"},
    )
    assert res.returncode == 0, res.stderr
    line = [x for x in res.stdout.splitlines() if "Overall exposure level" in x]
    assert line, res.stdout[-2000:]
    exposure = float(line[0].split(":")[1].split()[0])
    assert exposure <= 1.3, line[0]


@needs_analyze
def test_systemd_analyze_verify_is_silent(tmp_path):
    text = UNIT.read_text(encoding="utf-8")
    assert text.count(INSTALLED_BIN) == 1
    copy = tmp_path / "lino-loc.service"
    copy.write_text(text.replace(f"ExecStart={INSTALLED_BIN}", f"ExecStart={_real_binary()}"), encoding="utf-8")
    # only the ExecStart line differs
    diff = [(a, b) for a, b in zip(text.splitlines(), copy.read_text().splitlines(), strict=True) if a != b]
    assert len(diff) == 1 and diff[0][0].startswith("ExecStart=")
    res = _verify(copy)
    assert res.returncode == 0, res.stderr
    assert res.stderr == "", f"systemd-analyze verify warned:\n{res.stderr}"


@needs_analyze
def test_verify_does_check_exec_start(tmp_path):
    """The rewrite above is needed, and verify is not vacuous: a missing binary is fatal."""
    if Path(INSTALLED_BIN).exists():
        pytest.skip(f"{INSTALLED_BIN} is installed on this machine")
    copy = tmp_path / "lino-loc.service"
    shutil.copy(UNIT, copy)
    res = _verify(copy)
    assert res.returncode != 0
    assert f"{INSTALLED_BIN} is not executable" in res.stderr
    # and a misspelt key is reported (as a warning on stderr, exit 0)
    copy.write_text(
        UNIT.read_text().replace(f"ExecStart={INSTALLED_BIN}", f"ExecStart={_real_binary()}")
        .replace("WatchdogSec=5", "WatchdogSecs=5"),
        encoding="utf-8",
    )
    res = _verify(copy)
    assert "WatchdogSecs" in res.stderr


@pytest.mark.skipif(shutil.which("systemd-sysusers") is None, reason="systemd-sysusers not installed")
def test_sysusers_file_creates_the_user_with_device_groups(tmp_path):
    root = tmp_path / "root"
    (root / "etc").mkdir(parents=True)
    res = subprocess.run(
        ["systemd-sysusers", f"--root={root}", str(SYSUSERS)], capture_output=True, text=True, timeout=60
    )
    assert res.returncode == 0, res.stderr
    passwd = (root / "etc" / "passwd").read_text()
    user = [line for line in passwd.splitlines() if line.startswith("lino-loc:")]
    assert len(user) == 1
    fields = user[0].split(":")
    assert fields[5] == "/var/lib/lino-loc" and fields[6].endswith("nologin")
    assert int(fields[2]) < 1000  # a system user
    groups = {line.split(":")[0]: line.split(":")[3] for line in (root / "etc" / "group").read_text().splitlines()}
    assert "lino-loc" in groups["dialout"].split(",")
    assert "lino-loc" in groups["plugdev"].split(",")
