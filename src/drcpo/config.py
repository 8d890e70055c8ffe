"""Validated augmentation configuration: the paper's defaults, detector presets, YAML files.

A configuration is a tree of frozen dataclasses (:class:`AugmentConfig` at the root). It is read
from YAML (``yaml.safe_load``) or a plain dict by :func:`load_config`, which starts from the
paper's defaults (or a named detector preset) and applies the given keys on top, so a file only
needs the keys it changes. :meth:`AugmentConfig.to_dict` writes every key back out, and
``load_config(config.to_dict()) == config``.

Every key is checked: an unknown key raises :class:`~drcpo.errors.ConfigError` naming its path
and the keys allowed there; a value of the wrong type or out of range names the key and the
allowed range or choices.

Per-class values (object counts, minimum points) are mappings ``{class name: value}``; where a
single number makes sense for every class (minimum points) a plain number is accepted and stored
as ``{"default": n}``. The key ``default`` applies to classes without their own entry (in the
minimum-point maps and partition grids only: object counts are per named class). Every class
name used must be listed in the top-level ``known_classes`` (KITTI's classes by default), so a
misspelt name (``Pedestrain``) is an error rather than a class that never occurs.

YAML files are read as UTF-8 with PyYAML's safe loader, except that a key given twice in one
mapping is an error (naming the key and both lines) and ``5e4`` reads as a number, as in YAML 1.2.

Detector presets (``second``, ``pointrcnn``, ``pv_rcnn``, ``pv_rcnn_plusplus``) choose the e-HPR
viewpoint height and radius of the paper's reference configuration for each detector; they live
as YAML files in ``drcpo/configs/`` next to ``default.yaml`` (the paper defaults, spelled out).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from drcpo.errors import ConfigError, shown

#: Detector presets shipped with the package (``drcpo/configs/<name>.yaml``).
PRESETS: tuple[str, ...] = ("second", "pointrcnn", "pv_rcnn", "pv_rcnn_plusplus")
#: The preset whose e-HPR settings the paper defaults use.
DEFAULT_PRESET = "pv_rcnn_plusplus"
#: Pipelines :func:`build_pipeline` can make.
PIPELINES: tuple[str, ...] = ("drcpo", "cda")
#: Class names the per-class keys may use unless ``known_classes`` says otherwise (KITTI's).
KITTI_CLASSES: tuple[str, ...] = (
    "Car",
    "Van",
    "Truck",
    "Pedestrian",
    "Person_sitting",
    "Cyclist",
    "Tram",
    "Misc",
)
#: Largest e-HPR radius: the same bound as :data:`drcpo.occlusion.MAX_RADIUS` (not imported:
#: that module compiles numba kernels and this one must stay light).
MAX_RADIUS = 1e150


# --------------------------------------------------------------------------------------------
# Field specifications
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Spec:
    """How one config key is checked: its kind, inclusive/exclusive bounds or choices."""

    kind: str  # int, float, bool, choice, range, per_class, names, ints, grids, section
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple[str, ...] = ()
    optional: bool = False
    scalar_ok: bool = False  # per_class: a plain number means {"default": n}
    strict: bool = False  # range: low < high (an empty interval is meaningless)
    classes: bool = False  # names / per_class / grids: class names, checked vs known_classes
    nonempty: bool = False  # names: at least one

    def describe_range(self) -> str:
        left = "(" if self.low_open else "["
        right = ")" if self.high_open else "]"
        low = "-inf" if self.low is None else _fmt(self.low)
        high = "inf" if self.high is None else _fmt(self.high)
        return f"{left}{low}, {high}{right}"


def _fmt(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else repr(float(value))


def _spec(kind: str, doc: str = "", **spec: Any) -> dict[str, Any]:
    """Field metadata: how the key is checked (a :class:`_Spec`) and a one-line description."""
    return {"spec": _Spec(kind, **spec), "doc": doc}


_SECTION = {"spec": _Spec("section"), "doc": ""}


def _copy(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _copy(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_copy(v) for v in value]
    return value


# --------------------------------------------------------------------------------------------
# The configuration tree (paper defaults)
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FlipConfig:
    """Random flip: with ``probability`` per axis listed (``x``: y -> -y; ``y``: x -> -x)."""

    probability: float = field(
        default=0.5, metadata=_spec("float", "chance of each flip", low=0.0, high=1.0)
    )
    axes: list[str] = field(
        default_factory=lambda: ["x"],
        metadata=_spec("names", "axes to flip along", choices=("x", "y")),
    )


@dataclass(frozen=True)
class RotationConfig:
    """Random rotation about z, angle uniform in ``range`` (radians)."""

    range: list[float] = field(
        default_factory=lambda: [-math.pi / 4, math.pi / 4],
        metadata=_spec("range", "angle interval", low=-2 * math.pi, high=2 * math.pi),
    )


@dataclass(frozen=True)
class ScalingConfig:
    """Random uniform scaling of the scene, factor uniform in ``range``."""

    range: list[float] = field(
        default_factory=lambda: [0.95, 1.05],
        metadata=_spec("range", "factor interval", low=0.0, low_open=True, high=10.0),
    )


@dataclass(frozen=True)
class GlobalAugmentationConfig:
    """Global augmentation (flip, rotation, scaling), applied last, as OpenPCDet does."""

    enabled: bool = field(default=True, metadata=_spec("bool"))
    flip: FlipConfig = field(default_factory=FlipConfig, metadata=_SECTION)
    rotation: RotationConfig = field(default_factory=RotationConfig, metadata=_SECTION)
    scaling: ScalingConfig = field(default_factory=ScalingConfig, metadata=_SECTION)


@dataclass(frozen=True)
class GTSamplingConfig:
    """Ground-truth sampling with OpenPCDet's semantics (the conventional baseline)."""

    enabled: bool = field(default=True, metadata=_spec("bool"))
    targets: dict[str, int] = field(
        default_factory=lambda: {"Car": 20, "Pedestrian": 15, "Cyclist": 15},
        metadata=_spec(
            "per_class",
            "objects per class after sampling (existing ones count)",
            low=0,
            high=1000,
            classes=True,
        ),
    )
    min_points: dict[str, int] = field(
        default_factory=lambda: {"default": 5},
        metadata=_spec(
            "per_class",
            "fewest points a sampled object may have",
            low=0,
            high=1e6,
            scalar_ok=True,
            classes=True,
        ),
    )
    exclude_difficulty: list[int] = field(
        default_factory=lambda: [],
        metadata=_spec(
            "ints",
            "difficulty codes never sampled (OpenPCDet filter_by_difficulty)",
            low=-1,
            high=2,
        ),
    )
    use_road_plane: bool = field(
        default=True, metadata=_spec("bool", "put boxes on the KITTI road plane when present")
    )


