"""A device node's end of an intra-host link in a process of its own, for
tests/integration/test_intrahost.py: ``python -m tests.intrahost_peer MODE
PREFIX MISSION RUN BOUND``. It says ``ready`` on stdout once its server
exists (a trigger sent after that waits in its queue), then:

* ``echo``: answers each trigger with its bytes inverted (``b ^ 0xFF``),
  until stdin closes;
* ``hold``: never answers (to be killed with SIGKILL);
* ``ask``: the control node's end instead: sends one trigger, says
  ``ready``, and waits for stdin to close (to be killed with SIGKILL).
"""

from __future__ import annotations

import select
import sys

from zplatform.runtime.intrahost import IntraHostClient, IntraHostServer, link_names


def main() -> None:
    mode, prefix, mission, run, bound = sys.argv[1:6]
    names = link_names(mission, "rocket", run, "cn", "dn0")
    if mode == "ask":
        client = IntraHostClient(names, int(bound), int(bound), prefix=prefix)
        buf = client.trigger(3)
        assert buf is not None
        buf[:] = b"ask"
        assert client.send()
        sys.stdout.write("ready\n")
        sys.stdout.flush()
        sys.stdin.read()
        return
    server = IntraHostServer(names, int(bound), int(bound), prefix=prefix)
    sys.stdout.write("ready\n")
    sys.stdout.flush()
    out = bytearray(int(bound))
    while True:
        # Ends when the test closes our stdin (or kills us).
        if select.select([sys.stdin], [], [], 0)[0] and not sys.stdin.readline():
            break
        view = server.wait(0.05)
        if view is None or mode != "echo":
            continue
        n = len(view)
        reply = server.reply(n)
        if reply is None:
            continue
        # Invert through a scratch buffer (numpy-free: the peer stays small).
        out[:n] = view
        reply[:] = out[:n].translate(_INVERT)
        server.send()
    server.close()


_INVERT = bytes(255 - i for i in range(256))


def leftovers(prefix: str) -> list[str]:
    """The data segments (``*.data``) under ``prefix`` still in /dev/shm."""
    import glob

    return sorted(glob.glob(f"/dev/shm/{prefix}*.data"))


def wipe(prefix: str) -> None:
    """Remove every file iceoryx2 made under ``prefix`` (/dev/shm and its root)."""
    import glob
    import os

    for path in glob.glob(f"/dev/shm/{prefix}*") + glob.glob(
        f"/tmp/iceoryx2/**/{prefix}*", recursive=True
    ):
        try:
            os.unlink(path)
        except OSError:
            pass


if __name__ == "__main__":
    main()
