"""bench.frame_trace's reduction: hops between consecutive stamps of one
exchange, a step the code no longer has merged into the next hop, spans on
their own, copies per hop and per exchange."""

from __future__ import annotations

from typing import Any

from bench.frame_trace import (
    CN_MARKS,
    COPIES,
    DN_MARKS,
    DN_SPANS,
    SPANS,
    _CnStamps,
    _DnStamps,
    hop_table,
)


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


class _Logic:
    loop = 7


def _ticks() -> Any:
    return iter(range(1_000, 10**6, 1_000)).__next__


def test_the_cn_tracer_puts_each_point_in_its_column() -> None:
    st = _CnStamps(1)
    st.logic = _Logic()
    st.mono = _ticks()
    for name, v in [
        ("cn.encode", 0),
        ("cn.encoded", 0),
        ("cn.sealed", 0),
        ("sync.issued", 300),
        ("sync.sent", 0),
        ("sync.back", 200),
        ("sync.queued", 0),
        ("sync.taken", 0),
        ("cn.opened", 0),
        ("cn.decoded", 0),
        ("cn.applied", 0),
    ]:
        st.mark(name, 0, v)
    for name in ("tm.encode", "tm.encoded", "tm.sealed", "tm.put", "tm.sent"):
        st.mark(name, 7)
    # issued at the 4th tick, then one a tick in CN_MARKS order
    assert st.chain[7, 0].tolist() == [4_000 + 1_000 * k for k in range(len(CN_MARKS))]
    assert st.spans[7, 0].tolist() == [1_000] * len(SPANS)  # each span one tick
    assert (st.query_len, st.reply_len) == ([300], [200])


def test_the_dn_tracer_keeps_a_served_query_with_its_own_intake_only() -> None:
    st = _DnStamps()
    st.mono = _ticks()
    served = ["dn.serve", "dn.opened", "dn.decoded", "dn.encoded", "dn.sealed"]
    for name in ["dn.arrive", "dn.admitted", *served]:
        st.mark(name)
    st.mark("dn.replied", 5)
    st.mark("dn.apply")
    st.mark("dn.applied")
    row = dict(zip((*DN_MARKS, *DN_SPANS), st.rows[5].tolist(), strict=True))
    assert row["arrive"] == 1_000 and row["admitted"] == 2_000
    assert row["copied"] == row["verified"] == row["applied"] == 0  # no point of theirs
    assert [row[m] for m in ("serve", "opened", "decoded", "encoded", "sealed")] == [
        3_000,
        4_000,
        5_000,
        6_000,
        7_000,
    ]
    assert row["replied"] == 8_000 and row["dn.apply"] == 1_000
    # Two queries admitted before one serve (a backlog): neither row is kept.
    for name in ["dn.arrive", "dn.admitted", "dn.arrive", "dn.admitted", *served]:
        st.mark(name)
    st.mark("dn.replied", 6)
    st.mark("dn.serve")
    st.mark("dn.replied", 7)
    assert not st.rows[6].any() and not st.rows[7].any()