@dataclass(frozen=True)
class ConstructionConfig:
    """Iterative construction of whole-body objects in canonical pose."""

    mode: str = field(
        default="partition",
        metadata=_spec(
            "choice", "paper (partition) or reference (whole)", choices=("partition", "whole")
        ),
    )
    coverage: float = field(
        default=0.85,
        metadata=_spec(
            "float", "stop when this share of partitions is dense", low=0.0, high=1.0, low_open=True
        ),
    )
    max_iterations: int = field(
        default=20, metadata=_spec("int", "most construction rounds", low=0, high=1000)
    )
    margin: float = field(
        default=0.05,
        metadata=_spec(
            "float", "metres beyond the box where added points are kept", low=0.0, high=1.0
        ),
    )
    mirror: list[str] = field(
        default_factory=lambda: ["Car", "Cyclist"],
        metadata=_spec("names", "classes mirrored across the x axis", classes=True),
    )
    grids: dict[str, list[int]] = field(
        default_factory=lambda: {},
        metadata=_spec("grids", "partition grid overrides per class", classes=True),
    )


@dataclass(frozen=True)
class PlacementSettings:
    """Random placement: area, height, collision and background checks."""

    x_range: list[float] = field(
        default_factory=lambda: [0.0, 70.4],
        metadata=_spec("range", "metres, box inside", low=-200.0, high=200.0, strict=True),
    )
    y_range: list[float] = field(
        default_factory=lambda: [-40.0, 40.0],
        metadata=_spec("range", "metres, box inside", low=-200.0, high=200.0, strict=True),
    )
    height: str = field(
        default="ground",
        metadata=_spec(
            "choice",
            "box bottom on the local ground, or source height",
            choices=("ground", "source"),
        ),
    )
    max_non_ground_points: int = field(
        default=10,
        metadata=_spec("int", "frame points allowed inside a placed box", low=0, high=1_000_000),
    )
    ground_tolerance: float = field(
        default=0.2,
        metadata=_spec(
            "float", "points this far above the ground are non-ground (m)", low=0.0, high=10.0
        ),
    )
    attempts: int = field(
        default=1,
        metadata=_spec("int", "poses tried per sampled object (the paper: 1)", low=1, high=1000),
    )
    occluded_fraction: float | None = field(
        default=1.0,
        metadata=_spec(
            "float",
            "reject a placed box before construction once this share of its sensor-facing "
            "surface e-HPR hides behind the frame's points (it would almost always drop the "
            "object; 1.0: only fully hidden boxes; null: never)",
            low=0.0,
            high=1.0,
            low_open=True,
            optional=True,
        ),
    )
    camera_fov: str = field(
        default="auto",
        metadata=_spec(
            "choice",
            "place inside the camera view: auto = when the frame is cut to it",
            choices=("auto", "always", "never"),
        ),
    )


