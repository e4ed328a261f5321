"""The mission file's JSON Schema and its reference, from the typed config.

One source: the ``msgspec.Struct`` tree of :mod:`zplatform.config` (and the
``Config`` structs of the built-in boards and devices) carries every key's
type, default, bounds and description (a struct's docstring describes its
section). :func:`mission_schema` turns it into a JSON Schema (draft 2020-12)
for editors and validators (a board mapping checked against its driver's
config, a built-in device's ``config`` against its class's);
:func:`reference_markdown` into ``docs/mission-reference.md`` (every key with
its YAML path in the form errors use, the platform elements, the built-ins).

Contract: both functions are pure (no I/O) and deterministic, and raise
nothing for the shipped structs; ``zplatform schema [--markdown] [--out
FILE]`` prints or writes either, and ``tests/unit/test_schema.py`` fails when
the committed reference differs. The schema is a guide, not the judge:
``zplatform check`` runs every rule, and the schema never refuses a file
``check`` accepts.

See docs/mission-reference.md#completion-in-your-editor.
"""

from __future__ import annotations

import inspect
import json
import re
from typing import Any

import msgspec

from ..boards import GpiodBoardConfig, SerialBoardConfig, SimBoardConfig
from ..config import (
    CONTROLLER_MODES,
    BulkChannelConfig,
    ComponentConfig,
    ElementConfig,
    HazardousOutputConfig,
    HealthConfig,
    Mission,
    NodeConfig,
    ParamConfig,
    RecorderConfig,
)
from ..config import platform_elements as _platform_elements
from ..control import devices as _devices
from ..control.devices import Actuator, Sensor

__all__ = [
    "BOARD_CONFIGS",
    "REFERENCE_PATH",
    "builtin_devices",
    "mission_schema",
    "mission_schema_json",
    "reference_markdown",
]

JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"

REFERENCE_PATH = "docs/mission-reference.md"
"""Where the reference lives in the repository (relative to its root)."""

REGENERATE = f"zplatform schema --markdown --out {REFERENCE_PATH}"
"""The one command that rewrites the reference (run from the repository root)."""

BOARD_CONFIGS: dict[str, type[msgspec.Struct]] = {
    "sim": SimBoardConfig,
    "serial": SerialBoardConfig,
    "gpiod": GpiodBoardConfig,
}
"""The typed config of each built-in board driver
(:data:`zplatform.boards.BUILTIN_DRIVERS`), by driver name."""

# What a mapping's keys are called in a path: `$.nodes.<node>`.
_KEY_NAMES = {
    "$.nodes": "node",
    "$.regions": "region",
    "$.state_machine.states": "state",
    "$.commands.whitelist": "state",
    "$.commands.write_states": "element",
}
# Where a key's type links to when its keys are not in the mission's tables.
_LINKS = {
    "$.nodes.<node>.board": "#boards",
    "$.devices[i].config": "#built-in-devices",
    "$.controllers[i].config": "#own-code",
}
_DEFS = "#/$defs/"
_SCALARS = ("integer", "number", "bool", "string")


def builtin_devices() -> dict[str, type[Sensor | Actuator]]:
    """The shipped device classes by the class path a mission names them with
    (``zplatform.control.devices:DigitalOutput``), in export order."""
    out: dict[str, type[Sensor | Actuator]] = {}
    for name in _devices.__all__:
        obj = getattr(_devices, name)
        if (
            isinstance(obj, type)
            and issubclass(obj, Sensor | Actuator)
            and obj not in (Sensor, Actuator)
            and not inspect.isabstract(obj)
        ):
            out[f"{obj.__module__}:{obj.__qualname__}"] = obj
    return out


def _clean(text: str) -> str:
    """A docstring as one markdown paragraph: dedented, RST ````x```` as ```x```."""
    text = inspect.cleandoc(text).replace("``", "`")
    text = re.sub(r":[a-z]+:`~?(?:[\w.]+\.)?([\w]+)`", r"`\1`", text)  # :class:`~a.B` -> `B`
    return " ".join(text.split())


