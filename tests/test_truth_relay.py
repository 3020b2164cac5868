"""The simulation-only truth relay (services/truth_relay.py): valid truth messages are
republished unchanged, anything else is dropped, and it stops on request."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import zmq

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_fakes import FakePublisher  # noqa: E402

from services.messages import Pose2D, TruthMessage, encode
from services.truth_relay import TruthRelay


def _truth(seq: int) -> list[bytes]:
    return encode("truth", TruthMessage(stamp=1.0 + seq, seq=seq, pose=Pose2D(x=seq, y=0.0, theta=0.0)))


def test_relay_passes_valid_truth_and_drops_the_rest() -> None:
    pub = FakePublisher()
    relay = TruthRelay(zmq.Context.instance(), "inproc://unused", pub)  # type: ignore[arg-type]
    frames = _truth(3)
    assert relay.relay(frames)
    assert pub.frames == [[b"truth", frames[1]]] and relay.relayed == 1
    assert not relay.relay([b"truth"])
    assert not relay.relay([b"pose", frames[1]])
    assert not relay.relay([b"truth", b'{"stamp": "soon"}'])
    assert relay.relayed == 1 and len(pub.frames) == 1


def test_relay_thread_subscribes_and_stops() -> None:
    ctx = zmq.Context()
    sim = ctx.socket(zmq.PUB)
    sim.setsockopt(zmq.LINGER, 0)
    port = sim.bind_to_random_port("tcp://127.0.0.1")
    pub = FakePublisher()
    relay = TruthRelay(ctx, f"tcp://127.0.0.1:{port}", pub)  # type: ignore[arg-type]
    relay.start()
    try:
        deadline = time.monotonic() + 5.0
        seq = 0
        while not pub.frames:
            assert time.monotonic() < deadline, "nothing relayed"
            sim.send_multipart(_truth(seq))
            seq += 1
            time.sleep(0.02)
    finally:
        relay.stop()
        sim.close()
        ctx.term()
    assert not relay.is_alive()
    assert TruthMessage.model_validate_json(pub.frames[0][1]).seq >= 0
