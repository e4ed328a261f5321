"""zenoh's lowlatency transport carries every message a lowlatency mission
may send (LOWLATENCY_MAX_MESSAGE), byte for byte.

It cannot fragment: on zenoh 1.10 a put above about 48 KiB is dropped
without an error (measured while choosing the limit). If a zenoh upgrade
lowers that edge under our limit, this test fails before a mission loses
telemetry in silence.
"""

from __future__ import annotations

import queue

import zenoh

from zplatform.core.messages import LOWLATENCY_MAX_MESSAGE, lowlatency_for
from zplatform.mission.load import decode_mission
from zplatform.runtime.transport import free_port, is_matching, open_session, zenoh_config


def test_lowlatency_carries_the_largest_message_a_lowlatency_mission_sends() -> None:
    cn, dn = free_port(), free_port()
    m = decode_mission(
        f"""
mission: ll
nodes:
  cn: {{listen: ["tcp/127.0.0.1:{cn}"]}}
  dn0: {{listen: ["tcp/127.0.0.1:{dn}"], connect: ["tcp/127.0.0.1:{cn}"]}}
transport: {{lowlatency: true, shared_memory: false}}
regions:
  dn0_to_cn:
    - {{name: v, type: f64}}
"""
    )
    assert lowlatency_for(m)
    got: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    a = open_session(zenoh_config(m, "cn"))
    b = open_session(zenoh_config(m, "dn0"))
    try:
        sub = a.declare_subscriber(
            "ll/probe", zenoh.handlers.Callback(lambda s: got.put(s.payload.to_bytes()))
        )
        pub = b.declare_publisher("ll/probe")
        # Readiness: the publisher sees the subscriber (no sleep).
        matched: queue.SimpleQueue[bool] = queue.SimpleQueue()
        listener = pub.declare_matching_listener(
            zenoh.handlers.Callback(lambda st: matched.put(bool(st.matching)))
        )
        if not is_matching(pub):
            while not matched.get(timeout=10):
                pass
        for size in (1, 1024, LOWLATENCY_MAX_MESSAGE // 2, LOWLATENCY_MAX_MESSAGE):
            payload = bytes(i % 251 for i in range(size))
            pub.put(payload)
            assert got.get(timeout=5) == payload, size
        listener.undeclare()
        sub.undeclare()
    finally:
        b.close()
        a.close()
