"""Protocol 2.0 framing against the examples published in the ROBOTIS e-Manual, stuffing,
the streaming parser, angle conversions, and the real SDK's bytes as seen by the emulator."""

from __future__ import annotations

import math
import time

import dynamixel_sdk
import dynamixel_sdk.port_handler as sdk_port_handler
import numpy as np
import pytest

from drivers.dynamixel_protocol import (
    CorruptPacket,
    Inst,
    Packet,
    PacketParser,
    crc16,
    decode,
    encode_instruction,
    encode_status,
    rad_to_tick,
    read_params,
    stuff,
    sync_read_params,
    sync_write_params,
    tick_to_rad,
    unstuff,
    write_params,
)
from drivers.sim.dynamixel_emulator import DynamixelBusEmulator


def h(text: str) -> bytes:
    return bytes.fromhex(text)


# Published examples (ROBOTIS e-Manual, Protocol 2.0 instruction pages).
SPEC_EXAMPLES = {
    "ping id 1": (encode_instruction(1, Inst.PING), "FF FF FD 00 01 03 00 01 19 4E"),
    "ping status (model 1030, fw 38)": (
        encode_status(1, 0, h("06 04 26")),
        "FF FF FD 00 01 07 00 55 00 06 04 26 65 5D",
    ),
    "read present position": (
        encode_instruction(1, Inst.READ, read_params(132, 4)),
        "FF FF FD 00 01 07 00 02 84 00 04 00 1D 15",
    ),
    "read status (166)": (
        encode_status(1, 0, (166).to_bytes(4, "little")),
        "FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0",
    ),
    "write goal position 512": (
        encode_instruction(1, Inst.WRITE, write_params(116, (512).to_bytes(4, "little"))),
        "FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89",
    ),
    "empty status": (encode_status(1, 0), "FF FF FD 00 01 04 00 55 00 A1 0C"),
    "reboot id 1": (encode_instruction(1, Inst.REBOOT), "FF FF FD 00 01 03 00 08 2F 4E"),
    "sync read ids 1,2 present position": (
        encode_instruction(0xFE, Inst.SYNC_READ, sync_read_params(132, 4, [1, 2])),
        "FF FF FD 00 FE 09 00 82 84 00 04 00 01 02 CE FA",
    ),
    "sync read status of id 2 (2079)": (
        encode_status(2, 0, (2079).to_bytes(4, "little")),
        "FF FF FD 00 02 08 00 55 00 1F 08 00 00 BA BE",
    ),
    "sync write ids 1,2 goal 150/170": (
        encode_instruction(
            0xFE,
            Inst.SYNC_WRITE,
            sync_write_params(
                116, 4, {1: (150).to_bytes(4, "little"), 2: (170).to_bytes(4, "little")}
            ),
        ),
        "FF FF FD 00 FE 11 00 83 74 00 04 00 01 96 00 00 00 02 AA 00 00 00 82 87",
    ),
}


@pytest.mark.parametrize("name", list(SPEC_EXAMPLES))
def test_encoding_matches_published_examples(name: str) -> None:
    ours, published = SPEC_EXAMPLES[name]
    assert ours == h(published), f"{name}: {ours.hex(' ').upper()}"


def test_crc_of_ping_header() -> None:
    assert crc16(h("FF FF FD 00 01 03 00 01")) == 0x4E19
    # a CRC detects any single-bit error in the example packet
    wire = bytearray(h("FF FF FD 00 01 07 00 02 84 00 04 00"))
    good = crc16(wire)
    for i in range(len(wire)):
        for bit in range(8):
            wire[i] ^= 1 << bit
            assert crc16(wire) != good
            wire[i] ^= 1 << bit


@pytest.mark.parametrize("name", list(SPEC_EXAMPLES))
def test_decode_round_trip(name: str) -> None:
    wire, _ = SPEC_EXAMPLES[name]
    pkt = decode(wire)
    again = (
        encode_status(pkt.id, pkt.error, pkt.params)
        if pkt.is_status
        else encode_instruction(pkt.id, pkt.instruction, pkt.params)
    )
    assert again == wire


