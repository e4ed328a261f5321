"""Cost of the region frame: encode, decode and apply into the Data Vector.

For each data size (64 B, 1 KB, 64 KB, 1 MB) three variants run side by side
in one process, on the same bytes:

* ``copy_<size>``: ``bytes(region_view)``, one plain copy of the region: the
  floor any frame has to pay at least once;
* ``zplatform_<size>``: ``RegionCodec.encode`` on the sender's Data Vector,
  then ``RegionCodec.apply`` of that frame on the receiver's (decode, checks,
  copy into the region): the whole per-region cost of the sync protocol
  outside zenoh;
* ``msgspec_<size>``: the baseline: msgspec's own ``Encoder.encode_into`` of
  the same 4-tuple ``(layout_id, seq, t_ns, region_view)`` into a reused
  ``bytearray``, ``Decoder`` into an array-like struct, then the same copy
  into the region.

What is measured: ``time.perf_counter_ns`` around each iteration (one sample
per iteration, its own seq), with the garbage collector disabled during the
timed loop, after a warm-up. The figures are in microseconds (``p50_us``,
``p99_us``, ...; ``bench.common.summarize``); ``vs_copy_p50`` is a variant's
p50 over the copy's p50 of the same size. The zplatform variant also reports
``encode_p50_us`` and ``apply_p50_us`` from separate timed loops. The timer's
own cost (about 0.05-0.1 us) is in ``params.timer_p50_ns`` and is not
subtracted.

Targets (reported, not asserted): 1 KB encode+decode within 3 us p50; at 1 MB
within 3x the plain copy.

Blocks for about 5 s (``--quick``: under 1 s). Run
``python -m bench.codec [--quick] [--json PATH]``; results go to
``bench/results/codec.json``.
"""

from __future__ import annotations

import gc
import os
import random
import time
from collections.abc import Callable
from typing import Any

import msgspec

from bench.common import bench_argparser, summarize, write_result
from zplatform import DataVector, Layout, RegionCodec, decode_mission

SIZES = {"64B": 64, "1KB": 1024, "64KB": 65536, "1MB": 1 << 20}
# Iterations per size (full run); --quick divides by 10.
ITERATIONS = {"64B": 100_000, "1KB": 100_000, "64KB": 20_000, "1MB": 2_000}
WARMUP_FRACTION = 10  # warm up with 1/10 of the iterations
TARGET_1KB_P50_US = 3.0
TARGET_1MB_VS_COPY = 3.0
REGION = "cn_to_dn0"
SEED = 20240601


class _Frame(msgspec.Struct, array_like=True, gc=False):
    layout_id: int
    seq: int
    t_ns: int
    data: memoryview


def _vectors(n: int) -> tuple[DataVector, DataVector]:
    """Sender (CN) and receiver (DN) Data Vectors whose cn_to_dn0 region is n bytes."""
    text = (
        "mission: bench\nnodes: {cn: {}, dn0: {}}\n"
        f"regions:\n  {REGION}:\n    - {{name: payload, type: 'u8[{n}]'}}\n"
    )
    m = decode_mission(text)
    tx = DataVector(Layout.for_node(m, "cn"))
    rx = DataVector(Layout.for_node(m, "dn0"))
    rng = random.Random(SEED)
    tx.write_region(REGION, rng.randbytes(n))
    return tx, rx


