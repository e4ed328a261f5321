"""The Data Vector: one typed byte buffer of named elements (thesis 4.1).

A :class:`Layout` is computed once from the mission for one node: every
element's offset and size, every region's offset, size and ``layout_id``. A
:class:`DataVector` owns one ``bytearray`` of that size and a little-endian
numpy structured view over it (no copy: the view *is* the buffer).
Endianness is fixed little-endian on every host (thesis 4.3.4, solved).

Access paths, fastest first:

* :meth:`DataVector.handle` returns a :class:`Handle` bound to one element's
  offset and ``struct`` format; ``handle.get()`` / ``handle.set(v)`` are the
  hot path (no dict lookup, no allocation for scalars).
* :meth:`DataVector.get` / :meth:`DataVector.set` by name, with full range
  and enum checks on ``set`` (for commands and actions: slower, safe).
* Regions are copied out into a caller's preallocated buffer
  (:meth:`read_region`) and in from bytes (:meth:`write_region`); a size
  mismatch raises instead of truncating; :meth:`region_view` is a zero-copy
  ``memoryview`` for encoders. See docs/architecture.md#data-vector.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ..config.types import ScalarType
from ..errors import DataVectorError

if TYPE_CHECKING:
    from ..config import ElementConfig, Mission

__all__ = ["DataVector", "ElementSpec", "Handle", "Layout", "RegionSpec"]

LAYOUT_MAGIC = "zplatform-region-v1"
VECTOR_MAGIC = "zplatform-vector-v1"


@dataclass(frozen=True, slots=True)
class ElementSpec:
    """Where one element lives and what it holds.

    ``count`` is 0 for a scalar, the array length otherwise; ``offset`` is
    from the start of the node's buffer; ``index`` is the element's position
    in the CN's full element list (used by WRITE commands).
    """

    name: str
    region: str
    scalar: ScalarType
    count: int
    offset: int
    size: int
    enum: tuple[str, ...] | None
    initial: Any
    index: int

    @property
    def type_text(self) -> str:
        """The canonical type text used in ``layout_id`` (``f32[3]``, ``enum(u8:A,B)``)."""
        if self.enum is not None:
            return f"enum({self.scalar.name}:{','.join(self.enum)})"
        return f"{self.scalar.name}[{self.count}]" if self.count else self.scalar.name

    def name_of(self, value: int) -> str:
        """An enum value's name (``str(value)`` when out of range or not an enum)."""
        if self.enum is not None and 0 <= value < len(self.enum):
            return self.enum[value]
        return str(value)


@dataclass(frozen=True, slots=True)
class RegionSpec:
    """A contiguous run of elements, the unit of synchronisation."""

    name: str
    offset: int
    size: int
    elements: tuple[ElementSpec, ...]
    layout_id: int


def _region_descriptor(name: str, elements: Iterable[ElementSpec]) -> str:
    return ";".join([LAYOUT_MAGIC, name, *(f"{e.name}:{e.type_text}" for e in elements)])


def layout_id_of(name: str, elements: Iterable[ElementSpec]) -> int:
    """The stable u32 ``layout_id`` of a region: CRC-32 of its descriptor.

    The descriptor is ``zplatform-region-v1;<region>;<name>:<type>;...``
    (``codecs/FORMAT.md``); a peer with other names, types or order gets
    another id and its frames are refused, not misread.
    """
    return zlib.crc32(_region_descriptor(name, elements).encode()) & 0xFFFFFFFF


class Layout:
    """Offsets and sizes of one node's Data Vector, computed once.

    Build with :meth:`for_node` (a node's own regions) or :meth:`for_regions`.
    Immutable after construction; safe to share between Data Vectors.
    """

    def __init__(self, regions: list[tuple[str, list[ElementConfig]]], all_names: list[str]):
        from ..config import element_spec

        index = {n: i for i, n in enumerate(all_names)}
        offset = 0
        self.regions: dict[str, RegionSpec] = {}
        self.elements: dict[str, ElementSpec] = {}
        for rname, configs in regions:
            start = offset
            specs: list[ElementSpec] = []
            for ec in configs:
                scalar, count = element_spec(ec)
                size = scalar.size * max(count, 1)
                spec = ElementSpec(
                    name=ec.name,
                    region=rname,
                    scalar=scalar,
                    count=count,
                    offset=offset,
                    size=size,
                    enum=tuple(ec.enum) if ec.enum is not None else None,
                    initial=ec.initial,
                    index=index[ec.name],
                )
                specs.append(spec)
                self.elements[ec.name] = spec
                offset += size
            self.regions[rname] = RegionSpec(
                rname, start, offset - start, tuple(specs), layout_id_of(rname, specs)
            )
        self.size = offset
        self.layout_id = (
            zlib.crc32(
                "\n".join(
                    [VECTOR_MAGIC]
                    + [_region_descriptor(r.name, r.elements) for r in self.regions.values()]
                ).encode()
            )
            & 0xFFFFFFFF
        )
        names, formats, offsets = [], [], []
        for e in self.elements.values():
            names.append(e.name)
            formats.append((e.scalar.numpy, (e.count,)) if e.count else e.scalar.numpy)
            offsets.append(e.offset)
        self.dtype = np.dtype(
            {"names": names, "formats": formats, "offsets": offsets, "itemsize": max(self.size, 1)}
        )

    @classmethod
    def for_node(cls, mission: Mission, node: str) -> Layout:
        """The layout of ``node``'s Data Vector (CN: every region)."""
        return cls.for_regions(mission, mission.node_regions(node))

    @classmethod
    def for_regions(cls, mission: Mission, regions: list[str]) -> Layout:
        all_names = [e.name for r in mission.region_names() for e in mission.regions[r]]
        return cls([(r, mission.regions[r]) for r in regions], all_names)

    def element(self, name: str) -> ElementSpec:
        """The spec of ``name``; raises DataVectorError naming close matches."""
        try:
            return self.elements[name]
        except KeyError:
            raise DataVectorError(f"no element named {name!r} in this Data Vector") from None

    def region(self, name: str) -> RegionSpec:
        try:
            return self.regions[name]
        except KeyError:
            raise DataVectorError(
                f"no region named {name!r}; regions: {list(self.regions)}"
            ) from None


