"""The $ODO line protocol (docs/protocols.md) and the differential-drive arc kinematics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.odometry_protocol import (
    U32,
    LineError,
    OdometrySample,
    arc_increment,
    arc_step,
    crc8,
    format_line,
    parse_line,
    ticks_to_metres,
    wrap_delta,
)
from lino_loc.poses import compose

DOC_EXAMPLE = b"$ODO,1234,567890,4294967290,1048576*9F\r\n"  # as printed in docs/protocols.md


def test_crc8_catalogue_check_value() -> None:
    # CRC-8/SMBUS catalogue check: crc("123456789") = 0xF4
    assert crc8(b"123456789") == 0xF4
    assert crc8(b"") == 0


def test_documented_example_line() -> None:
    assert format_line(1234, 567890, 4294967290, 1048576) == DOC_EXAMPLE
    assert parse_line(DOC_EXAMPLE) == OdometrySample(1234, 567890, 4294967290, 1048576)
    assert "$ODO,1234,567890,4294967290,1048576*9F" in open("docs/protocols.md").read()


def test_round_trip_and_wrapping_of_values() -> None:
    rng = np.random.default_rng(11)
    for _ in range(500):
        v = [int(x) for x in rng.integers(0, U32, 4, dtype=np.uint64)]
        line = format_line(*v)
        assert line.endswith(b"\r\n") and len(line) < 128
        assert parse_line(line) == OdometrySample(*v)
    assert parse_line(format_line(-1, U32 + 5, -3, 0)) == OdometrySample(U32 - 1, 5, U32 - 3, 0)


@pytest.mark.parametrize(
    "line, reason",
    [
        (b"$ODO,1,2,3,4*00\r\n", "checksum mismatch"),
        (b"$ODO,1,2,3,4\r\n", "no '*hh' checksum"),
        (b"ODO,1,2,3,4*11\r\n", "no '$' at the start"),
        (b"$ODO,1,2,3,4*G1\r\n", "bad checksum digits"),
    ],
)
def test_bad_lines_are_rejected(line: bytes, reason: str) -> None:
    with pytest.raises(LineError) as info:
        parse_line(line)
    assert info.value.reason == reason


def _signed(body: bytes) -> bytes:
    return b"$%s*%02X\r\n" % (body, crc8(body))


def test_field_errors_and_extensions() -> None:
    for body, reason in [
        (b"ODO,1,2,3", "too few fields"),
        (b"XYZ,1,2,3,4", "unknown sentence"),
        (b"ODO,1,2,x,4", "non-numeric field"),
        (b"ODO,1,2,-3,4", "field out of range"),
        (b"ODO,1,2,4294967296,4", "field out of range"),
    ]:
        with pytest.raises(LineError) as info:
            parse_line(_signed(body))
        assert info.value.reason == reason
    # extra fields after right_ticks are ignored (forward compatible)
    assert parse_line(_signed(b"ODO,7,8,9,10,42,ok")) == OdometrySample(7, 8, 9, 10)


def test_checksum_catches_digit_transpositions_and_single_errors() -> None:
    body = b"ODO,1234,567890,4294967290,1048576"
    good = crc8(body)
    for i in range(len(body) - 1):
        swapped = bytearray(body)
        swapped[i], swapped[i + 1] = swapped[i + 1], swapped[i]
        if swapped != body:
            assert crc8(swapped) != good  # NMEA XOR would miss every one of these
        for d in b"0123456789":
            changed = bytearray(body)
            if changed[i] != d:
                changed[i] = d
                assert crc8(changed) != good


def test_checksum_catches_every_adjacent_swap_in_any_line() -> None:
    # CRC-8 is linear (crc(x ^ e) = crc(x) ^ crc(e) with init 0): a swap is missed only if the
    # error pattern e = (d, d) at two adjacent bytes has crc 0, for d = a ^ b of two characters
    alphabet = b"0123456789,ODO"
    diffs = {a ^ b for a in alphabet for b in alphabet if a != b}
    for d in diffs:
        for tail in range(0, 126):  # bytes after the pair, up to the longest line
            assert crc8(bytes((d, d)) + bytes(tail)) != 0


def test_wrap_delta() -> None:
    assert wrap_delta(5, U32 - 5) == 10
    assert wrap_delta(U32 - 5, 5) == -10
    assert wrap_delta(100, 100) == 0
    assert wrap_delta(2**31 - 1, 0) == 2**31 - 1


def test_arc_straight_and_spin() -> None:
    np.testing.assert_allclose(arc_increment(0.3, 0.3, 0.3), [0.3, 0.0, 0.0])
    np.testing.assert_allclose(arc_increment(-0.15, 0.15, 0.3), [0.0, 0.0, 1.0], atol=1e-15)


def test_arc_matches_circle_closed_form() -> None:
    b = 0.3
    dl, dr = 0.2, 0.4  # over one interval
    dth = (dr - dl) / b
    radius = b / 2 * (dr + dl) / (dr - dl)
    np.testing.assert_allclose(
        arc_increment(dl, dr, b), [radius * math.sin(dth), radius * (1 - math.cos(dth)), dth]
    )
    # N equal arcs compose into the same circle: exact, whatever N
    for n in (1, 7, 50):
        pose = np.zeros(3)
        for _ in range(n):
            pose = compose(pose, arc_increment(dl / n, dr / n, b))
        np.testing.assert_allclose(pose[:2], arc_increment(dl, dr, b)[:2], atol=1e-12)


def test_arc_small_angle_series_is_continuous() -> None:
    b = 0.3
    for eps in (1e-9, 9.9e-7, 1.01e-6, 1e-5):
        dl, dr = 0.1, 0.1 + eps * b
        got = arc_increment(dl, dr, b)
        dth = (dr - dl) / b
        ds = (dl + dr) / 2
        np.testing.assert_allclose(got[0], ds * math.sin(dth) / dth, rtol=1e-12)
        # 1 - cos(x) = 2 sin^2(x/2) without cancellation: the reference for tiny angles
        np.testing.assert_allclose(got[1], ds * 2 * math.sin(dth / 2) ** 2 / dth, rtol=1e-9)
    # vectorized
    out = arc_increment(np.array([0.1, 0.2]), np.array([0.1, -0.2]), b)
    assert out.shape == (2, 3)


def test_scalar_arc_step_equals_vectorized() -> None:
    rng = np.random.default_rng(4)
    dl = rng.normal(0, 0.01, 300)
    dr = dl + rng.choice([0.0, 1e-9, 1e-7, 1e-3, 0.02], 300) * rng.normal(size=300)
    vec = arc_increment(dl, dr, 0.3)
    for i in range(300):
        np.testing.assert_allclose(arc_step(dl[i], dr[i], 0.3), vec[i], rtol=1e-12, atol=1e-18)


def test_ticks_to_metres() -> None:
    assert ticks_to_metres(4096, 0.05, 4096) == pytest.approx(2 * math.pi * 0.05)


def _counters(stamp: float, board_ms: int, left: int, right: int):
    from drivers.interfaces import BoardCounters

    return BoardCounters(stamp, board_ms % U32, left % U32, right % U32, 1e-4, -1e-4, 0.3)


def test_wheel_travel_between_two_readings_of_one_board_run() -> None:
    from drivers.odometry_protocol import CLOCK_TOLERANCE_S, wheel_travel

    a = _counters(1000.0, 5_000, 100, 200)
    # 20 s later by both clocks, the counters wrapped forward / went backwards through 0
    b = _counters(1020.0, 25_000, U32 - 50, 10_200)
    dl, dr = wheel_travel(a, b)
    assert dl == pytest.approx(-150 * 1e-4) and dr == pytest.approx(-10_000 * 1e-4)
    # the board's clock wraps too (every 49.7 days)
    c = _counters(1020.0, U32 - 1_000 + 20_000, 100, 200)
    assert wheel_travel(_counters(1000.0, U32 - 1_000, 100, 200), c) == (0.0, 0.0)
    # latency between the two stamps within the tolerance
    assert wheel_travel(a, _counters(1021.5, 25_000, 100, 200)) == (0.0, 0.0)
    assert CLOCK_TOLERANCE_S == 2.0


def test_wheel_travel_names_a_board_restart() -> None:
    from drivers.odometry_protocol import wheel_travel

    a = _counters(1000.0, 60_000, 100, 200)
    went_back = wheel_travel(a, _counters(1010.0, 4_000, 0, 0))
    assert isinstance(went_back, str) and "went back" in went_back and "restarted" in went_back
    # restarted after the save and up longer than the board was before: its clock lags
    lag = wheel_travel(_counters(1000.0, 1_000, 100, 200), _counters(1030.0, 5_000, 0, 0))
    assert isinstance(lag, str) and "advanced 4.0 s while the host's advanced 30.0 s" in lag
    backwards = wheel_travel(a, _counters(990.0, 60_000, 100, 200))
    assert isinstance(backwards, str) and "out of order" in backwards