@dataclass(frozen=True)
class SelfOcclusionConfig:
    """s-HPR on each placed object, viewpoint at the sensor."""

    enabled: bool = field(default=True, metadata=_spec("bool"))
    radius_factor: float = field(
        default=200.0,
        metadata=_spec("float", "R = box diagonal x this", low=0.0, low_open=True, high=1e9),
    )
    min_points: int = field(
        default=5, metadata=_spec("int", "fewest points an object keeps", low=0, high=1_000_000)
    )


@dataclass(frozen=True)
class ExternalOcclusionConfig:
    """e-HPR (or the range-image mode) on the frame after insertion."""

    enabled: bool = field(default=True, metadata=_spec("bool"))
    mode: str = field(
        default="hpr",
        metadata=_spec(
            "choice", "hpr (the paper) or range_image (z-buffer)", choices=("hpr", "range_image")
        ),
    )
    preset: str = field(
        default=DEFAULT_PRESET,
        metadata=_spec("choice", "detector whose (R, z) is used", choices=PRESETS),
    )
    scope: str = field(
        default="inserted",
        metadata=_spec("choice", "which points e-HPR may remove", choices=("inserted", "frame")),
    )
    radius: float | None = field(
        default=None,
        metadata=_spec(
            "float", "override R", low=0.0, low_open=True, high=MAX_RADIUS, optional=True
        ),
    )
    viewpoint_z: float | None = field(
        default=None,
        metadata=_spec(
            "float", "override viewpoint height (m)", low=-100.0, high=100.0, optional=True
        ),
    )


@dataclass(frozen=True)
class DRCPOConfig:
    """DR.CPO: sample, construct, place, s-HPR, insert, e-HPR, filter labels."""

    enabled: bool = field(default=True, metadata=_spec("bool"))
    sample: dict[str, int] = field(
        default_factory=lambda: {"Car": 10, "Pedestrian": 10, "Cyclist": 10},
        metadata=_spec(
            "per_class",
            "objects tried per frame",
            low=0,
            high=1000,
            classes=True,
        ),
    )
    min_points: dict[str, int] = field(
        default_factory=lambda: {"default": 5},
        metadata=_spec(
            "per_class",
            "fewest points a sampled source object has",
            low=0,
            high=1e6,
            scalar_ok=True,
            classes=True,
        ),
    )
    exclude_difficulty: list[int] = field(
        default_factory=lambda: [],
        metadata=_spec("ints", "difficulty codes never sampled", low=-1, high=2),
    )
    min_points_after: int = field(
        default=5,
        metadata=_spec(
            "int", "a box with fewer points after e-HPR is dropped", low=0, high=1_000_000
        ),
    )
    construction: ConstructionConfig = field(default_factory=ConstructionConfig, metadata=_SECTION)
    placement: PlacementSettings = field(default_factory=PlacementSettings, metadata=_SECTION)
    self_occlusion: SelfOcclusionConfig = field(
        default_factory=SelfOcclusionConfig, metadata=_SECTION
    )
    external_occlusion: ExternalOcclusionConfig = field(
        default_factory=ExternalOcclusionConfig, metadata=_SECTION
    )


