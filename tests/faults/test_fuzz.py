"""Coverage-guided fuzzing (atheris) of the frame decoder and the command
request path, bounded: each run is a subprocess with ``-runs=N`` and
``-max_total_time``; the targets and properties are in fuzz_targets.py.

The default suite runs each target briefly (a smoke run of the harness and
the properties, a few seconds); ``-m slow`` runs them long. Set
``ZPLATFORM_FUZZ_RUNS`` to fuzz longer still (e.g. 10000000) by hand.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("atheris", reason="atheris is not installed (pip install atheris)")

ROOT = Path(__file__).resolve().parents[2]
SCALE = int(os.environ.get("ZPLATFORM_FUZZ_RUNS", "0"))


def fuzz(target: str, corpus: Path, runs: int, max_s: int) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [
            *(sys.executable, "-m", "tests.faults.fuzz_targets", target),
            "--seed",  # the starting corpus, written by the fuzzing process itself
            f"-runs={SCALE or runs}",
            f"-max_total_time={max_s if not SCALE else 3600}",
            "-seed=1",
            "-max_len=512",
            f"-artifact_prefix={corpus.parent}/",
            str(corpus),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=(max_s if not SCALE else 3600) + 60,
    )


def check(r: subprocess.CompletedProcess[str]) -> None:
    out = r.stdout + r.stderr
    tail = out[-4000:]
    assert r.returncode == 0, tail
    assert "Uncaught Python exception" not in out, tail
    assert "Done " in r.stderr, tail


@pytest.mark.timeout(120)
def test_fuzz_frame_decoder_raises_only_codec_errors(tmp_path: Path) -> None:
    check(fuzz("codec", tmp_path / "corpus", runs=20_000, max_s=20))


@pytest.mark.timeout(120)
def test_fuzz_command_requests_never_raise(tmp_path: Path) -> None:
    check(fuzz("command", tmp_path / "corpus", runs=2_000, max_s=20))


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.parametrize(("target", "runs"), [("codec", 2_000_000), ("command", 100_000)])
def test_fuzz_long(tmp_path: Path, target: str, runs: int) -> None:
    """The same properties, fuzzed long (the default suite's runs are a smoke test)."""
    check(fuzz(target, tmp_path / "corpus", runs=runs, max_s=180))


@pytest.mark.timeout(120)
def test_fuzz_harness_reports_a_failing_property(tmp_path: Path) -> None:
    r = fuzz("canary", tmp_path / "corpus", runs=100, max_s=20)
    assert r.returncode != 0
    assert "canary: a frame decoded" in r.stdout + r.stderr
