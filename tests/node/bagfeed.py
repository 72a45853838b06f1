"""Feeding a recording's messages to a NodeBody as a transport would (deserialized, in bag
order), and collecting what it publishes."""

from __future__ import annotations

import time
from pathlib import Path

from rosbags.highlevel import AnyReader

DEMO = Path(__file__).resolve().parents[2] / "data" / "demo"


def demo_messages(t_max: float = float("inf")) -> list[tuple[str, str, object]]:
    """(topic, msgtype, message) of the demo recording up to t_max s after its start."""
    out = []
    with AnyReader([DEMO / "demo"]) as bag:
        for conn, stamp, raw in bag.messages():
            if (stamp - bag.start_time) * 1e-9 > t_max:
                break
            out.append((conn.topic, conn.msgtype, bag.deserialize(raw, conn.msgtype)))
    return out


class Published:
    """publish(name, msgtype, msg) that keeps every message by name (serialized once, as a
    transport would, so that a message the store cannot encode fails here)."""

    def __init__(self, store):
        self.store, self.by_name = store, {}

    def __call__(self, name: str, msgtype: str, msg) -> None:
        self.store.serialize_cdr(msg, msgtype)
        self.by_name.setdefault(name, []).append(msg)


def feed(body, messages, wait: float = 0.0) -> None:
    """Hand `messages` to body.receive, then wait until its queue is empty (at most 120 s)."""
    for topic, msgtype, msg in messages:
        body.receive(topic, msgtype, msg)
        if wait:
            time.sleep(wait)
    t0 = time.monotonic()
    while body.queue and time.monotonic() - t0 < 120:
        time.sleep(0.05)
