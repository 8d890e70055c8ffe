"""The transform contract: :class:`Transform` (``transform(frame, rng) -> frame``),
:class:`Compose`, per-frame :class:`Stats` and the registry that rebuilds transforms from their
configs.

Every transform is a small object with a plain ``__call__(data, rng)``. ``data`` is a
:class:`~drcpo.frame.Frame` or an OpenPCDet-style data dict (``points``, ``gt_boxes``,
``gt_names``; other keys pass through) and the result is of the same kind. Randomness comes only
from the ``rng`` argument (a :class:`numpy.random.Generator`), so the same seed gives the same
output, and transforms hold no mutable state, so they are safe in forked worker processes (as
PyTorch's DataLoader uses them). Inputs are never modified.

Each call records per-frame statistics (objects tried, rejected by reason and added per class;
construction iterations; points before and after each stage; milliseconds per stage) in the
returned frame's ``metadata["augment_stats"]`` (in the dict form: the ``augment_stats`` key), as
plain JSON types; see :class:`Stats`.

Each transform keeps its parameters in a frozen config (:mod:`drcpo.config`), exposed by
``to_config()``; ``from_config(...)`` rebuilds an equal transform.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import Any

import numpy as np

from drcpo.config import to_dict
from drcpo.database import GroundTruthDatabase
from drcpo.errors import ConfigError
from drcpo.frame import DICT_FIELDS, FRAME_FIELDS, Frame, validate_frame

__all__ = [
    "DRAW_KEYS",
    "STATS_KEY",
    "TRANSFORMS",
    "Compose",
    "FrameLike",
    "Stats",
    "Transform",
    "as_frame",
    "config_body",
    "register",
    "transform_from_config",
    "without_timings",
]

FrameLike = Frame | dict[str, Any]
STATS_KEY = "augment_stats"
#: Keys of a global stage's statistics that hold its random draws (lists, one entry per run).
DRAW_KEYS = ("flipped", "angle", "scale")


# --------------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------------
class Stats:
    """Per-frame statistics of one augmentation call, as a plain JSON-able dict.

    Layout of :meth:`to_dict`::

        {"stages": {name: {"ms": float, "points_in": int, "points_out": int}},
         "objects": {transform: {class: {"tried": n, "added": n, "rejected": {reason: n}}}},
         "construction_iterations": {class: [iterations of each constructed object]},
         "labels_dropped": {class: original boxes dropped for losing their points}}

    The global stages also record what they drew, as lists with one entry per run of the stage
    (:data:`DRAW_KEYS`): ``global_flip`` ``"flipped"`` (per run, the axes flipped),
    ``global_rotation`` ``"angle"`` (radians) and ``global_scaling`` ``"scale"``, so that a caller
    can tell how the frame moved (OpenPCDet's ``flip_x``, ``noise_rot``, ``noise_scale``).

    A stage recorded twice (e.g. two rotations in one pipeline) adds up its milliseconds, keeps
    the first ``points_in`` and the last ``points_out`` and appends its draws. A new
    :class:`Stats` starts from the statistics already attached to the input frame, so a
    pipeline's stages accumulate.
    """

    def __init__(self, existing: Mapping[str, Any] | None = None) -> None:
        data = copy.deepcopy(dict(existing)) if existing else {}
        self.stages: dict[str, dict[str, Any]] = data.get("stages", {})
        self.objects: dict[str, dict[str, dict[str, Any]]] = data.get("objects", {})
        self.iterations: dict[str, list[int]] = data.get("construction_iterations", {})
        self.dropped: dict[str, int] = data.get("labels_dropped", {})

    @classmethod
    def of(cls, frame: Frame) -> Stats:
        return cls(frame.metadata.get(STATS_KEY))

    @contextmanager
    def stage(self, name: str, points_in: int) -> Iterator[dict[str, Any]]:
        """Time a stage; set ``record["points_out"]`` inside the block (default: unchanged)."""
        record: dict[str, Any] = {"ms": 0.0, "points_in": int(points_in), "points_out": None}
        start = time.perf_counter()
        try:
            yield record
        finally:
            record["ms"] = (time.perf_counter() - start) * 1000.0
            if record["points_out"] is None:
                record["points_out"] = record["points_in"]
            record["points_out"] = int(record["points_out"])
            previous = self.stages.get(name)
            if previous is None:
                self.stages[name] = record
            else:
                previous["ms"] += record["ms"]
                previous["points_out"] = record["points_out"]
                for key in DRAW_KEYS:  # a stage run twice keeps each run's draw, in order
                    if key in record:
                        previous[key] = previous.get(key, []) + record[key]

    def _object_entry(self, transform: str, name: str) -> dict[str, Any]:
        per_transform = self.objects.setdefault(transform, {})
        return per_transform.setdefault(str(name), {"tried": 0, "added": 0, "rejected": {}})

    def tried(self, transform: str, name: str, count: int = 1) -> None:
        self._object_entry(transform, name)["tried"] += int(count)

    def added(self, transform: str, name: str, count: int = 1) -> None:
        self._object_entry(transform, name)["added"] += int(count)

    def rejected(self, transform: str, name: str, reason: str, count: int = 1) -> None:
        if count:
            reasons = self._object_entry(transform, name)["rejected"]
            reasons[reason] = reasons.get(reason, 0) + int(count)

    def construction(self, name: str, iterations: int) -> None:
        self.iterations.setdefault(str(name), []).append(int(iterations))

    def label_dropped(self, name: str, count: int = 1) -> None:
        self.dropped[str(name)] = self.dropped.get(str(name), 0) + int(count)

    def to_dict(self) -> dict[str, Any]:
        return {
            "stages": self.stages,
            "objects": self.objects,
            "construction_iterations": self.iterations,
            "labels_dropped": self.dropped,
        }

    def attach(self, frame: Frame) -> Frame:
        """``frame`` with these statistics in a new metadata dict (the old one is untouched)."""
        return frame.replace(metadata={**frame.metadata, STATS_KEY: self.to_dict()})


# --------------------------------------------------------------------------------------------
# Base class and composition
# --------------------------------------------------------------------------------------------
def as_frame(data: FrameLike) -> tuple[Frame, bool]:
    """``(frame, was_dict)`` for a :class:`Frame` or an OpenPCDet-style data dict."""
    if isinstance(data, Frame):
        return data, False
    if isinstance(data, Mapping):
        return Frame.from_dict(dict(data)), True
    raise TypeError(f"expected a Frame or an OpenPCDet data dict, got {type(data).__name__}")


def _source(frame: Frame) -> str:
    """How error messages name a frame: its id when it has one."""
    frame_id = frame.metadata.get("frame_id")
    return "frame" if frame_id is None else f"frame {frame_id}"


def _check_rng(rng: Any) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise TypeError(
            "transforms take an explicit numpy.random.Generator (np.random.default_rng(seed)), "
            f"got {type(rng).__name__}"
        )
    return rng


class Transform:
    """Base class: dict/Frame handling, statistics, config round trip and ``repr``.

    Subclasses implement :meth:`apply` on a :class:`Frame` and set ``config`` (a frozen config
    dataclass) and ``name`` (the key of their statistics).
    """

    name = "transform"
    config: Any

    def __call__(self, data: FrameLike, rng: np.random.Generator) -> FrameLike:
        """Augment one frame (a :class:`Frame` or an OpenPCDet data dict, not modified).

        Raises :class:`DataError` naming the field and the first bad row on invalid input
        (:func:`drcpo.frame.validate_frame`: NaN/inf values, non-positive box sizes, bad
        shapes, dtypes or names), before any work.
        """
        frame, was_dict = as_frame(data)
        validate_frame(frame, _source(frame), DICT_FIELDS if was_dict else FRAME_FIELDS)
        stats = Stats.of(frame)
        out = stats.attach(self.apply(frame, _check_rng(rng), stats))
        return out.to_dict() if was_dict else out

    def apply(self, frame: Frame, rng: np.random.Generator, stats: Stats) -> Frame:
        raise NotImplementedError

    def to_config(self) -> dict[str, Any]:
        """``{"type": class name, **parameters}`` as plain types."""
        return {"type": type(self).__name__, **to_dict(self.config)}

    def __repr__(self) -> str:
        params = ", ".join(f"{k}={v!r}" for k, v in to_dict(self.config).items())
        return f"{type(self).__name__}({params})"

    def __eq__(self, other: object) -> bool:
        return type(self) is type(other) and self.to_config() == other.to_config()

    __hash__ = None  # type: ignore[assignment]


class Compose(Transform):
    """Apply transforms in order; the frame is converted to and from a dict only once."""

    name = "compose"

    def __init__(self, transforms: Sequence[Transform]) -> None:
        for t in transforms:
            if not isinstance(t, Transform):
                raise TypeError(f"Compose takes drcpo transforms, got {type(t).__name__}")
        self.transforms: tuple[Transform, ...] = tuple(transforms)

    def apply(self, frame: Frame, rng: np.random.Generator, stats: Stats) -> Frame:
        for transform in self.transforms:
            frame = transform.apply(frame, rng, stats)
        return frame

    def to_config(self) -> dict[str, Any]:
        return {"type": "Compose", "transforms": [t.to_config() for t in self.transforms]}

    @classmethod
    def from_config(
        cls,
        data: Mapping[str, Any],
        database: GroundTruthDatabase | None = None,
        index: Any = None,
    ) -> Compose:
        return cls(
            [transform_from_config(t, database=database, index=index) for t in data["transforms"]]
        )

    def __repr__(self) -> str:
        inner = "".join(f"\n  {t!r}," for t in self.transforms)
        return f"Compose([{inner}\n])"

    def __len__(self) -> int:
        return len(self.transforms)

    def __getitem__(self, i: int) -> Transform:
        return self.transforms[i]


def config_body(data: Mapping[str, Any], cls_name: str) -> dict[str, Any]:
    body = dict(data)
    kind = body.pop("type", cls_name)
    if kind != cls_name:
        raise ConfigError(f"config of type {kind!r} given to {cls_name}.from_config")
    return body


# --------------------------------------------------------------------------------------------
# Building transforms from configs
# --------------------------------------------------------------------------------------------
#: Transform classes by name, as configs name them (filled by :func:`register`).
TRANSFORMS: dict[str, type[Transform]] = {}


def register(cls: type[Transform]) -> type[Transform]:
    """Class decorator: make ``cls`` buildable by :func:`transform_from_config`."""
    TRANSFORMS[cls.__name__] = cls
    return cls


register(Compose)


def transform_from_config(
    data: Mapping[str, Any], database: GroundTruthDatabase | None = None, index: Any = None
) -> Transform:
    """Rebuild a transform from its :meth:`Transform.to_config` dict."""
    kind = data.get("type") if isinstance(data, Mapping) else None
    if kind not in TRANSFORMS:
        raise ConfigError(
            f"transform type {kind!r} is unknown; allowed: {', '.join(sorted(TRANSFORMS))}"
        )
    return TRANSFORMS[kind].from_config(data, database=database, index=index)


def without_timings(stats: Any) -> Any:
    """Statistics (:class:`Stats`' dict form, or any part of it) with every ``"ms"`` key left
    out: what the same seed reproduces, timings differing from run to run."""
    if isinstance(stats, dict):
        return {k: without_timings(v) for k, v in stats.items() if k != "ms"}
    if isinstance(stats, list):
        return [without_timings(v) for v in stats]
    return stats