class Handle:
    """Fast access to one element, bound at start-up.

    ``get()`` returns a Python scalar (``int``/``float``/``bool``) for scalar
    elements and a writable numpy view (no copy) for arrays. ``set(v)`` writes
    without range checks beyond what ``struct`` enforces (ints that do not fit
    raise :class:`DataVectorError`, and the element then reads 0: ``struct``
    clears the bytes before it converts); use :meth:`DataVector.set` for
    checked writes of untrusted values, which leaves the vector unchanged.
    ``bump(n)`` adds to a scalar integer counter and saturates at the type's
    maximum (a u32 error counter sticks at 4294967295, it never wraps to 0).
    """

    __slots__ = ("_buf", "_fmt", "_max", "_off", "_view", "spec")

    def __init__(self, dv: DataVector, spec: ElementSpec):
        self.spec = spec
        self._buf = dv.buf
        self._off = spec.offset
        self._fmt = struct.Struct("<" + spec.scalar.struct)
        self._view: np.ndarray | None = dv.array[spec.name][0] if spec.count else None
        # Only scalar integer elements (enums included) can be counters.
        self._max: int | None = (
            spec.scalar.hi if spec.scalar.kind == "int" and not spec.count else None
        )

    def get(self) -> Any:
        if self._view is not None:
            return self._view
        return self._fmt.unpack_from(self._buf, self._off)[0]

    def set(self, value: Any) -> None:
        if self._view is not None:
            self._view[:] = value
            return
        try:
            self._fmt.pack_into(self._buf, self._off, value)
        except (struct.error, OverflowError, TypeError) as exc:
            raise DataVectorError(
                f"cannot store {value!r} in {self.spec.name} ({self.spec.type_text}): {exc}"
            ) from exc

    def bump(self, n: int = 1) -> int:
        """Add ``n`` (>= 0) to a counter, saturating at the type's maximum; return the new value.

        For scalar integer elements only (DataVectorError otherwise, raised
        before anything is written). Saturation, not wrap-around: a counter
        that reads its maximum means "at least that many". Costs what
        ``set(get() + n)`` costs: one unpack, one add, one pack.
        """
        hi = self._max
        if hi is None:
            raise DataVectorError(
                f"bump() needs a scalar integer element; {self.spec.name} is {self.spec.type_text}"
            )
        v = self._fmt.unpack_from(self._buf, self._off)[0] + n
        if v > hi:
            v = hi
        self._fmt.pack_into(self._buf, self._off, v)
        return int(v)