def _time(step: Callable[[int], object], iterations: int) -> list[int]:
    """Per-iteration ns of ``step(i)``; gc off while timing, warm-up first."""
    clock = time.perf_counter_ns
    for i in range(max(iterations // WARMUP_FRACTION, 10)):
        step(i)
    samples = [0] * iterations
    was_enabled = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        for i in range(iterations):
            t0 = clock()
            step(i)
            samples[i] = clock() - t0
    finally:
        if was_enabled:
            gc.enable()
    return samples


def _timer_overhead() -> int:
    clock = time.perf_counter_ns
    samples = []
    for _ in range(20_000):
        t0 = clock()
        samples.append(clock() - t0)
    samples.sort()
    return samples[len(samples) // 2]


def bench_size(label: str, n: int, iterations: int) -> dict[str, dict[str, Any]]:
    tx, rx = _vectors(n)
    view = tx.region_view(REGION)
    t_ns = 1_700_000_000_000_000_000
    out: dict[str, dict[str, Any]] = {}

    # the floor: one plain copy of the region
    def copy(i: int) -> object:
        return bytes(view)

    out[f"copy_{label}"] = summarize(_time(copy, iterations))

    # zplatform: encode on the sender, decode + check + apply on the receiver
    enc = RegionCodec(tx, REGION)
    dec = RegionCodec(rx, REGION)

    def full(i: int) -> object:
        return dec.apply(enc.encode(i, t_ns))

    zp = summarize(_time(full, iterations))
    frame = bytes(enc.encode(1, t_ns))
    zp["encode_p50_us"] = summarize(_time(lambda i: enc.encode(i, t_ns), iterations))["p50_us"]
    zp["apply_p50_us"] = summarize(_time(lambda i: dec.apply(frame), iterations))["p50_us"]
    zp["frame_bytes"] = len(frame)
    assert bytes(rx.region_view(REGION)) == bytes(view), "apply did not copy the region"
    out[f"zplatform_{label}"] = zp

    # msgspec baseline: encode_into a reused buffer, typed decode, same copy in
    m_enc = msgspec.msgpack.Encoder()
    m_dec = msgspec.msgpack.Decoder(_Frame)
    buf = bytearray()
    lid = enc.layout_id
    target = rx.region_view(REGION)

    def baseline(i: int) -> object:
        m_enc.encode_into((lid, i, t_ns, view), buf)
        f = m_dec.decode(buf)
        target[:] = f.data
        return f

    ms = summarize(_time(baseline, iterations))
    ms["frame_bytes"] = len(buf)
    out[f"msgspec_{label}"] = ms

    copy_p50 = out[f"copy_{label}"]["p50_us"]
    for fig in out.values():
        fig["size_bytes"] = n
        fig["vs_copy_p50"] = round(fig["p50_us"] / copy_p50, 2) if copy_p50 else None
    return out


def main(argv: list[str] | None = None) -> int:
    args = bench_argparser(__doc__.splitlines()[0] if __doc__ else "codec").parse_args(argv)
    scale = 10 if args.quick else 1
    iterations = {k: max(v // scale, 100) for k, v in ITERATIONS.items()}
    variants: dict[str, dict[str, Any]] = {}
    for label, n in SIZES.items():
        variants.update(bench_size(label, n, iterations[label]))

    zp_1k = variants["zplatform_1KB"]
    zp_1k["target_p50_us"] = TARGET_1KB_P50_US
    zp_1k["target_met"] = zp_1k["p50_us"] <= TARGET_1KB_P50_US
    zp_1m = variants["zplatform_1MB"]
    zp_1m["target_vs_copy"] = TARGET_1MB_VS_COPY
    zp_1m["target_met"] = (zp_1m["vs_copy_p50"] or 0.0) <= TARGET_1MB_VS_COPY

    params = {
        "sizes_bytes": SIZES,
        "iterations": iterations,
        "quick": args.quick,
        "region": REGION,
        "seed": SEED,
        "timer_p50_ns": _timer_overhead(),
        "pid": os.getpid(),
        "gc_disabled_while_timing": True,
    }
    write_result("codec", params, variants, args.json)

    print(
        f"\n{'size':>6}  {'copy p50':>9}  {'zplatform p50':>13}  {'x copy':>6}  "
        f"{'msgspec p50':>11}  {'x copy':>6}  {'enc p50':>8}  {'apply p50':>9}"
    )
    for label in SIZES:
        c, z, m = (variants[f"{k}_{label}"] for k in ("copy", "zplatform", "msgspec"))
        print(
            f"{label:>6}  {c['p50_us']:>9.2f}  {z['p50_us']:>13.2f}  {z['vs_copy_p50']:>6.2f}  "
            f"{m['p50_us']:>11.2f}  {m['vs_copy_p50']:>6.2f}  {z['encode_p50_us']:>8.2f}  "
            f"{z['apply_p50_us']:>9.2f}"
        )
    print(
        f"\ntarget 1 KB encode+decode p50 <= {TARGET_1KB_P50_US} us: "
        f"{'met' if zp_1k['target_met'] else 'NOT met'} ({zp_1k['p50_us']} us)"
    )
    print(
        f"target 1 MB within {TARGET_1MB_VS_COPY}x the plain copy: "
        f"{'met' if zp_1m['target_met'] else 'NOT met'} ({zp_1m['vs_copy_p50']}x)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