@dataclass(frozen=True)
class AugmentConfig:
    """The whole augmentation: which pipeline and each stage's settings."""

    pipeline: str = field(
        default="drcpo",
        metadata=_spec("choice", "drcpo or the conventional baseline (cda)", choices=PIPELINES),
    )
    preset: str | None = field(
        default=None,
        metadata=_spec(
            "choice", "detector preset applied before these keys", choices=PRESETS, optional=True
        ),
    )
    known_classes: list[str] = field(
        default_factory=lambda: list(KITTI_CLASSES),
        metadata=_spec("names", "class names the per-class keys may use", nonempty=True),
    )
    gt_sampling: GTSamplingConfig = field(default_factory=GTSamplingConfig, metadata=_SECTION)
    drcpo: DRCPOConfig = field(default_factory=DRCPOConfig, metadata=_SECTION)
    global_augmentation: GlobalAugmentationConfig = field(
        default_factory=GlobalAugmentationConfig, metadata=_SECTION
    )

    def to_dict(self) -> dict[str, Any]:
        """Every key as plain YAML/JSON types; :func:`load_config` reads it back unchanged."""
        return to_dict(self)

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)


# --------------------------------------------------------------------------------------------
# Reading, validating, writing
# --------------------------------------------------------------------------------------------
def to_dict(config: Any) -> dict[str, Any]:
    """Plain-dict form of any config dataclass in this module."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        out[f.name] = to_dict(value) if dataclasses.is_dataclass(value) else _copy(value)
    return out


def from_dict(cls: type, data: Mapping[str, Any] | None, path: str = "") -> Any:
    """Build config dataclass ``cls`` from ``data`` on top of its defaults, validating every key.

    Args:
        cls: a config dataclass of this module.
        data: the keys to set (missing keys keep their defaults).
        path: dotted key path of ``data`` within the whole config, for messages.
    """
    return _merge(cls(), data, path)


def _merge(base: Any, data: Mapping[str, Any] | None, path: str) -> Any:
    if data is None:
        return base
    if not isinstance(data, Mapping):
        raise ConfigError(f"config key {path or '<root>'!r} must be a mapping, got {shown(data)}")
    fields = {f.name: f for f in dataclasses.fields(base)}
    changes: dict[str, Any] = {}
    for key, value in data.items():
        where = f"{path}.{key}" if path else str(key)
        if key not in fields:
            raise ConfigError(
                f"unknown config key {where!r}; allowed keys here: {', '.join(sorted(fields))}"
            )
        spec: _Spec = fields[key].metadata["spec"]
        if spec.kind == "section":
            changes[key] = _merge(getattr(base, key), value, where)
        else:
            changes[key] = _check(value, spec, where)
    return dataclasses.replace(base, **changes)


def _check(value: Any, spec: _Spec, where: str) -> Any:
    if value is None:
        if spec.optional:
            return None
        raise ConfigError(f"config key {where!r} must be set (null is not allowed)")
    kind = spec.kind
    if kind == "bool":
        if not isinstance(value, bool):
            raise ConfigError(f"config key {where!r} must be true or false, got {shown(value)}")
        return value
    if kind in ("int", "float"):
        return _number(value, spec, where, integer=kind == "int")
    if kind == "choice":
        if value not in spec.choices:
            raise ConfigError(
                f"config key {where!r} = {shown(value)} is not allowed; "
                f"choose one of: {', '.join(spec.choices)}"
            )
        return value
    if kind == "range":
        return _interval(value, spec, where)
    if kind == "per_class":
        return _per_class(value, spec, where)
    if kind == "names":
        return _names(value, spec, where)
    if kind == "ints":
        if not isinstance(value, list | tuple):
            raise ConfigError(f"config key {where!r} must be a list of integers")
        return [_number(v, spec, f"{where}[{i}]", integer=True) for i, v in enumerate(value)]
    if kind == "grids":
        return _grids(value, where)
    raise AssertionError(f"unknown spec kind {kind}")


def _number(value: Any, spec: _Spec, where: str, integer: bool) -> int | float:
    ok_types = (int,) if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, ok_types):
        if integer and isinstance(value, float) and value.is_integer():
            value = int(value)
        else:
            wanted = "an integer" if integer else "a number"
            raise ConfigError(f"config key {where!r} must be {wanted}, got {shown(value)}")
    # Integers compare exactly with the bounds (float() of a huge one would overflow).
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(f"config key {where!r} must be finite, got {value}")
    too_low = spec.low is not None and (value <= spec.low if spec.low_open else value < spec.low)
    too_high = spec.high is not None and (
        value >= spec.high if spec.high_open else value > spec.high
    )
    if too_low or too_high:
        raise ConfigError(
            f"config key {where!r} = {shown(value)} is out of range; allowed range: "
            f"{spec.describe_range()}"
        )
    return int(value) if integer else float(value)


def _interval(value: Any, spec: _Spec, where: str) -> list[float]:
    if not isinstance(value, list | tuple) or len(value) != 2:
        raise ConfigError(f"config key {where!r} must be a pair [low, high], got {shown(value)}")
    low, high = (_number(v, spec, f"{where}[{i}]", integer=False) for i, v in enumerate(value))
    if spec.strict and low >= high:
        raise ConfigError(f"config key {where!r} = [{low}, {high}]: low must be below high")
    if low > high:
        raise ConfigError(f"config key {where!r} = [{low}, {high}]: low must not exceed high")
    return [low, high]


def _per_class(value: Any, spec: _Spec, where: str) -> dict[str, int]:
    if spec.scalar_ok and isinstance(value, int | float) and not isinstance(value, bool):
        return {"default": _number(value, spec, where, integer=True)}
    if not isinstance(value, Mapping):
        hint = "a number or " if spec.scalar_ok else ""
        raise ConfigError(
            f"config key {where!r} must be {hint}a mapping of class name to integer, "
            f"got {shown(value)}"
        )
    out = {}
    for name, count in value.items():
        if not isinstance(name, str) or not name:
            raise ConfigError(f"config key {where!r}: class names must be strings, got {name!r}")
        out[name] = _number(count, spec, f"{where}.{name}", integer=True)
    return out


def _names(value: Any, spec: _Spec, where: str) -> list[str]:
    if isinstance(value, str) or not isinstance(value, list | tuple):
        raise ConfigError(f"config key {where!r} must be a list of names, got {shown(value)}")
    if spec.nonempty and not value:
        raise ConfigError(f"config key {where!r} must name at least one class")
    seen: set[str] = set()
    for i, name in enumerate(value):
        if not isinstance(name, str) or not name:
            raise ConfigError(
                f"config key {f'{where}[{i}]'!r} must be a non-empty string, got {shown(name)}"
            )
        if spec.choices and name not in spec.choices:
            raise ConfigError(
                f"config key {f'{where}[{i}]'!r} = {name!r} is not allowed; "
                f"choose from: {', '.join(spec.choices)}"
            )
        if name in seen:
            raise ConfigError(f"config key {f'{where}[{i}]'!r} = {name!r} is listed twice")
        seen.add(name)
    return list(value)


def _grids(value: Any, where: str) -> dict[str, list[int]]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"config key {where!r} must map class names to [nx, ny, nz]")
    out = {}
    cell_spec = _Spec("int", low=1, high=100)
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


def _check_classes(config: AugmentConfig) -> None:
    """Every class name in a per-class key of ``config`` is one of its ``known_classes``.

    Runs on the whole tree once it is merged, so ``known_classes`` may come anywhere in a file.
    ``default`` is allowed where it is a fallback (minimum points, grids), not in object counts.
    """
    known = config.known_classes
    if "default" in known:
        raise ConfigError(
            "config key 'known_classes' lists 'default', which is not a class name "
            "(it is the fallback entry of the per-class maps)"
        )
    for where, spec, value, default in _class_keys(config, AugmentConfig(), ""):
        fallback = spec.scalar_ok or spec.kind == "grids"
        if spec.kind == "names":
            labelled = [(f"{where}[{i}]", name) for i, name in enumerate(value)]
        else:
            labelled = [(f"{where}.{name}", name) for name in value]
        for key, name in labelled:
            if name in known or (fallback and name == "default"):
                continue
            close = difflib.get_close_matches(name, known, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            allowed = ", ".join(sorted(known)) + (", default" if fallback else "")
            if value == default:
                what, advice = " (a default value)", f"set {where} for your classes"
            else:
                what, advice = "", "list a data set's own classes in the top-level known_classes"
            raise ConfigError(
                f"config key {key!r}{what}: unknown class {name!r}{hint}; "
                f"known classes: {allowed}; {advice}"
            )


def _class_keys(config: Any, default: Any, path: str) -> Iterator[tuple[str, _Spec, Any, Any]]:
    """``(key path, spec, value, default value)`` of every class-keyed field of ``config``."""
    for f in dataclasses.fields(config):
        where = f"{path}.{f.name}" if path else f.name
        spec: _Spec = f.metadata["spec"]
        value, default_value = getattr(config, f.name), getattr(default, f.name)
        if spec.kind == "section":
            yield from _class_keys(value, default_value, where)
        elif spec.classes:
            yield where, spec, value, default_value


def per_class(values: Mapping[str, int], name: str, fallback: int = 0) -> int:
    """The value of class ``name`` in a per-class mapping (its ``default`` key, else fallback)."""
    return int(values.get(name, values.get("default", fallback)))


class _ConfigLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # libyaml when built
    """PyYAML's safe loader, refusing a key given twice in one mapping (the last would win
    silently) and reading ``5e4`` as a number (YAML 1.1 reads it as a string; 1.2 as a float)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        first_line: dict[Any, int] = {}
        for key_node, _ in node.value:
            # Merge keys (<<) are exempt: the keys written next to one are meant to override it.
            if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == _MERGE_TAG:
                continue
            key = self.construct_object(key_node)
            line = key_node.start_mark.line + 1
            if key in first_line:
                raise _DuplicateKey(
                    f"{line}: duplicate key {key!r} (first on line {first_line[key]})"
                )
            first_line[key] = line
        return super().construct_mapping(node, deep=deep)


