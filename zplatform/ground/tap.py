"""``zplatform tap``: any sample of a mission's key space, decoded to named values.

:class:`TapDecoder` turns a sample into a dict: a region frame or telemetry
into its elements (checked with the mission key when it is at hand, else
decoded and marked ``"verified": false``), an event into its
:class:`~zplatform.telemetry.records.EventRecord`, a bulk sample into its header and a summary
of its array, anything else into its first bytes. :func:`run_tap` prints
samples through a :class:`~.link.GroundLink` until a count, a timeout or
Ctrl-C; when nothing came it says whether the mission is running at all
(liveliness), so a quiet key is not mistaken for a dead vehicle.
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any, TextIO

import msgspec
import zenoh

from ..config import Mission
from ..core.auth import TAG_LEN, Channel, KeyError_, link_of, load_keys
from ..core.codec import RegionCodec
from ..core.datavector import DataVector, Layout
from ..core.events import EventReader
from ..errors import CodecError, CommandError, TransportError
from ..runtime.bulk import bulk_key, decode_sample, tags_bytes
from ..runtime.transport import KeySpace
from ..telemetry.logs import f32_value
from ..telemetry.records import EventRecord

__all__ = ["TAP_SILENCE_S", "TapDecoder", "check_keyexpr", "format_tap", "run_tap", "tap_keys"]

TAP_SILENCE_S = 5.0
"""``tap`` without ``--timeout`` gives up when nothing at all arrived this long."""


class TapDecoder:
    """Decodes any sample of the key space into named values (module doc).

    Frames and events of an authenticating mission are checked with the
    keys a read-only tool holds (the downlink's and every node's event
    keys: ``tool.keys``) when they are at hand; what they do not cover
    (the triggers and replies of the cn<->dnX links, command requests) and
    everything without them is still decoded, marked ``"verified": false``."""

    def __init__(self, mission: Mission) -> None:
        self.mission = mission
        space = KeySpace(mission.vehicle)
        self._auth = mission.security.auth
        try:
            keys = load_keys(mission, "tool")
        except KeyError_:
            keys = None

        def chan(name: str) -> Channel | None:
            return keys.channel(name) if keys is not None and keys.has(link_of(name)) else None

        self._events = EventReader(mission, keys)
        self._by_key: dict[str, Any] = {}
        # A bulk sample carries a tag per reader, each on a link only the
        # owner and that reader hold (no tool: a tool key can forge none),
        # so a tap shows it unverified, as a sync frame it cannot check.
        self._bulk = {bulk_key(mission.vehicle, c): c for c in mission.bulk}
        cn = DataVector(Layout.for_node(mission, "cn"))
        self._by_key[space.telemetry] = (RegionCodec(cn), cn, chan("telemetry"))
        for region in mission.region_names():
            if region == "cn":
                continue
            dv = DataVector(Layout.for_regions(mission, [region]))
            self._by_key[space.region(region)] = (RegionCodec(dv, region), dv, chan(region))

    def decode(self, key: str, payload: bytes, rx_ns: int = 0) -> dict[str, Any]:
        """``{"key": key, ...}``: the sample's values, its event, or an ``error``."""
        if key.endswith("/events"):
            try:
                e, verified = self._events.read(key, payload)
            except CodecError as exc:
                return {"key": key, "error": str(exc)}
            return {"key": key, "event": msgspec.to_builtins(EventRecord.of(e, rx_ns, verified))}
        bulk = self._bulk.get(key)
        if bulk is not None:
            ch = bulk
            try:
                hdr, arr = decode_sample(payload, ch, tagged=self._auth)
            except (TransportError, CodecError) as exc:
                return {"key": key, "error": str(exc)}
            return {
                "key": key,
                "seq": hdr.seq,
                "loop": hdr.loop,
                "t_ns": hdr.t_ns,
                **({"verified": False} if self._auth else {}),
                "bulk": {
                    "channel": ch.name,
                    "bytes": len(payload) - tags_bytes(ch, self._auth),  # its tags aside
                    "min": float(arr.min()),
                    "max": float(arr.max()),
                    "mean": float(arr.mean()),
                },
            }
        entry = self._by_key.get(key)
        if entry is None:
            return {"key": key, "bytes": len(payload), "hex": payload[:64].hex()}
        codec, dv, channel = entry
        verified = None
        try:
            body: bytes | memoryview = payload
            if channel is not None:
                body, verified = channel.open(payload), True
            elif self._auth:
                body, verified = payload[:-TAG_LEN], False
            frame = codec.apply(body)
        except CodecError as exc:
            return {"key": key, "error": str(exc)}
        values: dict[str, Any] = {}
        for name, spec in dv.layout.elements.items():
            if spec.enum is not None:
                values[name] = dv.get_name(name)
                continue
            v = dv.get(name).tolist() if spec.count else dv.get(name)
            if spec.scalar.kind == "float" and spec.scalar.size == 4:
                # An f32 shown at its own precision, not the double's noise.
                v = [f32_value(x) for x in v] if spec.count else f32_value(v)
            values[name] = v
        out: dict[str, Any] = {"key": key, "seq": frame.seq, "t_ns": frame.t_ns}
        if verified is not None:
            out["verified"] = verified
        out["values"] = values
        return out


