"""The intra-host sync between real node processes (transport.intra_host:
auto; docs/architecture.md#intra-host): a DN killed with SIGKILL leaves its
iceoryx2 server behind; the CN's link falls back to zenoh, and the DN
started again takes the service over the dead one's and syncs over shared
memory again."""

from __future__ import annotations

from pathlib import Path

from .harness import CONFIGS, Cluster


def test_a_dn_killed_with_sigkill_and_restarted_syncs_over_shared_memory_again(
    tmp_path: Path,
) -> None:
    with Cluster(CONFIGS / "minimal.yaml", tmp_path) as c:
        c.spawn("dn0")
        c.spawn("cn")
        c.wait_for(lambda dv: dv.get_name("dn0_sync_path") == "shm", 60, "dn0 on shm")
        c.kill("dn0")  # SIGKILL: its server, node and segments stay in /dev/shm
        missed = int(c.tm.get("cn_missed_dn0"))
        c.wait_for(lambda dv: int(dv.get("cn_missed_dn0")) > missed + 10, 30, "dn0 missed")
        c.spawn("dn0")
        # Its replies come again, and over shared memory: the restarted DN
        # removed the dead one's resources and opened the server (a reply
        # says the path its trigger came by; the dead DN's last said shm,
        # so only a reply for a later loop counts).
        last = int(c.tm.get("dn0_loop"))
        c.wait_for(
            lambda dv: dv.get_name("dn0_sync_path") == "shm" and int(dv.get("dn0_loop")) > last,
            60,
            "dn0 back on shm",
        )
        assert "intra-host" not in c.log("dn0")  # no failure to open its link
        # The CN evented both ways (sync_on_shm, then sync_fallback at the kill).
        log = c.log("cn")
        assert "sync_on_shm" in log and "sync_fallback" in log
