"""bench.frame_trace's reduction: hops between consecutive stamps of one
exchange, a step the code no longer has merged into the next hop, spans on
their own, copies per hop and per exchange."""

from __future__ import annotations

from typing import Any

from bench.frame_trace import CN_MARKS, COPIES, DN_MARKS, DN_SPANS, SPANS, _Spy, hop_table


def _rows(skip: set[str]) -> tuple[list[int], list[int]]:
    """One exchange 10 us a stamp apart, but for the marks in ``skip``."""
    t = 1_000_000
    cn: list[int] = []
    dn: list[int] = []
    for name in [*(f"cn.{m}" for m in CN_MARKS[:2]), *(f"dn.{m}" for m in DN_MARKS)]:
        t += 10_000
        (cn if name.startswith("cn.") else dn).append(0 if name in skip else t)
    for m in CN_MARKS[2:]:
        t += 10_000
        cn.append(0 if f"cn.{m}" in skip else t)
    return cn, dn


def test_every_hop_and_the_exchange() -> None:
    cn, dn = _rows(set())
    spans = [[5_000 * (k + 1) for k in range(len(SPANS))]]
    out = hop_table({7: [cn]}, {7: spans}, [{7: [*dn, 3_000]}])
    assert out["cn.issued->cn.sent"]["p50_us"] == 10.0
    assert out["dn.sealed->dn.replied"]["copies"] == COPIES["dn.replied"][0]
    n_chain = 2 + len(DN_MARKS) + len(CN_MARKS) - 2
    assert out["exchange"]["p50_us"] == 10.0 * (n_chain - 1)
    assert out["tm.put"]["p50_us"] == 5.0 * (SPANS.index("tm.put") + 1)
    assert out[DN_SPANS[0]]["p50_us"] == 3.0
    hops = [k for k in out if "->" in k]
    assert len(hops) == n_chain - 1
    assert out["exchange"]["copies"] == sum(
        out[k]["copies"] for k in [*hops, "cn.encode", "cn.seal", *DN_SPANS]
    )


def test_a_step_not_stamped_merges_into_the_next_hop() -> None:
    cn, dn = _rows({"dn.applied"})
    out = hop_table({3: [cn]}, {3: [[0] * len(SPANS)]}, [{3: dn}])
    assert "dn.decoded->dn.applied" not in out
    assert out["dn.decoded->dn.encoded"]["p50_us"] == 20.0
    assert "cn.encode" not in out  # a span never stamped is no hop


def test_an_exchange_the_dn_did_not_stamp_is_left_out() -> None:
    cn, _ = _rows(set())
    assert hop_table({3: [cn]}, {}, [{}]) == {}


def test_a_spy_stamps_around_the_named_method_and_passes_the_rest() -> None:
    calls: list[str] = []

    class Target:
        __slots__ = ("x",)

        def __init__(self) -> None:
            self.x = 5

        def work(self, a: int) -> int:
            calls.append("work")
            return a + self.x

    spy: Any = _Spy(Target(), {"work": (lambda: calls.append("pre"), lambda: calls.append("post"))})
    assert spy.work(2) == 7 and spy.x == 5
    assert calls == ["pre", "work", "post"]