class DataVector:
    """One node's data: a ``bytearray`` and a structured numpy view over it.

    Not thread-safe: one loop thread owns it (thesis 3.3.2, single-threaded
    loops). Copies in and out are explicit; nothing here allocates per call
    except :meth:`get`/:meth:`set` by name (dict lookups) and array values.
    """

    def __init__(self, layout: Layout):
        self.layout = layout
        self.buf = bytearray(max(layout.size, 1))
        self._mv = memoryview(self.buf)
        # The structured view shares memory with buf: writes through either
        # are seen by both; no copy is ever made here.
        self.array: np.ndarray = np.frombuffer(self.buf, dtype=layout.dtype, count=1)
        self._handles: dict[str, Handle] = {}
        self.reset()

    # -- whole vector ------------------------------------------------------
    @property
    def size(self) -> int:
        return self.layout.size

    def reset(self) -> None:
        """Write every element's initial value."""
        for spec in self.layout.elements.values():
            h = self.handle(spec.name)
            h.set(spec.initial)

    def read_all(self, out: bytearray | memoryview) -> None:
        """Copy the whole vector into ``out``, which must be exactly ``size`` bytes."""
        if len(out) != self.layout.size:
            raise DataVectorError(
                f"copy buffer is {len(out)} bytes; the Data Vector is {self.layout.size}"
            )
        out[:] = self._mv[: self.layout.size]

    def write_all(self, data: bytes | bytearray | memoryview) -> None:
        """Replace the whole vector with ``data`` (exactly ``size`` bytes)."""
        if len(data) != self.layout.size:
            raise DataVectorError(
                f"data is {len(data)} bytes; the Data Vector is {self.layout.size}"
            )
        self._mv[: self.layout.size] = data

    def view(self) -> memoryview:
        """Zero-copy view of the whole vector (valid as long as this object)."""
        return self._mv[: self.layout.size]

    # -- regions -----------------------------------------------------------
    def region_view(self, name: str) -> memoryview:
        """Zero-copy view of region ``name``; writes through it change the vector."""
        r = self.layout.region(name)
        return self._mv[r.offset : r.offset + r.size]

    def read_region(self, name: str, out: bytearray | memoryview) -> None:
        """Copy region ``name`` into ``out`` (exactly the region's size)."""
        r = self.layout.region(name)
        if len(out) != r.size:
            raise DataVectorError(f"copy buffer is {len(out)} bytes; region {name} is {r.size}")
        out[:] = self._mv[r.offset : r.offset + r.size]

    def write_region(self, name: str, data: bytes | bytearray | memoryview) -> None:
        """Copy ``data`` into region ``name``; refuses a size mismatch."""
        r = self.layout.region(name)
        if len(data) != r.size:
            raise DataVectorError(f"data is {len(data)} bytes; region {name} is {r.size}")
        self._mv[r.offset : r.offset + r.size] = data

    # -- elements ----------------------------------------------------------
    def handle(self, name: str) -> Handle:
        """A :class:`Handle` for ``name`` (cached; build handles at start-up)."""
        h = self._handles.get(name)
        if h is None:
            h = Handle(self, self.layout.element(name))
            self._handles[name] = h
        return h

    def get(self, name: str) -> Any:
        """Value of ``name`` (enums as their integer; arrays as a numpy view)."""
        return self.handle(name).get()

    def get_name(self, name: str) -> str:
        """An enum element's current value as its name."""
        h = self.handle(name)
        return h.spec.name_of(h.get())

    def set(self, name: str, value: Any) -> None:
        """Checked write: enum names accepted, ranges enforced.

        Raises :class:`DataVectorError` when the value does not fit the
        element's type; the vector is unchanged then.
        """
        h = self.handle(name)
        h.set(self.coerce(h.spec, value))

    @staticmethod
    def coerce(spec: ElementSpec, value: Any) -> Any:
        """Check ``value`` against ``spec`` and convert it to what is stored."""
        st = spec.scalar
        if spec.count:
            # dtype=object keeps Python ints exact: a plain asarray makes
            # [0, 2**64 - 1] a float64 array, and its check would then fail.
            arr = value if isinstance(value, np.ndarray) else np.asarray(value, dtype=object)
            if arr.shape not in ((), (spec.count,)):
                raise DataVectorError(
                    f"{spec.name} holds {spec.count} values, got shape {arr.shape}"
                )
            items = arr.reshape(-1).tolist()
            for x in items:
                if isinstance(x, np.generic):  # numpy scalars inside a list
                    x = x.item()
                if not st.fits(x):
                    raise DataVectorError(f"{x!r} does not fit {spec.name} ({spec.type_text})")
            return value
        if spec.enum is not None:
            if isinstance(value, str):
                if value not in spec.enum:
                    raise DataVectorError(
                        f"{value!r} is not one of {spec.name}'s names {list(spec.enum)}"
                    )
                return spec.enum.index(value)
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            if isinstance(value, bool) or not isinstance(value, int | np.integer):
                raise DataVectorError(f"{spec.name} is an enum; got {value!r}")
            if not 0 <= int(value) < len(spec.enum):
                raise DataVectorError(
                    f"{value!r} is out of range for {spec.name} (0..{len(spec.enum) - 1})"
                )
            return int(value)
        if isinstance(value, np.generic):
            value = value.item()
        if not st.fits(value):
            rng = f" (range {st.lo}..{st.hi})" if st.kind == "int" else ""
            raise DataVectorError(f"{value!r} does not fit {spec.name} ({st.name}){rng}")
        if st.kind == "int":
            return int(value)
        if st.kind == "bool":
            return bool(value)
        return float(value)

    def values(self) -> dict[str, Any]:
        """A snapshot of every element as Python values (arrays as lists).

        Allocates: for tools and tests, not for the loop.
        """
        out: dict[str, Any] = {}
        for name, spec in self.layout.elements.items():
            v = self.handle(name).get()
            out[name] = v.tolist() if spec.count else v
        return out
