"""Real node processes on loopback for integration and system tests.

:class:`Cluster` copies a mission onto free ports, spawns nodes as separate
processes (``python -m zplatform node ...``), and watches the CN's telemetry
from the test process. Waiting is always on telemetry predicates (or process
exit), never on sleeps; every spawned process is killed at exit.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from tests.waits import poll_until
from zplatform.config import Mission
from zplatform.core.datavector import DataVector
from zplatform.ground.link import GroundLink
from zplatform.mission.load import load_mission
from zplatform.runtime.transport import rewrite_endpoints
from zplatform.security.pki import ensure_mission_pki

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"


class Cluster:
    """``transport``: the copy's ``security.transport`` (``"plain"`` for a
    test whose attacker must reach the nodes); the mission's own otherwise.
    An mTLS mission's PKI is made as ``up`` makes it (the session's config
    directory, tests/conftest.py), so every node and the test's ground find it."""

    def __init__(
        self, mission_file: str | Path, tmp: Path, *, transport: str | None = None
    ) -> None:
        self.path = tmp / "mission.yaml"
        rewrite_endpoints(mission_file, self.path)
        if transport is not None:
            raw = yaml.safe_load(self.path.read_text())
            raw.setdefault("security", {})["transport"] = transport
            self.path.write_text(yaml.safe_dump(raw, sort_keys=False))
        self.mission: Mission = load_mission(self.path)
        if self.mission.mtls:
            ensure_mission_pki(self.mission)
        self.tmp = tmp
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self._rx: GroundLink | None = None

    # -- processes ---------------------------------------------------------
    def spawn(
        self, name: str, *extra: str, env: dict[str, str] | None = None
    ) -> subprocess.Popen[bytes]:
        """Start node ``name`` (or ``"world"``, the mission's vehicle world).

        A device node of a mission with a vehicle world needs that world:
        the first one spawned starts it and waits for it to serve (its
        ``READY`` line), as ``zplatform up`` does. Spawning ``"world"``
        again returns the running one."""
        if name == "world" and "world" in self.procs:
            return self.procs["world"]
        if (
            name in self.mission.device_nodes
            and self.mission.world is not None
            and "world" not in self.procs
        ):
            self.spawn("world")
            self._wait_ready("world")
        e = dict(os.environ, PYTHONUNBUFFERED="1")
        e.update(env or {})
        log = open(self.tmp / f"{name}.log", "ab")  # noqa: SIM115 - closed with the process
        # "world": the mission's vehicle world process (zplatform world), not a node.
        argv = (
            ["world", str(self.path)]
            if name == "world"
            else ["node", str(self.path), name, "--summary", str(self.tmp / f"{name}.json")]
        )
        p = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "zplatform",
                *argv,
                # These clusters run no ground node: the CN must not wait for one.
                *(["--ground-wait", "0"] if name == "cn" else []),
                *extra,
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
            env=e,
            cwd=ROOT,
        )
        self.procs[name] = p
        return p

    def _wait_ready(self, name: str, timeout_s: float = 60.0) -> None:
        """Block until process ``name`` printed ``READY`` (or fail with its log)."""
        p = self.procs[name]

        def ready() -> bool:  # the line the child writes; failing at once if it exited
            if p.poll() is not None:
                raise AssertionError(f"{name} exited:\n{self.log(name)[-3000:]}")
            return "READY" in self.log(name)

        if not poll_until(ready, timeout_s):
            raise AssertionError(f"{name} did not get ready:\n{self.log(name)[-3000:]}")

    def log(self, name: str) -> str:
        return (self.tmp / f"{name}.log").read_text(errors="replace")

    def kill(self, name: str) -> None:
        p = self.procs.pop(name)
        p.kill()
        p.wait()

    def close(self) -> None:
        if self._rx is not None:
            self._rx.close()
        for p in self.procs.values():
            if p.poll() is None:
                p.terminate()
        for p in self.procs.values():
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()

    def __enter__(self) -> Cluster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- telemetry ---------------------------------------------------------
    @property
    def rx(self) -> GroundLink:
        """The test's ground: a tool's link, checking telemetry as every ground does."""
        if self._rx is None:
            self._rx = GroundLink(self.mission, events=False)
        return self._rx

    @property
    def session(self) -> Any:
        """The test's zenoh session (the ground link's)."""
        return self.rx.ns.session

    @property
    def tm(self) -> DataVector:
        return self.rx.dv

    def wait_for(
        self, pred: Callable[[DataVector], bool], timeout_s: float = 30.0, what: str = ""
    ) -> None:
        """Read telemetry until ``pred(dv)`` holds; fail with the last values."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for name, p in self.procs.items():
                if p.poll() is not None and name == "cn":
                    raise AssertionError(f"cn exited ({p.returncode}):\n{self.log('cn')[-3000:]}")
            if self.rx.next(0.2) is not None and pred(self.rx.dv):
                return
        raise AssertionError(
            f"timed out waiting for {what or pred}; last telemetry: "
            f"{ {k: v for k, v in self.rx.dv.values().items() if k.startswith('cn_')} }"
        )

    def advance(self, loops: int, timeout_s: float = 30.0) -> None:
        """Wait until the CN ran ``loops`` more loops."""
        self.wait_for(lambda dv: True, timeout_s, "telemetry")
        target = int(self.tm.get("cn_loop")) + loops
        self.wait_for(
            lambda dv: int(dv.get("cn_loop")) >= target, timeout_s, f"cn_loop >= {target}"
        )


def zp_side_by_side(
    *runs: tuple[str, ...],
    cwd: Path | None = None,
    stdins: dict[int, str] | None = None,
    envs: dict[int, dict[str, str]] | None = None,
    base_env: dict[str, str] | None = None,
    timeout: float = 90,
) -> list[subprocess.CompletedProcess[str]]:
    """``python -m zplatform ARGS`` for each argument list, all running at
    once (each verb is a process of its own, so the test waits for the
    slowest, not the sum), each one's result in order.

    ``stdins`` and ``envs`` are by position: text written to that process's
    stdin at once (then closed), variables over ``base_env`` (default: this
    process's environment). Blocks until all have ended or ``timeout``
    passed for one (subprocess.TimeoutExpired); kills whatever is left on
    the way out."""
    stdins, envs = stdins or {}, envs or {}
    base = dict(os.environ) if base_env is None else base_env
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "zplatform", *args],
            cwd=cwd or ROOT,
            stdin=subprocess.PIPE if i in stdins else subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**base, **envs.get(i, {})},
        )
        for i, args in enumerate(runs)
    ]
    done = []
    try:
        for i, text in stdins.items():  # all of it at once: a few lines
            stdin = procs[i].stdin
            assert stdin is not None
            stdin.write(text)
            stdin.close()
            procs[i].stdin = None  # written and closed: communicate() only reads
        for p in procs:
            out, err = p.communicate(timeout=timeout)
            done.append(subprocess.CompletedProcess(p.args, p.returncode, out, err))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.communicate()
    return done
