"""The pose port's topic names and the subscription prefixes that can match them.

Kept apart from :mod:`services.messages` (the payload models, which need numpy and pydantic)
so that the pose relay (:mod:`services.pose_relay`), a process of its own, imports only
pyzmq. :data:`services.messages.TOPICS` maps the same names to their models.
"""

from __future__ import annotations

#: The published topics (docs/zeromq.md), each message's first frame.
TOPIC_NAMES: tuple[str, ...] = ("pose", "status", "particles", "truth")
#: Every subscription prefix that can match a published topic (a topic's name starts with
#: it), the empty one included; subscriptions outside it are ignored.
TOPIC_PREFIXES: frozenset[bytes] = frozenset(
    t.encode("ascii")[:k] for t in TOPIC_NAMES for k in range(len(t) + 1)
)
#: The longest subscription that can match a topic: the longest topic name, bytes.
MAX_SUBSCRIPTION_BYTES = max(len(t) for t in TOPIC_NAMES)
