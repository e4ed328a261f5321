"""Coverage-guided fuzz targets (atheris / libFuzzer) for the frame decoder
and the command request path. Run as a program (``test_fuzz.py`` does, with
``-runs=N``)::

    python -m tests.faults.fuzz_targets codec   [--seed] [libFuzzer flags] [corpus dirs]
    python -m tests.faults.fuzz_targets command [--seed] [libFuzzer flags] [corpus dirs]

``--seed`` first writes the starting corpus (:func:`seeds`) into the last
corpus directory, in the same process (``seeds DIR`` alone only writes it):
each process pays for instrumenting zplatform, about 2 s.

Properties:

* ``codec``: ``decode_frame(data)`` and ``RegionCodec(dv, region).check(data)``
  (every region of the CN of configs/led_test.yaml) raise nothing but
  :class:`zplatform.errors.CodecError`; a frame that decodes re-encodes to a
  frame that decodes to the same header and data.
* ``command``: a sequence of ``gn_to_cn`` frames (some well-formed requests
  with chosen commands, sequence numbers, element indices and values, some
  raw region bytes, some arbitrary frames) is applied through
  ``RegionCodec(dv, "gn_to_cn")`` to a fresh CN Data Vector, and every frame
  is followed by ``CommandHandler.step(applied, t)`` and the state machine's
  step. The only exception allowed anywhere is CodecError from ``apply``;
  ``cn_cmd_status`` is always a valid status.

Any other exception propagates: atheris prints it and exits non-zero.
"""

from __future__ import annotations

import math
import struct
import sys
from pathlib import Path

import atheris

# The zplatform modules the targets run, for coverage guidance (found by
# profiling both targets on random and seeded inputs: the same coverage as
# instrumenting all of zplatform, 386 edges for `command`). Instrumenting
# every module zplatform's package imports (58) cost each fuzzing process
# about 2 s of CPU before its first run. atheris takes a package to include
# (a module name counts as its top-level package), so the rest are excluded.
FUZZED_MODULES = {
    "zplatform.core.codec",
    "zplatform.control.commands",
    "zplatform.config",
    "zplatform.core.datavector",
    "zplatform.core.events",
    "zplatform.control.params",
    "zplatform.control.statemachine",
    "zplatform.config.types",
}
_SRC = Path(__file__).resolve().parents[2] / "zplatform"
_NOT_FUZZED = sorted(
    ".".join(("zplatform", *p.relative_to(_SRC).with_suffix("").parts)).removesuffix(".__init__")
    for p in _SRC.rglob("*.py")
    if ".".join(("zplatform", *p.relative_to(_SRC).with_suffix("").parts)) not in FUZZED_MODULES
)

with atheris.instrument_imports(include=["zplatform"], exclude=_NOT_FUZZED):
    from zplatform.control.commands import CommandHandler, CommandStatus
    from zplatform.control.statemachine import StateMachine
    from zplatform.core.codec import RegionCodec, decode_frame, encode_frame
    from zplatform.core.datavector import DataVector, Layout
    from zplatform.core.events import EventLog
    from zplatform.errors import CodecError
    from zplatform.mission.load import load_mission

from tests.drive import step_request  # noqa: E402 (after the instrumented imports)

MISSION = load_mission(Path(__file__).resolve().parents[2] / "configs" / "led_test.yaml")
LAYOUT = Layout.for_node(MISSION, "cn")
REGIONS = list(LAYOUT.regions)
_DV = DataVector(LAYOUT)
_CODECS = [RegionCodec(_DV, r) for r in REGIONS]
GN = LAYOUT.region("gn_to_cn")
# gn_cmd u8, gn_cmd_seq u32, gn_cmd_element u16, gn_cmd_value f64 (packed LE)
_REQ = struct.Struct("<BQQHd")  # gn_cmd, gn_cmd_seq, gn_cmd_epoch, gn_cmd_element, gn_cmd_value
assert _REQ.size == GN.size, "gn_to_cn layout changed: update _REQ"
_SPECIAL = (math.nan, math.inf, -math.inf, 0.0, -0.0, 1.0, 255.0, 256.0, -1.0, 1e300, 0.5)


