"""Drive the sans-IO loop from a test the way a driver does."""

from __future__ import annotations

from zplatform import DataVector, Layout, RegionCodec
from zplatform.loop import DeviceLogic


def run_dn_loop(
    logic: DeviceLogic, loop: int, t_ns: int, cn: DataVector | None = None
) -> None:
    """One DN loop: the CN's trigger frame for ``loop`` at ``t_ns`` (its
    ``cn_to_dnX`` region from ``cn``, a CN-layout vector; initial values if
    None), then the run."""
    if cn is None:
        cn = DataVector(Layout.for_node(logic.mission, "cn"))
    reply = logic.step(RegionCodec(cn, f"cn_to_{logic.node}").encode(loop, t_ns), t_ns)
    assert reply is not None and logic.triggered == loop, logic.reject_reason
