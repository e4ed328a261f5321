"""Session-wide test set-up.

Every mission authenticates its traffic by default, so every node process a
test starts needs the mission key. The tests run with one random key in the
environment (``ZPLATFORM_KEY``), which the processes they spawn inherit.

Nothing is written to the user's configuration: ``XDG_CONFIG_HOME`` points
at a directory of this session's own (removed at exit), so a key set and
mission PKI that ``up`` (or a test) makes land there, and no deployment
named by the user's environment is used.

Hypothesis runs without its per-example deadline (200 ms by default): the
suite must pass on a busy 2-core box beside a CPU hog, where one example may
wait that long for a CPU, and a test asserts behaviour, not the box's speed
(tests/budget.py).

Likewise a control node loads (and PRM_SAVE writes) its mission's parameter
file: the tests keep them in a directory of their own
(``ZPLATFORM_PARAMS_DIR``), removed at exit, never in the user's.

Missions with a flight recorder (the shipped flight and recovery_igniter
ones) record into a temporary directory of the session
(``ZPLATFORM_RECORDER_DIR``, inherited too), removed at exit, and the
ground archive into another (``ZPLATFORM_ARCHIVE_DIR``): nothing is
written to the user's state directory.

And the registry of running missions (``zplatform ps``; every verb takes a
running mission's name) is the session's own too: a mission that ``up`` runs
elsewhere on the machine is not one a test can see by name (a test that
expects ``keygen led_test`` to fail without a running ``led_test`` failed
whenever someone else ran one).

The suite starts hundreds of Python processes (nodes, ground tools), and
each compiled every zplatform module from source where the environment
says ``PYTHONDONTWRITEBYTECODE`` (this machine's does): a fifth of a second
of CPU per process. Likewise each pytest worker compiled, and rewrote the
asserts of, every test module it collected, run after run (about half of
its collection's CPU). They all share one bytecode cache instead
(``PYTHONPYCACHEPREFIX``, and ``sys.pycache_prefix`` here, before any test
module is imported): the first process compiles a module, the others read
it. In a virtual environment (scripts/test.sh's ``.venv``) the cache is
kept there (``zplatform-test-pycache``), for the next run too; elsewhere it
is a temporary directory removed at exit. Nothing is written beside the
sources either way (a cached file stands for its source only while the
source's size and time are unchanged: Python's and pytest's own check).
"""

from __future__ import annotations

import atexit
import os
import pathlib
import secrets
import shutil
import sys
import tempfile

import pytest
from hypothesis import settings

os.environ.setdefault("ZPLATFORM_KEY", secrets.token_hex(32))
os.environ.pop("ZPLATFORM_KEY_FILE", None)
os.environ.pop("ZPLATFORM_DEPLOYMENT", None)
_CONFIG_HOME = tempfile.mkdtemp(prefix="zplatform-test-config-")
os.environ["XDG_CONFIG_HOME"] = _CONFIG_HOME
atexit.register(shutil.rmtree, _CONFIG_HOME, ignore_errors=True)

settings.register_profile("zplatform", deadline=None)
settings.load_profile("zplatform")

_PARAMS_DIR = tempfile.mkdtemp(prefix="zplatform-test-params-")
os.environ["ZPLATFORM_PARAMS_DIR"] = _PARAMS_DIR
atexit.register(shutil.rmtree, _PARAMS_DIR, True)

_RUN_DIR = tempfile.mkdtemp(prefix="zplatform-test-run-")
os.environ["ZPLATFORM_RUNTIME_DIR"] = _RUN_DIR
atexit.register(shutil.rmtree, _RUN_DIR, True)

_RECORDER_DIR = tempfile.mkdtemp(prefix="zplatform-test-recorder-")
os.environ["ZPLATFORM_RECORDER_DIR"] = _RECORDER_DIR
atexit.register(shutil.rmtree, _RECORDER_DIR, True)

_ARCHIVE_DIR = tempfile.mkdtemp(prefix="zplatform-test-archive-")
os.environ["ZPLATFORM_ARCHIVE_DIR"] = _ARCHIVE_DIR
atexit.register(shutil.rmtree, _ARCHIVE_DIR, True)