class _DuplicateKey(Exception):
    """A key repeated in one YAML mapping (the message starts with its line)."""


_MERGE_TAG = "tag:yaml.org,2002:merge"
_ConfigLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config file ({exc.strerror or exc})") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{path}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}); "
            "save the config file as UTF-8"
        ) from None
    try:
        data = yaml.load(text, Loader=_ConfigLoader)  # a SafeLoader subclass: no arbitrary objects
    except _DuplicateKey as exc:
        raise ConfigError(f"{path}:{exc}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from exc
    except RecursionError:
        raise ConfigError(f"{path}: not a config file (YAML nested too deeply)") from None
    except Exception as exc:
        # PyYAML's scalar constructors raise plain ValueError, KeyError, AttributeError ... on
        # values they cannot convert (!!int abc, 2001-13-45, !!bool maybe, a 5000-digit int).
        raise ConfigError(f"{path}: not valid YAML (unreadable value: {exc!r})") from exc
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config file must hold a mapping at the top level")
    return data


def preset_path(name: str) -> Path:
    """Path of a packaged config file (``default`` or a detector preset name)."""
    if name != "default" and name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; choose one of: default, {', '.join(PRESETS)}")
    return Path(str(resources.files("drcpo") / "configs" / f"{name}.yaml"))


def load_config(source: str | os.PathLike | Mapping[str, Any] | AugmentConfig | None = None):
    """Read and validate a configuration.

    Args:
        source: ``None`` (the paper defaults), a mapping, a YAML file path, or the name of a
            packaged preset (``default``, ``second``, ``pointrcnn``, ``pv_rcnn``,
            ``pv_rcnn_plusplus``) when no file of that name exists.

    The keys given are applied on top of the defaults; a ``preset`` key first applies that
    detector preset. Raises :class:`ConfigError` naming the file and key on any bad value.
    """
    if isinstance(source, AugmentConfig):
        _build(source.to_dict())  # one built in code is checked as a file would be
        return source
    if source is None:
        return AugmentConfig()
    origin = ""
    if isinstance(source, Mapping):
        data = dict(source)
    elif isinstance(source, str | os.PathLike):
        path = _config_path(source)
        data, origin = _read_yaml(path), str(path)
    else:
        raise ConfigError(
            f"a config must be a mapping, a YAML file path or a preset name, got {shown(source)}"
        )
    try:
        return _build(data)
    except ConfigError as exc:
        raise ConfigError(f"{origin}: {exc}" if origin else str(exc)) from None


def _config_path(source: str | os.PathLike) -> Path:
    """The YAML file ``source`` names: itself, else the packaged preset of that name."""
    path = Path(source)
    try:
        if not path.exists() and str(source) in ("default", *PRESETS):
            path = preset_path(str(source))
        found = path.is_file()
    except (OSError, ValueError) as exc:  # e.g. a name too long, a NUL byte
        raise ConfigError(f"{shown(str(source))}: not a usable config file path ({exc})") from None
    if not found:
        raise ConfigError(
            f"{path}: config file not found (or give a preset: default, {', '.join(PRESETS)})"
        )
    return path


def _build(data: dict[str, Any]) -> AugmentConfig:
    base = AugmentConfig()
    preset = data.get("preset")
    if preset is not None:
        spec = {f.name: f for f in dataclasses.fields(AugmentConfig)}["preset"].metadata["spec"]
        _check(preset, spec, "preset")
        preset_data = _read_yaml(preset_path(preset))
        preset_data.pop("preset", None)
        base = _merge(base, preset_data, "")
    config = _merge(base, data, "")
    _check_classes(config)
    return config
