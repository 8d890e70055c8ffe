"""The detection benchmark's arms: what augmentation each trains with.

An arm is ``NAME`` or ``NAME:KEY=VALUE,KEY=VALUE...`` (:func:`parse_arm`): a built-in arm
(:data:`BUILT_IN`), a drcpo preset or a YAML config path, with config keys overridden, so an
ablation is one command line. :func:`make_augment` builds its augmentation callable.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from typing import Any

import numpy as np
import yaml

from drcpo.frame import Frame
from drcpo.transforms.base import Stats, Transform

#: The built-in arms; any other name is a DR.CPO configuration (see :func:`parse_arm`).
BUILT_IN = {
    "none": "no augmentation",
    "cda": "ground-truth sampling and global flip, rotation, scaling (the conventional baseline)",
    "paper": "DR.CPO as the paper configures it (drcpo's default config) on top of cda",
    "broken": "negative control: cda with every inserted label moved 0.5 m along its heading",
}
BROKEN_SHIFT_M = 0.5


@dataclass(frozen=True)
class Arm:
    """One augmentation arm: the spec as given, its pipeline kind (``none``, ``cda``,
    ``broken`` or ``drcpo``) and the full config (``None`` for ``none``)."""

    spec: str
    kind: str
    config: dict[str, Any] | None

    @property
    def slug(self) -> str:
        """A file name for the arm: the spec's letters, and a hash when it has overrides."""
        plain = re.sub(r"[^A-Za-z0-9_.-]+", "_", self.spec)[:40]
        if plain == self.spec:
            return plain
        return f"{plain}_{hashlib.sha1(self.spec.encode()).hexdigest()[:8]}"


def parse_arm(spec: str) -> Arm:
    """An arm from ``NAME`` or ``NAME:KEY=VALUE,KEY=VALUE...``.

    ``NAME`` is a built-in arm (:data:`BUILT_IN`), a drcpo preset or a YAML config path (DR.CPO
    with that config). Overrides set config keys by their dotted path (a path that does not
    start at the config's top, such as ``placement.location``, is taken inside ``drcpo``);
    values are YAML (``false``, ``12``, ``[0.5, 1.0]``). The result is validated as a config
    file would be. Raises :class:`~drcpo.errors.ConfigError` naming the arm and the bad key.
    """
    from drcpo.config import load_config
    from drcpo.errors import ConfigError

    base, _, rest = spec.partition(":")
    if not base or (":" in spec and not rest):
        raise ConfigError(f"arm {spec!r}: expected NAME or NAME:KEY=VALUE,...")
    if base == "none":
        if rest:
            raise ConfigError(f"arm {spec!r}: 'none' takes no overrides")
        return Arm(spec, "none", None)
    kind = base if base in ("cda", "broken") else "drcpo"
    source = "default" if base in BUILT_IN else base
    try:
        config = load_config(source).to_dict()
        for item in rest.split(",") if rest else []:
            key, equals, text = item.partition("=")
            if not equals or not key.strip():
                raise ConfigError(f"override {item!r} is not KEY=VALUE")
            _set(config, key.strip(), yaml.safe_load(text))
        config = load_config(config).to_dict()
    except (ConfigError, yaml.YAMLError) as exc:
        raise ConfigError(f"arm {spec!r}: {exc}") from None
    return Arm(spec, kind, config)


def _set(config: dict[str, Any], key: str, value: Any) -> None:
    from drcpo.errors import ConfigError

    path = key.split(".")
    if path[0] not in config:
        path = ["drcpo", *path]
    node = config
    for part in path[:-1]:
        if not isinstance(node.get(part), dict):
            raise ConfigError(f"unknown key {key!r} ({'.'.join(path)} is not a section)")
        node = node[part]
    if path[-1] not in node and not _open_mapping(path):
        known = ", ".join(sorted(node))
        raise ConfigError(f"unknown key {key!r} (known in {'.'.join(path[:-1])}: {known})")
    node[path[-1]] = value


def _open_mapping(path: list[str]) -> bool:
    """Whether the last key of ``path`` may be new: a class in a per-class mapping."""
    return len(path) >= 2 and path[-2] in ("sample_groups", "min_points", "max_counts", "grids")


class ShiftInsertedLabels(Transform):
    """Negative control: the wrapped transform's inserted objects keep their points but their
    labels move ``shift`` metres along the heading, as a careless inserter would misplace them."""

    name = "broken"

    def __init__(self, inner: Transform, shift: float) -> None:
        self.inner, self.shift = inner, shift

    def apply(self, frame: Frame, rng: np.random.Generator, stats: Stats) -> Frame:
        before = len(frame.boxes)
        frame = self.inner.apply(frame, rng, stats)
        boxes = frame.boxes.copy()
        heading = boxes[before:, 6]
        boxes[before:, 0] += self.shift * np.cos(heading)
        boxes[before:, 1] += self.shift * np.sin(heading)
        return frame.replace(boxes=boxes)

    def to_config(self) -> dict[str, Any]:
        return {"type": "ShiftInsertedLabels", "shift": self.shift}


def make_augment(arm: Arm, db: str | None):
    """The augmentation callable of an arm (``None`` for ``none``)."""
    if arm.kind == "none":
        return None
    from drcpo.database import GroundTruthDatabase
    from drcpo.pipeline import build_pipeline
    from drcpo.transforms import Compose

    database = GroundTruthDatabase.open(db)
    pipeline = build_pipeline(arm.config, database, kind="drcpo" if arm.kind == "drcpo" else "cda")
    if arm.kind != "broken":
        return pipeline
    sampling, *rest = pipeline.transforms
    return Compose([ShiftInsertedLabels(sampling, BROKEN_SHIFT_M), *rest])
