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

Detector presets (``second``, ``pointrcnn``, ``pv_rcnn``, ``pv_rcnn_plusplus``) set the e-HPR
viewpoint height and radius of the paper's reference configuration for each detector; like the
pipeline presets they are YAML files in ``drcpo/configs/`` next to ``default.yaml`` (the paper
defaults, spelled out), and nowhere else.

Each stage's section is defined once, in the stage's module, and composed here:
``drcpo.construction`` is :class:`drcpo.construction.ConstructionConfig`, ``drcpo.placement``
:class:`drcpo.placement.PlacementConfig`, ``index`` :class:`drcpo.index.IndexConfig` (how
``drcpo index --config`` builds the candidate index; its partition grids and mirrored classes are
construction's, so an index built from a config always matches it). All share one validation
mechanism, :mod:`drcpo.config_fields`.
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

from drcpo.config_fields import (
    SECTION,
    Checked,
    Spec,
    check,
    from_dict,
    key_fields,
    merge,
    spec,
    to_dict,
)
from drcpo.construction import ConstructionConfig
from drcpo.errors import ConfigError, shown
from drcpo.index import IndexConfig
from drcpo.placement import PlacementConfig

__all__ = [
    "KITTI_CLASSES",
    "PIPELINES",
    "PIPELINE_PRESETS",
    "PRESETS",
    "AugmentConfig",
    "ConstructionConfig",
    "DRCPOConfig",
    "ExternalOcclusionConfig",
    "FlipConfig",
    "GTSamplingConfig",
    "GlobalAugmentationConfig",
    "IndexConfig",
    "PlacementConfig",
    "RotationConfig",
    "ScalingConfig",
    "SelfOcclusionConfig",
    "from_dict",
    "load_config",
    "per_class",
    "preset_path",
    "to_dict",
]


#: Whole-pipeline presets (config files in drcpo/configs): ``paper`` is the method as
#: published (today's defaults), ``nuscenes`` sets nuScenes' ten classes, their mirroring and
#: sample counts and the full circle around the sensor.
PIPELINE_PRESETS: tuple[str, ...] = ("default", "paper", "nuscenes")
#: Detector presets shipped with the package (``drcpo/configs/<name>.yaml``: their e-HPR
#: radius and viewpoint height; the paper defaults are ``pv_rcnn_plusplus``'s).
PRESETS: tuple[str, ...] = ("second", "pointrcnn", "pv_rcnn", "pv_rcnn_plusplus")
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
# The configuration tree (paper defaults)
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class FlipConfig(Checked):
    """Random flip: with ``probability`` per axis listed (``x``: y -> -y; ``y``: x -> -x)."""

    KEY_PATH = "global_augmentation.flip"

    probability: float = field(
        default=0.5, metadata=spec("float", "chance of each flip", low=0.0, high=1.0)
    )
    axes: list[str] = field(
        default_factory=lambda: ["x"],
        metadata=spec("names", "axes to flip along", choices=("x", "y")),
    )


@dataclass(frozen=True, eq=False)
class RotationConfig(Checked):
    """Random rotation about z, angle uniform in ``range`` (radians)."""

    KEY_PATH = "global_augmentation.rotation"

    range: list[float] = field(
        default_factory=lambda: [-math.pi / 4, math.pi / 4],
        metadata=spec("range", "angle interval", low=-2 * math.pi, high=2 * math.pi),
    )


@dataclass(frozen=True, eq=False)
class ScalingConfig(Checked):
    """Random uniform scaling of the scene, factor uniform in ``range``."""

    KEY_PATH = "global_augmentation.scaling"

    range: list[float] = field(
        default_factory=lambda: [0.95, 1.05],
        metadata=spec("range", "factor interval", low=0.0, low_open=True, high=10.0),
    )


@dataclass(frozen=True, eq=False)
class GlobalAugmentationConfig(Checked):
    """Global augmentation (flip, rotation, scaling), applied last, as OpenPCDet does."""

    KEY_PATH = "global_augmentation"

    enabled: bool = field(default=True, metadata=spec("bool"))
    flip: FlipConfig = field(default_factory=FlipConfig, metadata=SECTION)
    rotation: RotationConfig = field(default_factory=RotationConfig, metadata=SECTION)
    scaling: ScalingConfig = field(default_factory=ScalingConfig, metadata=SECTION)


@dataclass(frozen=True, eq=False)
class GTSamplingConfig(Checked):
    """Ground-truth sampling with OpenPCDet's semantics (the conventional baseline)."""

    KEY_PATH = "gt_sampling"

    enabled: bool = field(default=True, metadata=spec("bool"))
    targets: dict[str, int] = field(
        default_factory=lambda: {"Car": 20, "Pedestrian": 15, "Cyclist": 15},
        metadata=spec(
            "per_class",
            "objects per class after sampling (existing ones count)",
            low=0,
            high=1000,
            classes=True,
        ),
    )
    min_points: dict[str, int] = field(
        default_factory=lambda: {"default": 5},
        metadata=spec(
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
        metadata=spec(
            "ints",
            "difficulty codes never sampled (OpenPCDet filter_by_difficulty)",
            low=-1,
            high=2,
        ),
    )
    use_road_plane: bool = field(
        default=True, metadata=spec("bool", "put boxes on the KITTI road plane when present")
    )


@dataclass(frozen=True, eq=False)
class SelfOcclusionConfig(Checked):
    """s-HPR on each placed object, viewpoint at the sensor."""

    KEY_PATH = "drcpo.self_occlusion"

    enabled: bool = field(default=True, metadata=spec("bool"))
    radius_factor: float = field(
        default=200.0,
        metadata=spec("float", "R = box diagonal x this", low=0.0, low_open=True, high=1e9),
    )
    min_points: int = field(
        default=5, metadata=spec("int", "fewest points an object keeps", low=0, high=1_000_000)
    )


@dataclass(frozen=True, eq=False)
class ExternalOcclusionConfig(Checked):
    """e-HPR on the frame after insertion, scoped to the inserted objects (see
    :class:`drcpo.transforms.drcpo.DRCPO`)."""

    KEY_PATH = "drcpo.external_occlusion"

    enabled: bool = field(default=True, metadata=spec("bool"))
    radius: float = field(
        default=100000.0,
        metadata=spec(
            "float",
            "HPR radius R, metres (a detector preset sets the paper's: PV-RCNN++'s by default)",
            low=0.0,
            low_open=True,
            high=MAX_RADIUS,
        ),
    )
    viewpoint_z: float = field(
        default=0.0,
        metadata=spec(
            "float", "viewpoint height above the LiDAR origin, metres", low=-100.0, high=100.0
        ),
    )


@dataclass(frozen=True, eq=False)
class DRCPOConfig(Checked):
    """DR.CPO: sample, construct, place, s-HPR, insert, e-HPR, filter labels."""

    KEY_PATH = "drcpo"

    enabled: bool = field(default=True, metadata=spec("bool"))
    sample: dict[str, int] = field(
        default_factory=lambda: {"Car": 10, "Pedestrian": 10, "Cyclist": 10},
        metadata=spec(
            "per_class",
            "objects tried per frame",
            low=0,
            high=1000,
            classes=True,
        ),
    )
    min_points: dict[str, int] = field(
        default_factory=lambda: {"default": 5},
        metadata=spec(
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
        metadata=spec("ints", "difficulty codes never sampled", low=-1, high=2),
    )
    min_points_after: int = field(
        default=5,
        metadata=spec(
            "int", "a box with fewer points after e-HPR is dropped", low=0, high=1_000_000
        ),
    )
    construction: ConstructionConfig = field(default_factory=ConstructionConfig, metadata=SECTION)
    placement: PlacementConfig = field(default_factory=PlacementConfig, metadata=SECTION)
    self_occlusion: SelfOcclusionConfig = field(
        default_factory=SelfOcclusionConfig, metadata=SECTION
    )
    external_occlusion: ExternalOcclusionConfig = field(
        default_factory=ExternalOcclusionConfig, metadata=SECTION
    )


@dataclass(frozen=True, eq=False)
class AugmentConfig(Checked):
    """The whole augmentation: which pipeline and each stage's settings."""

    pipeline: str = field(
        default="drcpo",
        metadata=spec("choice", "drcpo or the conventional baseline (cda)", choices=PIPELINES),
    )
    preset: str | None = field(
        default=None,
        metadata=spec(
            "choice", "detector preset applied before these keys", choices=PRESETS, optional=True
        ),
    )
    known_classes: list[str] = field(
        default_factory=lambda: list(KITTI_CLASSES),
        metadata=spec("names", "class names the per-class keys may use", nonempty=True),
    )
    gt_sampling: GTSamplingConfig = field(default_factory=GTSamplingConfig, metadata=SECTION)
    drcpo: DRCPOConfig = field(default_factory=DRCPOConfig, metadata=SECTION)
    global_augmentation: GlobalAugmentationConfig = field(
        default_factory=GlobalAugmentationConfig, metadata=SECTION
    )
    index: IndexConfig = field(default_factory=IndexConfig, metadata=SECTION)

    def __post_init__(self) -> None:
        super().__post_init__()
        # The index partitions and mirrors as construction does: one source for both.
        built = self.drcpo.construction
        if (self.index.grids, self.index.mirror) != (built.grids, built.mirror):
            index = dataclasses.replace(self.index, grids=built.grids, mirror=built.mirror)
            object.__setattr__(self, "index", index)

    def to_dict(self) -> dict[str, Any]:
        """Every key as plain YAML/JSON types; :func:`load_config` reads it back unchanged."""
        return to_dict(self)

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)


# --------------------------------------------------------------------------------------------
# Reading, validating, writing
# --------------------------------------------------------------------------------------------
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
    for where, field_spec, value, default in _class_keys(config, AugmentConfig(), ""):
        fallback = field_spec.scalar_ok or field_spec.kind == "grids"
        if field_spec.kind == "names":
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


def _class_keys(config: Any, default: Any, path: str) -> Iterator[tuple[str, Spec, Any, Any]]:
    """``(key path, spec, value, default value)`` of every class-keyed key of ``config`` that
    is set (not null)."""
    for f in key_fields(config):
        where = f"{path}.{f.name}" if path else f.name
        field_spec: Spec = f.metadata["spec"]
        value, default_value = getattr(config, f.name), getattr(default, f.name)
        if field_spec.kind == "section":
            yield from _class_keys(value, default_value, where)
        elif field_spec.classes and value is not None:
            yield where, field_spec, value, default_value


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
    """Path of a packaged config file (a pipeline or a detector preset's name)."""
    if name not in PIPELINE_PRESETS and name not in PRESETS:
        names = ", ".join((*PIPELINE_PRESETS, *PRESETS))
        raise ConfigError(f"unknown preset {name!r}; choose one of: {names}")
    return Path(str(resources.files("drcpo") / "configs" / f"{name}.yaml"))


def load_config(source: str | os.PathLike | Mapping[str, Any] | AugmentConfig | None = None):
    """Read and validate a configuration.

    Args:
        source: ``None`` (the paper defaults), a mapping, a YAML file path, or the name of a
            packaged preset when no file of that name exists: a pipeline preset
            (:data:`PIPELINE_PRESETS`: ``default``, ``paper``, ``nuscenes``) or a
            detector preset (``second``, ``pointrcnn``, ``pv_rcnn``, ``pv_rcnn_plusplus``).

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
        if not path.exists() and str(source) in (*PIPELINE_PRESETS, *PRESETS):
            path = preset_path(str(source))
        found = path.is_file()
    except (OSError, ValueError) as exc:  # e.g. a name too long, a NUL byte
        raise ConfigError(f"{shown(str(source))}: not a usable config file path ({exc})") from None
    if not found:
        raise ConfigError(
            f"{path}: config file not found (or give a preset: "
            f"{', '.join((*PIPELINE_PRESETS, *PRESETS))})"
        )
    return path


def _build(data: dict[str, Any]) -> AugmentConfig:
    base = AugmentConfig()
    preset = data.get("preset")
    if preset is not None:
        preset_spec = AugmentConfig.__dataclass_fields__["preset"].metadata["spec"]
        check(preset, preset_spec, "preset")
        preset_data = _read_yaml(preset_path(preset))
        preset_data.pop("preset", None)
        base = merge(base, preset_data, "")
    config = merge(base, data, "")
    _check_classes(config)
    return config