def _clean_descriptions(node: Any) -> None:
    if isinstance(node, dict):
        if isinstance(node.get("description"), str):
            node["description"] = _clean(node["description"])
        for v in node.values():
            _clean_descriptions(v)
    elif isinstance(node, list):
        for v in node:
            _clean_descriptions(v)


def _def_name(ref: dict[str, Any]) -> str:
    return str(ref["$ref"]).removeprefix(_DEFS)


def mission_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of a mission file, as a fresh dict.

    The structs' own schema (``msgspec.json.schema``), with descriptions
    dedented, and two refinements msgspec cannot infer: ``nodes.<node>.board``
    is one of the built-in drivers' configs (``driver`` absent or ``sim``,
    ``serial``, ``gpiod``) or a ``package.module:Class`` driver with keys of
    its own; a device whose ``class`` is a built-in one has its ``config``
    checked against that class's ``Config``.
    """
    devices = builtin_devices()
    board_types = list(BOARD_CONFIGS.values())
    device_types = [cls.Config for cls in devices.values()]
    refs, defs = msgspec.json.schema_components(
        [Mission, *board_types, *device_types], ref_template=_DEFS + "{name}"
    )
    mission_ref, board_refs, device_refs = (
        refs[0],
        refs[1 : 1 + len(board_types)],
        refs[1 + len(board_types) :],
    )

    # Boards: each built-in config with its `driver` key, or a team's class.
    branches: list[dict[str, Any]] = []
    for driver, ref in zip(BOARD_CONFIGS, board_refs, strict=True):
        d = defs[_def_name(ref)]
        d["properties"] = {
            "driver": {"const": driver, "description": f"The `{driver}` board."},
            **d["properties"],
        }
        if driver != "sim":  # sim is the default: its `driver` may be left out
            d["required"] = ["driver", *d.get("required", [])]
        d["title"] = f"{driver} board"
        branches.append(ref)
    branches.append(
        {
            "title": "world board",
            "description": "A port onto the mission's vehicle world (`$.world`): the "
            "node's pins are declared in `$.world.boards.<dnX>`, so no other key.",
            "type": "object",
            "properties": {"driver": {"const": "world", "description": "The `world` board."}},
            "required": ["driver"],
            "additionalProperties": False,
        }
    )
    branches.append(
        {
            "title": "a team's own board",
            "description": "A `package.module:Class` driver; the other keys are its own "
            "config (its `Config` struct, checked at load).",
            "type": "object",
            "properties": {"driver": {"type": "string", "pattern": "^[^:\\s]+:[^:\\s]+$"}},
            "required": ["driver"],
        }
    )
    mission = defs[_def_name(mission_ref)]
    node = defs[_def_name(mission["properties"]["nodes"]["additionalProperties"])]
    board = node["properties"]["board"]
    board.pop("type", None)
    board.pop("additionalProperties", None)
    board["anyOf"] = branches

    # Devices: a built-in class's config is that class's Config.
    for (path, cls), ref in zip(devices.items(), device_refs, strict=True):
        d = defs[_def_name(ref)]
        d["title"] = f"{path} config"
        d["description"] = cls.__doc__ or ""
    component = mission["properties"]["devices"]["items"]
    mission["properties"]["devices"]["items"] = {
        "allOf": [
            component,
            *(
                {
                    "if": {"properties": {"class": {"const": path}}, "required": ["class"]},
                    "then": {"properties": {"config": ref}},
                }
                for path, ref in zip(devices, device_refs, strict=True)
            ),
        ]
    }
    _add_factory_defaults([Mission, *board_types, *device_types], defs)
    _clean_descriptions(defs)
    return {
        "$schema": JSON_SCHEMA_DIALECT,
        "title": "zplatform mission",
        "description": _clean(Mission.__doc__ or ""),
        **mission_ref,
        "$defs": defs,
    }


def _add_factory_defaults(roots: list[type], defs: dict[str, Any]) -> None:
    """Give ``defs`` the defaults msgspec leaves out: a field whose default
    comes from a factory other than a struct (``priority: ["ABORT"]``)."""
    structs: list[type[msgspec.Struct]] = []
    todo: list[Any] = list(msgspec.inspect.multi_type_info(roots))
    while todo:
        t = todo.pop()
        if isinstance(t, msgspec.inspect.StructType):
            if t.cls in structs:
                continue
            structs.append(t.cls)
            todo += [f.type for f in t.fields]
        elif isinstance(t, msgspec.inspect.Metadata):
            todo.append(t.type)
        else:  # containers and unions: look inside
            for attr in ("item_type", "key_type", "value_type"):
                if hasattr(t, attr):
                    todo.append(getattr(t, attr))
            todo += list(getattr(t, "types", ()) or ()) + list(getattr(t, "item_types", ()) or ())
    short = [c.__name__ for c in structs]
    for cls in structs:
        # msgspec's own naming: the class name, or the full path where two collide.
        unique = short.count(cls.__name__) == 1
        name = cls.__name__ if unique else f"{cls.__module__}.{cls.__qualname__}"
        props = defs[name]["properties"]
        for f in msgspec.structs.fields(cls):
            factory = f.default_factory
            if factory is msgspec.NODEFAULT or isinstance(factory, type):
                # No factory; `list`, `dict` (msgspec gives those), or a struct
                # (its keys have defaults of their own).
                continue
            props[f.encode_name].setdefault("default", msgspec.to_builtins(factory()))


def mission_schema_json() -> str:
    """:func:`mission_schema` as indented JSON text, ending in a newline."""
    return json.dumps(mission_schema(), indent=2, ensure_ascii=False) + "\n"


# ---------------------------------------------------------------------------
# the reference


class _Section(msgspec.Struct):
    path: str
    description: str
    rows: list[tuple[str, str, str, str, str]]  # path, type, default, bounds, meaning


def _anchor(path: str) -> str:
    """The anchor of a key table: ``$.nodes.<node>`` -> ``key-nodes-node`` (a
    prefix no heading's own slug has, so no id is given twice)."""
    slug = re.sub(r"[^a-z0-9]+", "-", path.lower()).strip("-")
    return "key-" + (slug or "top")


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _code(v: Any) -> str:
    return "`" + json.dumps(v, ensure_ascii=False) + "`"


class _Walker:
    """Renders the schema's structs as sections of key tables, depth first."""

    def __init__(self, schema: dict[str, Any]) -> None:
        self.defs: dict[str, Any] = schema["$defs"]
        self.sections: list[_Section] = []

    def resolve(self, node: dict[str, Any]) -> dict[str, Any]:
        """``node`` with its ``$ref`` followed: the struct's own keys and
        description, the outer keys (a default) over them."""
        while "$ref" in node:
            outer = {k: v for k, v in node.items() if k not in ("$ref", "description")}
            node = {**self.defs[_def_name(node)], **outer}
        if "allOf" in node:  # a device: the component struct plus per-class configs
            return self.resolve(node["allOf"][0])
        return node

    def non_null(self, node: dict[str, Any]) -> dict[str, Any]:
        """``X | None`` -> X, resolved, with the outer default."""
        node = self.resolve(node)
        options = node.get("anyOf")
        if options:
            rest = [o for o in options if o.get("type") != "null"]
            if len(rest) == 1:
                inner = self.resolve(rest[0])
                outer = {k: v for k, v in node.items() if k not in ("anyOf", "description")}
                return {**inner, **outer}
        return node

    def is_struct(self, node: dict[str, Any]) -> bool:
        return "properties" in node and node.get("type") == "object"

    def type_text(self, node: dict[str, Any], link: str = "", key: str = "key") -> str:
        """How a value of ``node`` is written; ``link`` is where its keys are
        listed, ``key`` what a mapping's keys are called."""
        node = self.resolve(node)
        if "const" in node:
            return _code(node["const"])
        if "enum" in node:
            return "one of " + ", ".join(_code(v) for v in node["enum"])
        options = node.get("anyOf")
        if options:
            if any(self.resolve(o).get("type") == "object" for o in options):
                return f"[mapping]({link})" if link else "mapping"
            texts = [self.type_text(o) for o in options]
            if set(_SCALARS) <= set(texts):
                rest = [t for t in texts if t not in _SCALARS]
                texts = ["scalar (number, bool or string)", *rest]
            return " or ".join(dict.fromkeys(texts))
        kind = node.get("type")
        if self.is_struct(node):
            return f"[mapping]({link})" if link else "mapping"
        if kind == "array":
            if "prefixItems" in node:
                return "[" + ", ".join(self.type_text(i) for i in node["prefixItems"]) + "]"
            return "list of " + self.type_text(node.get("items", {}), link)
        if kind == "object":
            values = node.get("additionalProperties")
            if isinstance(values, dict) and values:
                return f"mapping of `<{key}>` to " + self.type_text(values, link)
            return f"[mapping]({link})" if link else "mapping"
        return {"boolean": "bool", "null": "null"}.get(str(kind), str(kind))

    @staticmethod
    def bounds(node: dict[str, Any]) -> str:
        parts = []
        for key, sign in (
            ("minimum", "≥"),
            ("exclusiveMinimum", ">"),
            ("maximum", "≤"),
            ("exclusiveMaximum", "<"),
        ):
            if key in node:
                parts.append(f"{sign} {node[key]}")
        if "minLength" in node:
            parts.append(f"length ≥ {node['minLength']}")
        if "minItems" in node and "prefixItems" not in node:
            parts.append(f"≥ {node['minItems']} items")
        return ", ".join(parts)

    def walk(self, node: dict[str, Any], path: str) -> None:
        """Add the section of struct ``node`` at ``path``, then its sub-structs'."""
        struct = self.resolve(node)
        section = _Section(path, _clean(struct.get("description", "")), [])
        self.sections.append(section)
        required = set(struct.get("required", []))
        later: list[tuple[dict[str, Any], str]] = []
        for key, prop in struct["properties"].items():
            kpath = f"{path}.{key}"
            value = self.non_null(prop)
            sub, sub_path = self._nested(value, kpath)
            link = f"#{_anchor(sub_path)}" if sub is not None else _LINKS.get(kpath, "")
            if sub is not None:
                later.append((sub, sub_path))
            default = (
                "required"
                if key in required
                else _code(prop["default"])
                if "default" in prop
                else "see below"
                if sub is not None
                else ""
            )
            bounds = self.bounds(value)
            items = value.get("items")
            if not bounds and isinstance(items, dict):  # a list's items' bounds
                bounds = self.bounds(self.non_null(items))
            # A field's own description, else the first sentence of its struct's.
            meaning = prop.get("description") or _first_sentence(value.get("description", ""))
            section.rows.append(
                (
                    f"`{kpath}`",
                    _cell(self.type_text(prop, link, _KEY_NAMES.get(kpath, "key"))),
                    _cell(default),
                    _cell(bounds),
                    _cell(_clean(meaning)),
                )
            )
        for sub, sub_path in later:
            self.walk(sub, sub_path)

    def _nested(self, value: dict[str, Any], path: str) -> tuple[dict[str, Any] | None, str]:
        """The struct inside ``value`` (itself, a list's item, a mapping's value),
        and its path; ``(None, path)`` when there is none."""
        if self.is_struct(value):
            return value, path
        items = value.get("items")
        if value.get("type") == "array" and isinstance(items, dict):
            return self._nested(self.non_null(items), f"{path}[i]")
        if value.get("type") == "object" and isinstance(value.get("additionalProperties"), dict):
            name = _KEY_NAMES.get(path, "key")
            return self._nested(self.non_null(value["additionalProperties"]), f"{path}.<{name}>")
        return None, path


def _first_sentence(text: str) -> str:
    m = re.match(r"(.+?\.)(\s|$)", _clean(text))
    return m.group(1) if m else _clean(text)


def _table(rows: list[tuple[str, str, str, str, str]]) -> list[str]:
    out = ["| key | type | default | bounds | meaning |", "|---|---|---|---|---|"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out


def _block(anchor: str, heading: str, section: _Section, rows: slice = slice(None)) -> list[str]:
    """One key table under its anchor, heading and description."""
    out = ["", f'<a id="{anchor}"></a>', "", heading, ""]
    if section.description:
        out += [section.description, ""]
    return out + _table(section.rows[rows])


def _platform_rows() -> list[str]:
    """The platform elements of every region, for a mission with a device
    node (``dnX``) on a serial board holding a hazardous output, a ground
    node, a standby control node, a controller, a bulk channel, a flight
    recorder, a parameter and health."""
    # Only the board's driver matters here (it decides the dnX_board_*
    # elements); the board is never built.
    serial = NodeConfig(board={"driver": "serial", "port": "/dev/ttyACM0"})
    example = Mission(
        mission="m",
        nodes={"cn": NodeConfig(), "cn_b": NodeConfig(), "dn0": serial, "gn": NodeConfig()},
        regions={"cn_to_dn0": [ElementConfig(name="out_x", type="bool")]},
        hazardous_outputs=[HazardousOutputConfig(element="out_x", states=["IDLE"])],
        controllers=[ComponentConfig(name="ctl", cls="m:C", node="cn")],
        bulk=[BulkChannelConfig(name="chan", node="dn0", type="u8[8]", readers=["cn"])],
        recorder=RecorderConfig(),
        health=HealthConfig(),
        params=[
            ParamConfig(
                name="param_x",
                type="f32",
                default=0.0,
                min=0.0,
                max=1.0,
                doc="the parameter's value (a mission with `params`; so are the `cn_prm_*`)",
            )
        ],
    )
    names = (
        ("param_x", "<parameter>"),
        ("dn0", "dnX"),
        ("ctl_mode", "<controller>_mode"),
        ("ctl_enabled_ns", "<controller>_enabled_ns"),
        ("controller ctl's", "the controller's"),
        ("bulk_chan_", "bulk_<channel>_"),
        ("chan: ", ""),
    )

    def generic(text: str) -> str:
        for a, b in names:
            text = text.replace(a, b)
        return text

    out = ["| region | element | type | meaning |", "|---|---|---|---|"]
    for region, elements in _platform_elements(example).items():
        for e in elements:
            if e.name in ("cn_state", "dn0_state"):
                kind = "enum: the states, in order"
            elif e.name == "param_x":
                kind = "its `type`"
            elif e.type == "enum" and e.enum == list(CONTROLLER_MODES):
                kind = "enum: " + ", ".join(CONTROLLER_MODES)
            elif e.type == "enum":
                kind = "enum: " + ", ".join(e.enum or ())
            else:
                kind = e.type
            doc = generic(e.doc)
            if e.limits is not None:  # the health elements' defaults (100 Hz)
                bands = [
                    f"{band} [{', '.join('-' if x is None else f'{x:g}' for x in rng)}]"
                    for band in ("yellow", "red")
                    if (rng := getattr(e.limits, band)) is not None
                ]
                doc += f"; default limits {', '.join(bands)}"
            out.append(
                f"| `{generic(region)}` | `{generic(e.name)}` | {_cell(kind)} | {_cell(doc)} |"
            )
    return out


_INTRO = f"""\
# Mission file reference

<!-- Generated from the typed config (zplatform/config.py, the built-in
boards and devices); do not edit by hand. Change the descriptions in the
structs, then regenerate from the repository root:
{REGENERATE} -->

A mission is one YAML file: its nodes and their zenoh endpoints, the Data
Vector, the state machine, the controllers and devices, and the command
rules. This page lists every key the platform reads, generated from the
same typed structs that check a mission at load, so it cannot drift from
the code. Paths are written the way errors name them:

    zplatform: error: Object contains unknown field `lisen` - at `$.nodes.cn`

`$` is the top of the file, `.key` a key of a mapping, `[i]` an item of a
list, and `<node>`, `<state>`, `<region>` stand for names you choose. A
key with a default may be left out; an unknown key is an error. A
`mapping` links to the table of its keys. Bounds are checked at load.

`zplatform check MISSION` runs every rule, including the ones a table
cannot show (names that exist, regions that match the nodes, pins a board
has, each class's own config). The [tutorial](tutorial.md) builds a
mission step by step; [architecture](architecture.md) explains what runs
where.

## Completion in your editor

`zplatform schema` prints the mission file's JSON Schema, the source of
this page. Save it next to your missions and point your editor at it:

    zplatform schema --out mission.schema.json

With the YAML language server (VS Code's YAML extension, Neovim, Helix,
Emacs lsp-mode), a comment on the first line of a mission file does it:

    # yaml-language-server: $schema=mission.schema.json

(the path is relative to the mission file), or, for every mission of a
folder, VS Code's `settings.json`:

    "yaml.schemas": {{"./mission.schema.json": "missions/*.yaml"}}

Keys complete with their descriptions, and wrong types, bounds and unknown
keys are marked as you type. A board's keys follow its `driver`, and a
built-in device's `config` follows its `class`; your own classes' configs
are checked by `zplatform check`.
"""

_OWN_CODE = """\
<a id="own-code"></a>

## Your own controllers, devices, boards and physics

A component's `config:` mapping is decoded into the class's own typed
config, a nested `Config` struct; unknown keys and wrong types fail at
load with their YAML path (`$.controllers[0].config.gain`), and bounds in
`Annotated[..., Meta(...)]` are checked the same way:

```python
from typing import Annotated

import msgspec
from msgspec import Meta

from zplatform import Controller


class Thermostat(Controller):
    class Config(msgspec.Struct, forbid_unknown_fields=True):
        temperature: str                                  # an element to read
        heater: str                                       # an element to write
        band_c: Annotated[float, Meta(gt=0)] = 2.0

    def bind(self, dv):  # once, at load: element handles, checked
        self._t = self.input(self.config.temperature, "temperature", kinds=("float",))
        self._heater = self.output(self.config.heater, "heater", kinds=("bool",))

    def run_enabled(self, t_ns): ...
    def run_safed(self, t_ns): self._heater.set(False)
```

* **Controllers** subclass `zplatform.Controller` and implement
  `run_enabled(t_ns)` and `run_safed(t_ns)` (`run_manual` leaves the
  outputs to the operator's WRITEs). They run on the CN or a device node,
  every `rate_divisor`-th loop, in the mode the element
  `<name>_mode` holds (`enabled`, `safed`, `manual`; anything else runs
  `safed`). A controller that raises is counted, reported once per streak,
  and safed.
* **Devices** subclass `zplatform.Sensor` (run before the node's
  controllers) or `zplatform.Actuator` (after them; override
  `safe(t_ns)` to drive the output to its safe value) and implement
  `run(t_ns)`; they reach the hardware only through `self.board`.
* **Handles**: `self.input(name, field)` may read any element of the
  node's Data Vector; `self.output(name, field)` only one of a region the
  node writes (the CN: `cn`, `cn_to_dnX`; a device node: its `dnX_to_cn`).
  `field` names the config key, so a bad element name is reported at
  `$.controllers[i].config.<field>`.
* **Physics** (`board: {physics: "pkg.mod:function"}` on a sim board): a
  function `function(board, t_ns)`; give it a `Params` attribute (a
  `msgspec.Struct` type) and the board's `params` are decoded into it at
  load, read as `board.params`.
* **Boards** (`board: {driver: "pkg.mod:Class", ...}`): called as
  `Class(config, where=path)` with the mapping minus `driver`; decode it
  into a `Config` struct (`zplatform.core.components.decode_component_config`)
  and touch no hardware before `open()`. The board contract is in the
  docstring of `zplatform/boards/__init__.py`.

The mission file names each class by `package.module:ClassName`. Put your
package next to the mission file: the mission's own directory is on the
import path of every verb that runs mission code, so no `PYTHONPATH` is
needed (see the [tutorial](tutorial.md)).
"""


def reference_markdown() -> str:
    """``docs/mission-reference.md``: the mission file's keys, generated from
    :func:`mission_schema` (see the module docstring)."""
    schema = mission_schema()
    walker = _Walker(schema)
    walker.walk(schema, "$")
    out = [_INTRO, "## The mission file"]
    for s in walker.sections:
        out += _block(_anchor(s.path), f"### `{s.path}`", s)
    out += [
        "",
        "## Platform elements",
        "",
        "Every mission's Data Vector has these elements, added to its regions "
        "before the mission's own (do not declare them): one set per device node "
        "`dnX`, a `<controller>_mode` per controller (in `cn` for a controller on "
        "the CN, in `cn_to_dnX` for one on dnX), bulk counters per channel on its "
        "owner and readers, flight recorder counters on each node that records "
        "(`recorder`), the board link elements `dnX_board_*` of each device node "
        "whose board talks to hardware (`driver: serial` or `gpiod`), `dnX_state` "
        "and `dnX_interlocked` of each device node holding a hazardous output "
        "(`hazardous_outputs`), the health "
        "elements of each node when the mission has a `health:` section (`cn_...` "
        "in `cn`, `dnX_...` in `dnX_to_cn`; see `zplatform.core.health`), and "
        "`gn_to_cn` when the mission has a ground node. "
        "Counters saturate at their type's maximum (they never wrap); times are "
        "nanoseconds.",
        "",
        *_platform_rows(),
        "",
        "## Boards",
        "",
        "A device node's `board:` mapping names a `driver` (default `sim`); its "
        "other keys are that driver's, checked at load: "
        "`$.nodes.<dnX>.board.<key>`.",
    ]
    for driver in BOARD_CONFIGS:
        section = _struct_section(schema, f"{driver} board", "$.nodes.<dnX>.board")
        # Less the `driver` row (the first): the heading says it.
        out += _block(f"board-{driver}", f"### `driver: {driver}`", section, slice(1, None))
    out += [
        "",
        '<a id="board-world"></a>',
        "",
        "### `driver: world`",
        "",
        "A port onto the mission's vehicle world (`$.world`, see `zplatform.world.model`): "
        "one physics shared by every board of the vehicle. It takes no other key; the "
        "node's pins are declared in `$.world.boards.<dnX>`.",
    ]
    out += [
        "",
        "## Built-in devices",
        "",
        "Devices a mission uses by class path, on any device node: "
        "`{name, class, node, config}` in `$.devices`, with `config` as below "
        "(`$.devices[i].config.<key>`).",
    ]
    for path in builtin_devices():
        section = _struct_section(schema, f"{path} config", "$.devices[i].config")
        out += _block(_anchor(path), f"### `class: {path}`", section)
    out += ["", _OWN_CODE]
    return "\n".join(out).rstrip() + "\n"


def _struct_section(schema: dict[str, Any], title: str, path: str) -> _Section:
    """The key table of the ``$defs`` struct titled ``title``, at ``path``."""
    (name,) = (n for n, d in schema["$defs"].items() if d.get("title") == title)
    walker = _Walker(schema)
    walker.walk({"$ref": _DEFS + name}, path)
    return walker.sections[0]