def seeds() -> list[bytes]:
    """Valid frames of every region (a starting corpus)."""
    out = []
    for c in _CODECS:
        out.append(bytes(c.encode(1, 2)))
    return out


@atheris.instrument_func
def codec_target(data: bytes) -> None:
    try:
        f = decode_frame(data)
    except CodecError:
        pass
    else:
        again = decode_frame(encode_frame(f.layout_id, f.seq, f.t_ns, f.data))
        assert (again.layout_id, again.seq, again.t_ns, bytes(again.data)) == (
            f.layout_id,
            f.seq,
            f.t_ns,
            bytes(f.data),
        )
    for c in _CODECS:
        try:
            c.check(data)
        except CodecError:
            pass


@atheris.instrument_func
def command_target(data: bytes) -> None:
    fdp = atheris.FuzzedDataProvider(data)
    dv = DataVector(LAYOUT)
    events = EventLog("cn", capacity=64)
    sm = StateMachine(MISSION, dv, events)
    ch = CommandHandler(MISSION, dv, events, sm)
    gn = RegionCodec(dv, "gn_to_cn")
    t = fdp.ConsumeIntInRange(0, 1 << 62)
    seq = 0
    for _ in range(fdp.ConsumeIntInRange(1, 12)):
        kind = fdp.ConsumeIntInRange(0, 3)
        if kind <= 1:  # a request as the ground would build it, or nearly
            cmd = fdp.ConsumeIntInRange(0, 9)
            seq = max(0, min(seq + fdp.ConsumeIntInRange(-2, 3), 2**64 - 1))
            epoch = 0 if fdp.ConsumeBool() else fdp.ConsumeIntInRange(0, 2**64 - 1)
            elem = fdp.ConsumeIntInRange(0, len(LAYOUT.elements) + 2)
            value = (
                _SPECIAL[fdp.ConsumeIntInRange(0, len(_SPECIAL) - 1)]
                if kind == 0
                else fdp.ConsumeRegularFloat()
            )
            frame = encode_frame(GN.layout_id, seq, t, _REQ.pack(cmd, seq, epoch, elem, value))
        elif kind == 2:  # raw region bytes
            frame = encode_frame(GN.layout_id, seq, t, fdp.ConsumeBytes(GN.size).ljust(GN.size))
        else:  # any bytes at all
            frame = fdp.ConsumeBytes(fdp.ConsumeIntInRange(0, 64))
        try:
            gn.apply(frame)
            applied = True
        except CodecError:
            applied = False
        rejects = int(dv.get("cn_cmd_rejects"))
        step_request(ch, dv, applied, t)
        sm.step(t)
        status = int(dv.get("cn_cmd_status"))
        assert 0 <= status < len(CommandStatus), status
        # Every applied request gets a verdict: a status, or a refusal that
        # consumes no number (replay, another run's epoch), counted.
        refused = int(dv.get("cn_cmd_rejects")) == rejects + 1
        assert not applied or status != CommandStatus.NONE or refused
        events.drain()
        t += fdp.ConsumeIntInRange(0, 20_000_000_000)


def canary_target(data: bytes) -> None:
    """Fails on a frame that decodes: proves a failing property is reported
    (test_fuzz.py seeds it with a valid frame)."""
    try:
        decode_frame(data)
    except CodecError:
        return
    raise RuntimeError("canary: a frame decoded")


def write_seeds(d: Path) -> None:
    """The starting corpus (:func:`seeds`) as files in ``d``."""
    d.mkdir(parents=True, exist_ok=True)
    for i, s in enumerate(seeds()):
        (d / f"seed{i}").write_bytes(s)


TARGETS = {"codec": codec_target, "command": command_target, "canary": canary_target}


def main() -> None:
    name = sys.argv.pop(1)
    if name == "seeds":  # write the starting corpus into the given directory
        write_seeds(Path(sys.argv[1]))
        return
    if sys.argv[1:2] == ["--seed"]:
        del sys.argv[1]
        write_seeds(Path(sys.argv[-1]))
    atheris.Setup(sys.argv, TARGETS[name])
    atheris.Fuzz()


if __name__ == "__main__":
    main()