def check_keyexpr(keyexpr: str) -> None:
    """CommandError for a key expression zenoh refuses, with zenoh's reason."""
    try:
        zenoh.KeyExpr(keyexpr)
    except zenoh.ZError as exc:
        reason = str(exc).split(" at /", 1)[0]  # drop the Rust source location
        raise CommandError(
            f"{keyexpr!r} is not a zenoh key expression ({reason}); e.g. 'rocket/**', "
            "'rocket/dn0/*', 'rocket/*/events'"
        ) from None


def tap_keys(mission: Mission, keyexpr: str | None) -> list[str]:
    """The key expressions ``tap`` subscribes to for ``keyexpr`` (None: all
    it may). Without access control: ``keyexpr`` or the whole key space.
    Under the deployment's access control a tool may subscribe only to
    :func:`~zplatform.security.deploy.tool_watch_keys` (the nodes drop any other
    subscriber where it comes in, silently): None gives each of those, and a
    ``keyexpr`` none of them includes is a CommandError naming them, not a
    tap that stays silent. Reads the deployment (DeploymentError as
    :func:`~zplatform.security.deploy.require_deployment`)."""
    from ..security.deploy import require_deployment, tls_nodes, tool_watch_keys

    dep = require_deployment(mission)
    if dep is None or not dep.access_control or not tls_nodes(mission):
        return [keyexpr or KeySpace(mission.vehicle).everything]
    allowed = tool_watch_keys(mission)
    if keyexpr is None:
        return allowed
    check_keyexpr(keyexpr)
    k = zenoh.KeyExpr(keyexpr)
    if any(zenoh.KeyExpr(a).includes(k) for a in allowed):
        return [keyexpr]
    raise CommandError(
        f"{keyexpr!r}: the mission's access control lets a tool subscribe only to "
        f"{', '.join(allowed)} (or keys within them); tap one of those, or leave the key out"
    )


def format_tap(d: dict[str, Any], as_json: bool) -> str:
    """One printed line for a decoded sample."""
    key = d["key"]
    if as_json:
        return json.dumps(d, default=str)
    if "values" in d:
        vals = " ".join(f"{k}={v}" for k, v in d["values"].items())
        mark = " (unverified)" if d.get("verified") is False else ""
        return f"{key} seq={d['seq']} t_ns={d['t_ns']} via={d.get('via')} {vals}{mark}"
    if "event" in d:
        e = d["event"]
        mark = " (unverified)" if e.get("verified") is False else ""
        return (
            f"{key} EVENT {e['severity']:<8} {e['id']}: {e['text']}{mark}  "
            f"(seq={e['seq']} t_ns={e['t_ns']})"
        )
    return f"{key} {json.dumps({k: v for k, v in d.items() if k != 'key'})}"


def run_tap(
    mission: Mission,
    keyexpr: str | None,
    *,
    count: int | None = None,
    timeout_s: float | None = None,
    as_json: bool = False,
    out: TextIO = sys.stdout,
    silence_s: float = TAP_SILENCE_S,
) -> tuple[int, str | None]:
    """Print samples on ``keyexpr`` (default: the whole key space, or under
    access control every key a tool may watch, :func:`tap_keys`) until
    ``count`` samples, ``timeout_s`` or Ctrl-C. Blocks.

    Returns ``(samples printed, why none came)``: with none, the second
    says whether the mission is running (its nodes' liveliness) or not. With
    no bound at all, ``silence_s`` of silence ends the tap: a typo in the key
    or a mission that is not running must not look like a quiet vehicle.
    CommandError for a bad key expression.
    """
    from .link import GroundLink

    if keyexpr is not None:
        check_keyexpr(keyexpr)
    watched = tap_keys(mission, keyexpr)
    keyexpr = ", ".join(watched)
    dec = TapDecoder(mission)
    link = GroundLink(mission, keys=None, telemetry=False, events=False)
    for k in watched:
        link.tap(k)
    via: dict[str, list[int]] = {}  # per key: [through shared memory, copied]
    n = 0
    start = time.monotonic()
    deadline = start + timeout_s if timeout_s else None
    silence = timeout_s or silence_s
    try:
        while count is None or n < count:
            now = time.monotonic()
            if n == 0 and now - start >= silence:
                break
            left = 0.5 if deadline is None else min(deadline - now, 0.5)
            if left <= 0:
                break
            got = link.next_tap(left)
            if got is None:
                continue
            key, payload, shm = got
            n += 1
            counts = via.setdefault(key, [0, 0])
            counts[0 if shm else 1] += 1
            d = dec.decode(key, payload, link.clock.now_ns())
            d["via"] = "shm" if shm else "copied"
            d["shm_copied"] = counts
            print(format_tap(d, as_json), file=out, flush=True)
        why = None
        if n == 0:
            alive = link.alive_nodes()
            if alive:
                why = (
                    f"the mission is running (nodes alive: {', '.join(alive)}) but nothing was "
                    f"published on {keyexpr} within {silence:g} s"
                )
            else:
                why = (
                    f"no sample on {keyexpr} within {silence:g} s, and no node of mission "
                    f"{mission.mission!r} is alive (is it running? `zplatform ps`)"
                )
    except KeyboardInterrupt:
        why = None if n else f"interrupted before any sample arrived on {keyexpr}"
    finally:
        link.close()
    return n, why
