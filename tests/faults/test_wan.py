"""The WAN relay (bench/wan.py) carries a byte stream both ways
intact and in order, whatever it delays: a lost chunk waits, it is never
dropped."""

from __future__ import annotations

import socket
import threading

import pytest

from bench.wan import Wan


@pytest.mark.timeout(60)
def test_the_wan_carries_every_byte_both_ways_in_order() -> None:
    server = socket.create_server(("127.0.0.1", 0))

    def echo() -> None:
        conn, _ = server.accept()
        with conn:
            while data := conn.recv(65536):
                conn.sendall(data)

    threading.Thread(target=echo, daemon=True).start()
    # Every chunk "lost" (loss 1.0): each waits the retransmission time, none vanishes.
    wan = Wan(("127.0.0.1", 0), server.getsockname()[:2], delay_s=0.01, loss=1.0, rto_s=0.02)
    try:
        c = socket.create_connection(wan.address)
        sent = bytes(range(256)) * 400
        got = bytearray()
        for i in range(0, len(sent), 4096):
            c.sendall(sent[i : i + 4096])
        while len(got) < len(sent):
            got += c.recv(65536)
        assert bytes(got) == sent
        up, down = wan.stats["up"], wan.stats["down"]
        assert up[1] == down[1] == len(sent)
        assert up[2] == up[0] and down[2] == down[0]  # every chunk lost, all delivered
        c.close()
    finally:
        wan.close()
        server.close()
