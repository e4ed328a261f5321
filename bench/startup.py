"""Benchmark: what a mission costs to start and stop under ``zplatform up``.

Runs ``zplatform up MISSION --duration D --free-ports --quiet`` ``--runs``
times and times each from launch to exit; ``overhead`` is that wall time
less the run's own ``D`` (the start-up, to the first loop, plus the stop).
Every mission start-up of the live tests and of an operator's ``up`` pays
it. Baseline, measured in the same run: as many bare interpreters as the
mission has processes, started at once, each importing what a node imports
(``zplatform.node.control``, ``.device``, ``.ground``) and exiting: the
floor no start-up of Python nodes goes below on this host.

``--against TREE`` times another checkout of the repository too (its
``python -m zplatform``, run from that directory), interleaved run by run
with this one so the host's drift falls on both alike: how a change moved
the start-up.

Run: ``python -m bench.startup [--quick] [--runs N] [--against TREE]``;
writes ``bench/results/startup.json``. Blocks for about ``runs × (D + 4 s)``.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.common import REPO_ROOT, bench_argparser, write_result
from zplatform import load_mission

MISSION = REPO_ROOT / "configs" / "recovery_igniter.yaml"
IMPORTS = "import zplatform.node.control, zplatform.node.device, zplatform.node.ground"


def _env() -> dict[str, str]:
    # One bytecode cache, as the test suite has (tests/conftest.py): a
    # start-up measured compiling every module from source would measure
    # PYTHONDONTWRITEBYTECODE, not the platform.
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    env.setdefault(
        "PYTHONPYCACHEPREFIX", str(Path(tempfile.gettempdir()) / "zplatform-bench-pycache")
    )
    return env


def time_up(tree: Path, mission: Path, duration_s: float) -> float:
    """Seconds from launching ``up`` in ``tree`` to its exit; RuntimeError
    if the run did not end cleanly."""
    t0 = time.monotonic()
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "zplatform",
            "up",
            str(mission),
            "--duration",
            str(duration_s),
            "--free-ports",
            "--quiet",
        ],
        cwd=tree,
        env=_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        timeout=120,
        check=False,
    )
    wall = time.monotonic() - t0
    if done.returncode != 0:
        tail = done.stderr.decode(errors="replace").strip().splitlines()[-3:]
        raise RuntimeError(f"up in {tree} exited {done.returncode}: {tail}")
    return wall


def time_imports(processes: int) -> float:
    """Seconds for ``processes`` interpreters, started at once, to import
    what the nodes import and exit."""
    t0 = time.monotonic()
    procs = [
        subprocess.Popen([sys.executable, "-c", IMPORTS], cwd=REPO_ROOT, env=_env())
        for _ in range(processes)
    ]
    if any(p.wait(60) != 0 for p in procs):
        raise RuntimeError("a bare interpreter failed to import the nodes' modules")
    return time.monotonic() - t0


def _commit(tree: Path) -> str:
    """``tree``'s commit, ``+`` if its files differ from it."""
    git = ["git", "-C", str(tree)]
    head = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(
        [*git, "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True
    )
    return head.stdout.strip() + ("+" if dirty.stdout.strip() else "")


def _figures(walls: list[float], duration_s: float) -> dict[str, Any]:
    over = sorted(w - duration_s for w in walls)
    return {
        "runs": len(walls),
        "wall_s": [round(w, 3) for w in walls],
        "overhead_p50_s": round(statistics.median(over), 3),
        "overhead_min_s": round(over[0], 3),
        "overhead_max_s": round(over[-1], 3),
    }


def main(argv: list[str] | None = None) -> int:
    p = bench_argparser(__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=None, help="starts per tree (quick 3, full 12)")
    p.add_argument("--duration", type=float, default=1.0, help="each run's --duration (s)")
    p.add_argument("--mission", type=Path, default=MISSION)
    p.add_argument("--against", type=Path, default=None, help="another checkout to time too")
    a = p.parse_args(argv)
    a.mission = a.mission.resolve()  # one file for both trees (each runs from its own directory)
    runs = a.runs or (3 if a.quick else 12)
    m = load_mission(a.mission)
    processes = len(m.nodes) + 1 + (1 if m.world is not None else 0)  # + up itself
    trees = {"this": REPO_ROOT}
    if a.against is not None:
        trees["against"] = a.against.resolve()
    walls: dict[str, list[float]] = {n: [] for n in trees}
    floor: list[float] = []
    time_up(REPO_ROOT, a.mission, a.duration)  # warms the bytecode cache, not kept
    for _ in range(runs):
        for name, tree in trees.items():
            walls[name].append(time_up(tree, a.mission, a.duration))
        floor.append(time_imports(processes))
    variants: dict[str, dict[str, Any]] = {
        f"up_{name}": _figures(w, a.duration) for name, w in walls.items()
    }
    variants["floor_imports"] = {
        "runs": len(floor),
        "processes": processes,
        "wall_p50_s": round(statistics.median(floor), 3),
    }
    if "against" in walls:
        variants["ratio_this_over_against_p50"] = {
            "overhead": round(
                variants["up_this"]["overhead_p50_s"] / variants["up_against"]["overhead_p50_s"], 3
            )
        }
    params = {
        "mission": a.mission.name,
        "duration_s": a.duration,
        "runs": runs,
        "against": _commit(a.against) if a.against else None,
        "this": _commit(REPO_ROOT),
        "load_average_at_end": os.getloadavg(),
    }
    write_result("startup", params, variants, a.json)  # its latency table has no column here
    for name, fig in variants.items():
        print(f"  {name}: " + ", ".join(f"{k} {v}" for k, v in fig.items() if k != "wall_s"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
