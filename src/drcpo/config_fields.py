"""How config keys are declared and checked: the one validation mechanism of every stage's config.

Each stage defines its configuration once, as a frozen dataclass in its own module
(:class:`drcpo.construction.ConstructionConfig`, :class:`drcpo.placement.PlacementConfig`,
:class:`drcpo.index.IndexConfig`, the transforms' in :mod:`drcpo.config`), whose field names are
the YAML keys. Every field carries a :class:`Spec` (:func:`spec`): its kind, bounds or choices and
a one-line description. The dataclasses derive from :class:`Checked`, so a config built in code
is checked and normalised (lists for tuples, ``float`` for numbers) exactly as one read from a
file; :func:`merge` applies a YAML mapping on top of a config, naming the full key path on any
bad key or value, and :func:`to_dict` writes the keys back out.

A field whose spec has ``set_by`` is not a key of a config file: the code that uses the config
sets it (a per-call variant such as placement's ``fov_only``, or the index's grids, which come
from construction's). It is checked like the others, refused in a file with a message saying
where the value comes from, and left out of :func:`to_dict`.

This module is light (no numba, no stage imports), so that stage modules can use it and
:mod:`drcpo.config` can compose them without an import cycle.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from drcpo.errors import ConfigError, shown

__all__ = [
    "SECTION",
    "Checked",
    "Spec",
    "check",
    "from_dict",
    "key_fields",
    "merge",
    "spec",
    "to_dict",
]


@dataclass(frozen=True)
class Spec:
    """How one config key is checked: its kind, inclusive/exclusive bounds or choices."""

    kind: str  # int, float, bool, choice, range, per_class, names, ints, floats, grids, section
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple[str, ...] = ()
    optional: bool = False
    scalar_ok: bool = False  # per_class: a plain number means {"default": n}
    strict: bool = False  # range: low < high (an empty interval is meaningless)
    classes: bool = False  # names / per_class / grids: class names, checked vs known_classes
    nonempty: bool = False  # names, floats: at least one
    length: int = 0  # floats: exactly this many (0: any number)
    set_by: str = ""  # not a config file key: who sets it (shown when a file tries to)

    def describe_range(self) -> str:
        left = "(" if self.low_open else "["
        right = ")" if self.high_open else "]"
        low = "-inf" if self.low is None else _fmt(self.low)
        high = "inf" if self.high is None else _fmt(self.high)
        return f"{left}{low}, {high}{right}"

    @property
    def is_key(self) -> bool:
        """Whether the field is a key of a config file (else code sets it, see ``set_by``)."""
        return not self.set_by


def _fmt(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else repr(float(value))


def spec(kind: str, doc: str = "", **options: Any) -> dict[str, Any]:
    """Field metadata: how the key is checked (a :class:`Spec`) and a one-line description."""
    return {"spec": Spec(kind, **options), "doc": doc}


#: Metadata of a field holding a nested config section.
SECTION: dict[str, Any] = {"spec": Spec("section"), "doc": ""}


class Checked:
    """Base of the config dataclasses (declared ``@dataclass(frozen=True, eq=False)``): checks
    and normalises every field on construction; equal when of one class with equal fields, and
    hashable (so that a config can key a cache) although its values are lists and dicts.

    ``KEY_PATH`` is the dotted key path of the section in the whole config (for the messages of
    a config built in code; :func:`merge` names the path it was given).
    """

    KEY_PATH: ClassVar[str] = ""

    def _values(self) -> tuple[Any, ...]:
        return tuple(getattr(self, f.name) for f in dataclasses.fields(self))  # type: ignore[arg-type]

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return self._values() == other._values()  # type: ignore[attr-defined]

    def __hash__(self) -> int:
        return hash((type(self), _frozen(self._values())))

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            field_spec: Spec = f.metadata["spec"]
            if field_spec.kind == "section":
                continue
            where = f"{self.KEY_PATH}.{f.name}" if self.KEY_PATH else f.name
            object.__setattr__(self, f.name, check(getattr(self, f.name), field_spec, where))


def _frozen(value: Any) -> Any:
    """A hashable value equal where ``value`` is (dicts compare regardless of order)."""
    if isinstance(value, Mapping):
        return frozenset((k, _frozen(v)) for k, v in value.items())
    if isinstance(value, list | tuple):
        return tuple(_frozen(v) for v in value)
    return value


def key_fields(config: Any) -> Iterator[dataclasses.Field]:
    """The fields of config dataclass ``config`` that are config file keys (sections included)."""
    return (f for f in dataclasses.fields(config) if f.metadata["spec"].is_key)


def to_dict(config: Any) -> dict[str, Any]:
    """Every key of a config dataclass as plain YAML/JSON types (sections nested)."""
    out: dict[str, Any] = {}
    for f in key_fields(config):
        value = getattr(config, f.name)
        out[f.name] = to_dict(value) if dataclasses.is_dataclass(value) else _copy(value)
    return out


def _copy(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _copy(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_copy(v) for v in value]
    return value


def from_dict(cls: type, data: Mapping[str, Any] | None, path: str = "") -> Any:
    """Build config dataclass ``cls`` from ``data`` on top of its defaults, validating every key.

    Args:
        cls: a config dataclass (a :class:`Checked` with :func:`spec` fields).
        data: the keys to set (missing keys keep their defaults).
        path: dotted key path of ``data`` within the whole config, for messages.
    """
    return merge(cls(), data, path)


def merge(base: Any, data: Mapping[str, Any] | None, path: str) -> Any:
    """``base`` with the keys of ``data`` applied (sections recursively), each checked first so
    that a message names its full path ``path.key``."""
    if data is None:
        return base
    if not isinstance(data, Mapping):
        raise ConfigError(f"config key {path or '<root>'!r} must be a mapping, got {shown(data)}")
    fields = {f.name: f for f in dataclasses.fields(base)}
    keys = sorted(f.name for f in key_fields(base))
    changes: dict[str, Any] = {}
    for key, value in data.items():
        where = f"{path}.{key}" if path else str(key)
        if key not in fields:
            raise ConfigError(f"unknown config key {where!r}; allowed keys here: {', '.join(keys)}")
        field_spec: Spec = fields[key].metadata["spec"]
        if not field_spec.is_key:
            raise ConfigError(
                f"config key {where!r} is not set in a config file: {field_spec.set_by}; "
                f"allowed keys here: {', '.join(keys)}"
            )
        if field_spec.kind == "section":
            changes[key] = merge(getattr(base, key), value, where)
        else:
            changes[key] = check(value, field_spec, where)
    return dataclasses.replace(base, **changes)


def check(value: Any, field_spec: Spec, where: str) -> Any:
    """``value`` checked against ``field_spec`` and normalised; :class:`ConfigError` naming the
    key ``where`` and what is allowed otherwise."""
    if value is None:
        if field_spec.optional:
            return None
        raise ConfigError(f"config key {where!r} must be set (null is not allowed)")
    kind = field_spec.kind
    if kind == "bool":
        if not isinstance(value, bool):
            raise ConfigError(f"config key {where!r} must be true or false, got {shown(value)}")
        return value
    if kind in ("int", "float"):
        return _number(value, field_spec, where, integer=kind == "int")
    if kind == "choice":
        if value not in field_spec.choices:
            raise ConfigError(
                f"config key {where!r} = {shown(value)} is not allowed; "
                f"choose one of: {', '.join(field_spec.choices)}"
            )
        return value
    if kind == "range":
        return _interval(value, field_spec, where)
    if kind == "per_class":
        return _per_class(value, field_spec, where)
    if kind == "names":
        return _names(value, field_spec, where)
    if kind == "ints":
        if isinstance(value, str) or not isinstance(value, list | tuple):
            raise ConfigError(f"config key {where!r} must be a list of integers")
        return [_number(v, field_spec, f"{where}[{i}]", integer=True) for i, v in enumerate(value)]
    if kind == "floats":
        return _floats(value, field_spec, where)
    if kind == "grids":
        return _grids(value, where)
    raise AssertionError(f"unknown spec kind {kind}")


def _number(value: Any, field_spec: Spec, where: str, integer: bool) -> int | float:
    # numbers.Integral / Real: numpy scalars pass as well as Python's (bool never does).
    ok_types = (numbers.Integral,) if integer else (numbers.Real,)
    if isinstance(value, bool) or not isinstance(value, ok_types):
        if integer and isinstance(value, float) and value.is_integer():
            value = int(value)
        else:
            wanted = "an integer" if integer else "a number"
            raise ConfigError(f"config key {where!r} must be {wanted}, got {shown(value)}")
    value = int(value) if isinstance(value, numbers.Integral) else float(value)
    # Integers compare exactly with the bounds (float() of a huge one would overflow).
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(f"config key {where!r} must be finite, got {value}")
    low, high = field_spec.low, field_spec.high
    too_low = low is not None and (value <= low if field_spec.low_open else value < low)
    too_high = high is not None and (value >= high if field_spec.high_open else value > high)
    if too_low or too_high:
        raise ConfigError(
            f"config key {where!r} = {shown(value)} is out of range; allowed range: "
            f"{field_spec.describe_range()}"
        )
    return int(value) if integer else float(value)


def _interval(value: Any, field_spec: Spec, where: str) -> list[float]:
    if not isinstance(value, list | tuple) or len(value) != 2:
        raise ConfigError(f"config key {where!r} must be a pair [low, high], got {shown(value)}")
    low, high = (
        _number(v, field_spec, f"{where}[{i}]", integer=False) for i, v in enumerate(value)
    )
    if field_spec.strict and low >= high:
        raise ConfigError(f"config key {where!r} = [{low}, {high}]: low must be below high")
    if low > high:
        raise ConfigError(f"config key {where!r} = [{low}, {high}]: low must not exceed high")
    return [low, high]


def _per_class(value: Any, field_spec: Spec, where: str) -> dict[str, int]:
    if field_spec.scalar_ok and isinstance(value, int | float) and not isinstance(value, bool):
        return {"default": _number(value, field_spec, where, integer=True)}
    if not isinstance(value, Mapping):
        hint = "a number or " if field_spec.scalar_ok else ""
        raise ConfigError(
            f"config key {where!r} must be {hint}a mapping of class name to integer, "
            f"got {shown(value)}"
        )
    out = {}
    for name, count in value.items():
        if not isinstance(name, str) or not name:
            raise ConfigError(f"config key {where!r}: class names must be strings, got {name!r}")
        out[name] = _number(count, field_spec, f"{where}.{name}", integer=True)
    return out


def _names(value: Any, field_spec: Spec, where: str) -> list[str]:
    if isinstance(value, str) or not isinstance(value, list | tuple):
        raise ConfigError(f"config key {where!r} must be a list of names, got {shown(value)}")
    if field_spec.nonempty and not value:
        raise ConfigError(f"config key {where!r} must name at least one class")
    seen: set[str] = set()
    for i, name in enumerate(value):
        if not isinstance(name, str) or not name:
            raise ConfigError(
                f"config key {f'{where}[{i}]'!r} must be a non-empty string, got {shown(name)}"
            )
        if field_spec.choices and name not in field_spec.choices:
            raise ConfigError(
                f"config key {f'{where}[{i}]'!r} = {name!r} is not allowed; "
                f"choose from: {', '.join(field_spec.choices)}"
            )
        if name in seen:
            raise ConfigError(f"config key {f'{where}[{i}]'!r} = {name!r} is listed twice")
        seen.add(name)
    return list(value)


def _floats(value: Any, field_spec: Spec, where: str) -> list[float]:
    if isinstance(value, str) or not isinstance(value, list | tuple):
        raise ConfigError(f"config key {where!r} must be a list of numbers, got {shown(value)}")
    if field_spec.length and len(value) != field_spec.length:
        raise ConfigError(
            f"config key {where!r} must be a list of {field_spec.length} numbers, got {len(value)}"
        )
    if field_spec.nonempty and not value:
        raise ConfigError(f"config key {where!r} must list at least one number")
    return [_number(v, field_spec, f"{where}[{i}]", integer=False) for i, v in enumerate(value)]


def _grids(value: Any, where: str) -> dict[str, list[int]]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"config key {where!r} must map class names to [nx, ny, nz]")
    out = {}
    cell_spec = Spec("int", low=1, high=100)
    for name, grid in value.items():
        if not isinstance(name, str) or not name:
            raise ConfigError(f"config key {where!r}: class names must be strings, got {name!r}")
        if not isinstance(grid, list | tuple) or len(grid) != 3:
            raise ConfigError(
                f"config key {f'{where}.{name}'!r} must be [nx, ny, nz], got {shown(grid)}"
            )
        out[name] = [
            _number(n, cell_spec, f"{where}.{name}[{i}]", integer=True) for i, n in enumerate(grid)
        ]
    return out