if sys.prefix != sys.base_prefix:  # a virtual environment: the suite's own
    _PYCACHE = os.path.join(sys.prefix, "zplatform-test-pycache")
    os.makedirs(_PYCACHE, exist_ok=True)
else:
    _PYCACHE = tempfile.mkdtemp(prefix="zplatform-test-pycache-")
    atexit.register(shutil.rmtree, _PYCACHE, True)
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
os.environ["PYTHONPYCACHEPREFIX"] = _PYCACHE
sys.dont_write_bytecode = False
sys.pycache_prefix = _PYCACHE


# Tests that run node processes in real time (loops at 100 Hz, zenoh
# sessions, network namespaces) run one after another, on one worker, when
# the suite runs on several (scripts/test.sh: pytest-xdist, --dist
# loadgroup); the in-process tests (unit, property, lockstep) fill the other.
# Two live missions at once would be a second busy box for each other's
# deadlines: the live tests are built to pass beside a CPU hog, not beside
# each other by design, and the namespaces and relays they make are named
# per test run, not per worker.
# pytest 9.2 keeps an item's id in ``_id`` (a NodeId), and pytest-xdist 3.8
# still suffixes the old ``_nodeid`` with the group, which nothing reads
# (pytest-xdist issue 1386): no group took effect, and two live missions ran
# at once beside the hog (the pad flood's control node went unscheduled for
# 100 ms in half the hogged runs). So the hook below gives the worker's items
# the ``@group`` suffix itself (:func:`_suffix_group`), as xdist means to.
# The fault and integration files below start no node process and fly no
# mission (their nodes' logic, zenoh sessions, routers and relays are in this
# process, on free ports; the fuzzers are CPU-bound subprocesses with no
# deadline): they need not wait behind the live tests, and run on whichever
# worker is free. So does a test marked ``no_mission`` in a live file: it
# starts processes (a CLI verb, the web console's server, a relay) but no
# node and no mission, so it is no busier a neighbour than an in-process
# test, and the live worker's share (the suite's critical path) stays short.
_IN_PROCESS_SYSTEM = {
    "test_failover_sim.py",
    "test_flight.py",
    "test_lockstep_missions.py",
    "test_role.py",
}
_IN_PROCESS = {
    "faults": {
        "test_acl_declarations.py",
        "test_fuzz.py",
        "test_insider.py",
        "test_insider_acl.py",
        "test_insider_terms.py",
        "test_keyspace_faults.py",
        "test_wan.py",
    },
    "integration": {
        "test_archive_server.py",
        "test_console_history_remote.py",
        "test_ground_event_intake.py",
        "test_lowlatency.py",
        "test_recorder_server.py",
        "test_routers.py",
        "test_shm_sync.py",
    },
    "system": _IN_PROCESS_SYSTEM,
}
_LIVE_UNIT = {("unit", "test_world.py")}


def _runs_live(path: pathlib.Path) -> bool:
    kind = path.parent.name
    if kind in {"faults", "integration", "system"}:
        return path.name not in _IN_PROCESS[kind]
    return (kind, path.name) in _LIVE_UNIT


def _suffix_group(item: pytest.Item) -> None:
    """Give ``item``'s node id xdist's ``@group`` suffix, which the
    controller's loadgroup scheduler reads (once: a fixed xdist adds it too)."""
    try:
        from _pytest.nodeid import NodeId
    except ImportError:  # a pytest before 9.2: xdist's own ``_nodeid`` works
        return
    groups = sorted(
        {
            str(m.args[0] if m.args else m.kwargs.get("name", "default"))
            for m in item.iter_markers("xdist_group")
        }
    )
    if not groups or "@" in item.nodeid:
        return
    item._id = NodeId.parse(f"{item.nodeid}@{'_'.join(groups)}")  # type: ignore[attr-defined]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if not config.pluginmanager.hasplugin("xdist"):
        return
    for item in items:
        if _runs_live(item.path) and item.get_closest_marker("no_mission") is None:
            item.add_marker(pytest.mark.xdist_group("live"))
    if hasattr(config, "workerinput") and config.getvalue("loadgroup"):
        for item in items:
            _suffix_group(item)