def test_byte_stuffing_inserts_fd_and_round_trips() -> None:
    assert stuff(h("03 FF FF FD 01")) == h("03 FF FF FD FD 01")
    assert stuff(h("FF FF FD FD")) == h("FF FF FD FD FD")
    rng = np.random.default_rng(7)
    for _ in range(300):
        # payloads rich in FF/FD so the pattern occurs often
        body = bytes(rng.choice([0xFF, 0xFD, 0x00, 0x55], size=int(rng.integers(1, 40))))
        s = stuff(body)
        assert unstuff(s) == body
        # after stuffing, the header pattern FF FF FD is always followed by FD
        for i in range(len(s) - 2):
            if s[i : i + 3] == b"\xff\xff\xfd":
                assert s[i + 3 : i + 4] == b"\xfd"


def test_stuffed_packet_length_and_crc_cover_stuffed_bytes() -> None:
    params = write_params(116, h("FF FF FD 00"))
    wire = encode_instruction(1, Inst.WRITE, params)
    length = wire[5] | wire[6] << 8
    assert length == 1 + len(params) + 1 + 2  # one FD inserted
    assert crc16(wire[:-2]) == wire[-2] | wire[-1] << 8
    assert decode(wire).params == params


def test_parser_handles_garbage_split_and_corrupt_packets() -> None:
    rng = np.random.default_rng(3)
    a = encode_instruction(1, Inst.PING)
    b = encode_status(2, 0, h("FF FF FD 07"))
    bad = bytearray(encode_instruction(3, Inst.READ, read_params(132, 4)))
    bad[-1] ^= 0x5A
    stream = b"\x00\x13\xff" + a + bytes(bad) + b"\xfd\xff" + b
    parser = PacketParser()
    items: list[Packet | CorruptPacket] = []
    pos = 0
    while pos < len(stream):
        n = int(rng.integers(1, 6))
        items += parser.feed(stream[pos : pos + n])
        pos += n
    assert [type(x).__name__ for x in items] == ["Packet", "CorruptPacket", "Packet"]
    assert items[0] == Packet(1, Inst.PING, b"")
    assert items[2] == Packet(2, Inst.STATUS, h("FF FF FD 07"), 0)
    assert parser.skipped_bytes == 5


def test_angle_tick_conversion() -> None:
    assert rad_to_tick(0.0) == 2048
    assert rad_to_tick(math.pi / 2) == 3072
    assert rad_to_tick(-math.pi / 2) == 1024
    assert tick_to_rad(4096) == pytest.approx(math.pi)
    rng = np.random.default_rng(1)
    for a in rng.uniform(-3.1, 3.1, 200):
        assert abs(tick_to_rad(rad_to_tick(a)) - a) <= math.pi / 4096 + 1e-12


def test_real_sdk_bytes_match_our_encoder_and_emulator_replies() -> None:
    """The real SDK's packets, captured by the emulator, equal ours; its replies decode."""
    # The SDK as shipped spins holding the GIL while it waits; the emulator thread needs the
    # GIL to answer, and the interpreter hands it over every 5 ms: keep the timeout above that.
    sdk_port_handler.LATENCY_TIMER = 16
    with DynamixelBusEmulator((1, 2)) as emu:
        emu.wire_log = []
        port = dynamixel_sdk.PortHandler(emu.port)
        assert port.openPort()
        try:
            ph = dynamixel_sdk.PacketHandler(2.0)
            model, result, error = ph.ping(port, 1)
            assert (result, error, model) == (dynamixel_sdk.COMM_SUCCESS, 0, 1020)
            # a value containing FF FF FD exercises stuffing in the SDK and in the emulator
            result, error = ph.write4ByteTxRx(port, 1, 108, 0x00FDFFFF)
            assert (result, error) == (dynamixel_sdk.COMM_SUCCESS, 0)
            value, result, _ = ph.read4ByteTxRx(port, 1, 108)
            assert value == 0x00FDFFFF
            _, result, _ = ph.ping(port, 9)  # nobody there
            assert result == dynamixel_sdk.COMM_RX_TIMEOUT
            time.sleep(0.01)
        finally:
            port.closePort()
        sent = b"".join(emu.wire_log)
        assert encode_instruction(1, Inst.PING) in sent
        assert encode_instruction(9, Inst.PING) in sent
        # dynamixel-sdk 4.1 (Python) does not stuff what it sends (addStuffing builds a new
        # list that txPacket ignores); the emulator accepts both forms, and both carry the
        # same parameters. Our replies are stuffed and the SDK unstuffs them (value above).
        packets = [p for p in PacketParser().feed(sent) if isinstance(p, Packet)]
        writes = [p for p in packets if p.instruction == Inst.WRITE]
        assert [w.params for w in writes] == [write_params(108, h("FF FF FD 00"))]
        assert emu.crc_errors_received == 0
