"""Augmentation transforms: ``transform(frame, rng) -> frame``.

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
import json
import math
import os
import shutil
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from drcpo.config import (
    FlipConfig,
    GTSamplingConfig,
    RotationConfig,
    ScalingConfig,
    from_dict,
    per_class,
    to_dict,
)
from drcpo.database import GroundTruthDatabase
from drcpo.errors import ConfigError, DataError
from drcpo.frame import Frame
from drcpo.geometry import (
    bev_overlap_area,
    box_corners,
    from_canonical,
    points_in_boxes,
    wrap_angle,
)

FrameLike = Frame | dict[str, Any]
STATS_KEY = "augment_stats"


# --------------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------------
class Stats:
    """Per-frame statistics of one augmentation call, as a plain JSON-able dict.

    Layout of :meth:`to_dict`::

        {"stages": {name: {"ms": float, "points_in": int, "points_out": int}},
         "objects": {transform: {class: {"tried": n, "added": n, "rejected": {reason: n}}}},
         "construction_iterations": {class: [iterations of each constructed object]}}

    A stage recorded twice (e.g. two rotations in one pipeline) adds up its milliseconds and keeps
    the first ``points_in`` and the last ``points_out``. A new :class:`Stats` starts from the
    statistics already attached to the input frame, so a pipeline's stages accumulate.
    """

    def __init__(self, existing: Mapping[str, Any] | None = None) -> None:
        data = copy.deepcopy(dict(existing)) if existing else {}
        self.stages: dict[str, dict[str, Any]] = data.get("stages", {})
        self.objects: dict[str, dict[str, dict[str, Any]]] = data.get("objects", {})
        self.iterations: dict[str, list[int]] = data.get("construction_iterations", {})

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

    def to_dict(self) -> dict[str, Any]:
        return {
            "stages": self.stages,
            "objects": self.objects,
            "construction_iterations": self.iterations,
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
        frame, was_dict = as_frame(data)
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


def _config_body(data: Mapping[str, Any], cls_name: str) -> dict[str, Any]:
    body = dict(data)
    kind = body.pop("type", cls_name)
    if kind != cls_name:
        raise ConfigError(f"config of type {kind!r} given to {cls_name}.from_config")
    return body


# --------------------------------------------------------------------------------------------
# Global augmentation
# --------------------------------------------------------------------------------------------
class GlobalFlip(Transform):
    """Random flip of the whole scene, each listed axis with ``probability`` (OpenPCDet's
    ``random_world_flip``): along ``x`` maps y -> -y and heading -> -heading; along ``y`` maps
    x -> -x and heading -> pi - heading."""

    name = "global_flip"

    def __init__(self, probability: float = 0.5, axes: Sequence[str] = ("x",)) -> None:
        self.config: FlipConfig = from_dict(
            FlipConfig, {"probability": probability, "axes": list(axes)}, "GlobalFlip"
        )

    @classmethod
    def from_config(cls, data: Mapping[str, Any], **_: Any) -> GlobalFlip:
        return cls(**_config_body(data, cls.__name__))

    def apply(self, frame: Frame, rng: np.random.Generator, stats: Stats) -> Frame:
        with stats.stage(self.name, len(frame)):
            points, boxes = frame.points, frame.boxes
            for axis in self.config.axes:
                if rng.random() >= self.config.probability:
                    continue
                column = 1 if axis == "x" else 0
                points = points.copy() if points is frame.points else points
                boxes = boxes.copy() if boxes is frame.boxes else boxes
                points[:, column] = -points[:, column]
                boxes[:, column] = -boxes[:, column]
                boxes[:, 6] = -boxes[:, 6] if axis == "x" else np.pi - boxes[:, 6]
            if boxes is not frame.boxes:
                boxes[:, 6] = wrap_angle(boxes[:, 6])
            return frame.replace(points=points, boxes=boxes)


class GlobalRotation(Transform):
    """Rotate the whole scene about z by an angle uniform in ``range`` (radians)."""

    name = "global_rotation"

    def __init__(self, range: Sequence[float] = (-math.pi / 4, math.pi / 4)) -> None:
        self.config: RotationConfig = from_dict(
            RotationConfig, {"range": list(range)}, "GlobalRotation"
        )

    @classmethod
    def from_config(cls, data: Mapping[str, Any], **_: Any) -> GlobalRotation:
        return cls(**_config_body(data, cls.__name__))

    def apply(self, frame: Frame, rng: np.random.Generator, stats: Stats) -> Frame:
        with stats.stage(self.name, len(frame)):
            low, high = self.config.range
            angle = rng.uniform(low, high)
            cos, sin = math.cos(angle), math.sin(angle)
            points = frame.points.copy()
            x, y = frame.points[:, 0].astype(np.float64), frame.points[:, 1].astype(np.float64)
            points[:, 0] = cos * x - sin * y
            points[:, 1] = sin * x + cos * y
            boxes = frame.boxes.copy()
            bx, by = frame.boxes[:, 0], frame.boxes[:, 1]
            boxes[:, 0] = cos * bx - sin * by
            boxes[:, 1] = sin * bx + cos * by
            boxes[:, 6] = wrap_angle(boxes[:, 6] + angle)
            return frame.replace(points=points, boxes=boxes)


class GlobalScaling(Transform):
    """Scale the whole scene (points and boxes) by a factor uniform in ``range``."""

    name = "global_scaling"

    def __init__(self, range: Sequence[float] = (0.95, 1.05)) -> None:
        self.config: ScalingConfig = from_dict(
            ScalingConfig, {"range": list(range)}, "GlobalScaling"
        )

    @classmethod
    def from_config(cls, data: Mapping[str, Any], **_: Any) -> GlobalScaling:
        return cls(**_config_body(data, cls.__name__))

    def apply(self, frame: Frame, rng: np.random.Generator, stats: Stats) -> Frame:
        with stats.stage(self.name, len(frame)):
            low, high = self.config.range
            scale = rng.uniform(low, high)
            points = frame.points.copy()
            points[:, :3] = frame.points[:, :3].astype(np.float64) * scale
            boxes = frame.boxes.copy()
            boxes[:, :6] *= scale
            return frame.replace(points=points, boxes=boxes)


# --------------------------------------------------------------------------------------------
# Shared helpers for inserting objects
# --------------------------------------------------------------------------------------------
def match_features(points: np.ndarray, dim: int) -> np.ndarray:
    """``float32 (n, dim)``: the first ``dim`` columns of ``points``, zero-padded if it has fewer.

    Database objects carry x, y, z, intensity; a frame may carry other feature columns, which
    inserted points then fill with zeros.
    """
    points = np.asarray(points, dtype=np.float32)
    if points.shape[1] >= dim:
        return points[:, :dim]
    out = np.zeros((len(points), dim), dtype=np.float32)
    out[:, : points.shape[1]] = points
    return out


def road_plane_heights(plane: np.ndarray, calib: Any, xyz: np.ndarray) -> np.ndarray:
    """LiDAR z ``(M,)`` of a KITTI road plane below LiDAR points ``(M, 3)``.

    ``plane`` is ``(a, b, c, d)`` in rectified camera coordinates (``a x + b y + c z + d = 0``,
    y pointing down), as in KITTI's ``planes/*.txt``; ``calib`` a
    :class:`~drcpo.datasets.kitti.Calibration`. Same arithmetic as OpenPCDet's
    ``put_boxes_on_road_planes``: project the point into the camera frame, solve the plane for y
    there, and map the result back to LiDAR.
    """
    a, b, c, d = (float(v) for v in np.asarray(plane, dtype=np.float64).reshape(4))
    if abs(b) < 1e-9:
        raise DataError(f"road plane {plane!r} is vertical (b = 0); cannot put boxes on it")
    rect = np.asarray(calib.lidar_to_rect(np.asarray(xyz, dtype=np.float32)), dtype=np.float32)
    rect[:, 1] = (-d - a * rect[:, 0] - c * rect[:, 2]) / b
    return np.asarray(calib.rect_to_lidar(rect))[:, 2].astype(np.float64)


class BoxQuery:
    """Repeated "which points lie in this box" queries on one point array.

    Holds contiguous float32 copies of the x and y columns so each query first selects the
    points in the box's axis-aligned BEV bounds (a few cheap comparisons) and only tests those
    exactly with :func:`drcpo.geometry.points_in_boxes`, whose boundary rule (closed boxes) it
    keeps. About 30x faster than testing every point against every box for KITTI-size frames.

    Args:
        points: ``(N, 3+)`` points, metres.
    """

    _SLACK = 1e-3  # metres; keeps the float32 pre-filter conservative

    def __init__(self, points: np.ndarray) -> None:
        self.points = points
        self.x = np.ascontiguousarray(points[:, 0])
        self.y = np.ascontiguousarray(points[:, 1])

    def inside(self, box: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Indices ``int64 (k,)`` of the points in one ``(7,)`` box grown by ``margin``."""
        cos, sin = abs(math.cos(box[6])), abs(math.sin(box[6]))
        length, width = box[3] + 2.0 * margin, box[4] + 2.0 * margin
        half_x = (length * cos + width * sin) / 2.0 + self._SLACK
        half_y = (length * sin + width * cos) / 2.0 + self._SLACK
        near = np.flatnonzero(
            (self.x >= box[0] - half_x)
            & (self.x <= box[0] + half_x)
            & (self.y >= box[1] - half_y)
            & (self.y <= box[1] + half_y)
        )
        if len(near) == 0:
            return near
        return near[points_in_boxes(self.points[near], box[None], margin)[:, 0]]

    def inside_any(self, boxes: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """``bool (N,)``: points in at least one of the ``(M, 7)`` boxes."""
        mask = np.zeros(len(self.points), dtype=bool)
        for box in np.asarray(boxes, dtype=np.float64).reshape(-1, 7):
            mask[self.inside(box, margin)] = True
        return mask

    def counts(self, boxes: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """``int64 (M,)``: points in each box."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        return np.array([len(self.inside(box, margin)) for box in boxes], dtype=np.int64)


#: Metadata arrays holding one row per box, kept in step when boxes are added or removed, with
#: the value an added box gets when its source does not provide one.
PER_BOX_METADATA: dict[str, Any] = {
    "gt_boxes_mask": True,  # OpenPCDet
    "difficulty": -1,
    "occlusion": -1,
    "truncation": np.nan,
    "num_points_in_gt": -1,
}
#: Metadata that describes the original boxes as a whole and is dropped once they change.
STALE_WHEN_BOXES_CHANGE = ("labels",)


def update_box_metadata(
    metadata: Mapping[str, Any],
    num_boxes: int,
    keep: np.ndarray | None = None,
    added: int = 0,
    added_values: Mapping[str, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Metadata with its per-box arrays (:data:`PER_BOX_METADATA`) matching new boxes.

    Args:
        metadata: the frame's metadata (not modified).
        num_boxes: boxes before the change.
        keep: indices of the boxes kept, in order (``None``: all).
        added: boxes appended after the kept ones.
        added_values: values of the appended boxes per key (default: the fill value).
    """
    if keep is None and added == 0:
        return dict(metadata)
    out = {k: v for k, v in metadata.items() if k not in STALE_WHEN_BOXES_CHANGE}
    for key, fill in PER_BOX_METADATA.items():
        value = metadata.get(key)
        if value is None or np.ndim(value) != 1 or len(value) != num_boxes:
            continue
        value = np.asarray(value)
        kept = value if keep is None else value[keep]
        extra = (added_values or {}).get(key)
        if extra is None:
            extra = np.full(added, fill)
        out[key] = np.concatenate([kept, np.asarray(extra)]).astype(
            np.result_type(value.dtype, np.asarray(fill).dtype), copy=False
        )
    return out


def _sampling_pools(
    database: GroundTruthDatabase,
    classes: Sequence[str],
    min_points: Mapping[str, int],
    exclude_difficulty: Sequence[int],
) -> dict[str, np.ndarray]:
    """Eligible database rows per class (read-only arrays, shared safely across workers)."""
    pools = {}
    excluded = np.isin(database.difficulty, np.asarray(exclude_difficulty, dtype=np.int8))
    for name in classes:
        rows = database.rows_of_class(name)
        keep = (database.num_points[rows] >= per_class(min_points, name, 5)) & ~excluded[rows]
        pool = rows[keep]
        pool.setflags(write=False)
        pools[name] = pool
    return pools


# --------------------------------------------------------------------------------------------
# Ground-truth sampling (the conventional baseline)
# --------------------------------------------------------------------------------------------
class GroundTruthSampling(Transform):
    """OpenPCDet's ground-truth sampling (``gt_sampling``).

    For each class, in the order of ``targets``: draw ``max(0, target - objects of that class in
    the frame)`` database objects without replacement (only objects with at least
    ``min_points`` points and a difficulty not in ``exclude_difficulty``), at their original
    place and heading. A drawn box whose BEV footprint overlaps an existing box, a box kept
    earlier, or another box drawn in the same round is dropped (as OpenPCDet does, both boxes of
    a colliding drawn pair go). With a KITTI road plane in ``frame.metadata["plane"]`` and a
    calibration in ``metadata["calib"]``, kept boxes are moved vertically so that their bottom
    lies on the plane; otherwise they keep their original height. Frame points inside kept boxes
    are removed and the objects' points appended.

    Args:
        database: the ground-truth database to draw from.
        targets: objects per class after sampling (existing ones count), e.g. ``{"Car": 20}``.
        min_points: fewest points an object must have to be drawn (one number, or per class).
        exclude_difficulty: difficulty codes never drawn (OpenPCDet's ``filter_by_difficulty``).
        use_road_plane: put boxes on the road plane when the frame has one.
    """

    name = "gt_sampling"

    def __init__(
        self,
        database: GroundTruthDatabase,
        targets: Mapping[str, int] | None = None,
        min_points: int | Mapping[str, int] = 5,
        exclude_difficulty: Sequence[int] = (),
        use_road_plane: bool = True,
    ) -> None:
        params: dict[str, Any] = {
            "min_points": min_points if isinstance(min_points, int) else dict(min_points),
            "exclude_difficulty": list(exclude_difficulty),
            "use_road_plane": use_road_plane,
        }
        if targets is not None:
            params["targets"] = dict(targets)
        self.config: GTSamplingConfig = from_dict(GTSamplingConfig, params, "GroundTruthSampling")
        self.database = database
        self._pools = _sampling_pools(
            database,
            list(self.config.targets),
            self.config.min_points,
            self.config.exclude_difficulty,
        )

    @classmethod
    def from_settings(
        cls, config: GTSamplingConfig, database: GroundTruthDatabase
    ) -> GroundTruthSampling:
        return cls(
            database,
            targets=config.targets,
            min_points=config.min_points,
            exclude_difficulty=config.exclude_difficulty,
            use_road_plane=config.use_road_plane,
        )

    @classmethod
    def from_config(
        cls, data: Mapping[str, Any], database: GroundTruthDatabase | None = None, **_: Any
    ) -> GroundTruthSampling:
        if database is None:
            raise ConfigError("GroundTruthSampling.from_config needs database=...")
        body = _config_body(data, cls.__name__)
        body.pop("enabled", None)
        return cls.from_settings(from_dict(GTSamplingConfig, body, "GroundTruthSampling"), database)

    def to_config(self) -> dict[str, Any]:
        body = to_dict(self.config)
        body.pop("enabled")
        return {"type": type(self).__name__, **body}

    def __repr__(self) -> str:
        body = self.to_config()
        body.pop("type")
        params = ", ".join(f"{k}={v!r}" for k, v in body.items())
        return f"GroundTruthSampling({self.database!r}, {params})"

    def apply(self, frame: Frame, rng: np.random.Generator, stats: Stats) -> Frame:
        with stats.stage(self.name, len(frame)) as record:
            rows, boxes = self._draw(frame, rng, stats)
            out = self._insert(frame, rows, boxes)
            record["points_out"] = len(out)
            return out

    def _draw(
        self, frame: Frame, rng: np.random.Generator, stats: Stats
    ) -> tuple[np.ndarray, np.ndarray]:
        """Rows and boxes ``(S, 7)`` of the drawn objects that survive the collision checks."""
        kept_boxes = [frame.boxes]
        kept_rows = []
        for name, target in self.config.targets.items():
            pool = self._pools[name]
            wanted = max(0, int(target) - int(np.count_nonzero(frame.names == name)))
            count = min(wanted, len(pool))
            if count == 0:
                continue
            rows = rng.choice(pool, size=count, replace=False)
            boxes = self.database.boxes[rows]
            stats.tried(self.name, name, count)
            existing = np.concatenate(kept_boxes)
            hits_existing = bev_overlap_area(boxes, existing).max(axis=1, initial=0.0) > 0
            among = bev_overlap_area(boxes)
            np.fill_diagonal(among, 0.0)
            valid = ~hits_existing & ~(among.max(axis=1) > 0)
            stats.rejected(self.name, name, "collision", int(np.count_nonzero(~valid)))
            stats.added(self.name, name, int(np.count_nonzero(valid)))
            kept_boxes.append(boxes[valid])
            kept_rows.append(rows[valid])
        rows = np.concatenate(kept_rows) if kept_rows else np.zeros(0, dtype=np.int64)
        boxes = np.array(self.database.boxes[rows], dtype=np.float64).reshape(-1, 7)
        return rows, boxes

    def _insert(self, frame: Frame, rows: np.ndarray, boxes: np.ndarray) -> Frame:
        if len(rows) == 0:
            return frame
        plane, calib = frame.metadata.get("plane"), frame.metadata.get("calib")
        if self.config.use_road_plane and plane is not None and calib is not None:
            bottoms = boxes[:, 2] - boxes[:, 5] / 2.0
            boxes[:, 2] += road_plane_heights(plane, calib, boxes[:, :3]) - bottoms
        dim = frame.points.shape[1]
        objects = []
        for row, box in zip(rows, boxes, strict=True):
            placed = from_canonical(self.database.object_points(int(row)), box)
            objects.append(match_features(placed, dim))
        keep = ~BoxQuery(frame.points).inside_any(boxes)
        points = np.concatenate([frame.points[keep], *objects])
        names = np.concatenate([frame.names, self.database.names[rows].astype(str)])
        db = self.database
        metadata = update_box_metadata(
            frame.metadata,
            len(frame.boxes),
            added=len(rows),
            added_values={
                "difficulty": db.difficulty[rows],
                "occlusion": db.occlusion[rows],
                "truncation": db.truncation[rows],
                "num_points_in_gt": db.num_points[rows],
            },
        )
        return frame.replace(
            points=points,
            boxes=np.concatenate([frame.boxes, boxes]),
            names=names,
            metadata=metadata,
        )


# --------------------------------------------------------------------------------------------
# Building transforms from configs
# --------------------------------------------------------------------------------------------
TRANSFORMS: dict[str, type[Transform]] = {
    "Compose": Compose,
    "GlobalFlip": GlobalFlip,
    "GlobalRotation": GlobalRotation,
    "GlobalScaling": GlobalScaling,
    "GroundTruthSampling": GroundTruthSampling,
}


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


# --------------------------------------------------------------------------------------------
# Offline generation: augmented frames in KITTI layout
# --------------------------------------------------------------------------------------------
def kitti_label_lines(frame: Frame, image_shape: tuple[int, int] | None = None) -> list[str]:
    """KITTI ``label_2`` lines of a frame's boxes, through its ``metadata["calib"]``.

    Boxes go to the camera frame with :func:`drcpo.datasets.kitti.lidar_boxes_to_camera`;
    ``alpha`` is OpenPCDet's ``-arctan2(-y, x) + ry``; the 2D box is the projection of the
    eight corners clipped to the image. Truncation and occlusion come from the frame's per-box
    metadata when known, else 0.00 and 3 ("unknown", as KITTI defines it).
    """
    from drcpo.datasets.kitti import DEFAULT_IMAGE_SHAPE, lidar_boxes_to_camera

    calib = frame.metadata.get("calib")
    if calib is None:
        raise DataError(f"frame {frame.frame_id!r}: writing KITTI labels needs metadata['calib']")
    if len(frame.boxes) == 0:
        return []
    height, width = image_shape or frame.metadata.get("image_shape") or DEFAULT_IMAGE_SHAPE
    camera = lidar_boxes_to_camera(frame.boxes, calib)
    alpha = wrap_angle(-np.arctan2(-frame.boxes[:, 1], frame.boxes[:, 0]) + camera[:, 6])
    corners = box_corners(frame.boxes).reshape(-1, 3)
    pixels, _ = calib.rect_to_image(calib.lidar_to_rect(corners))
    pixels = pixels.reshape(-1, 8, 2)
    left_top = np.clip(pixels.min(axis=1), 0, [width - 1, height - 1])
    right_bottom = np.clip(pixels.max(axis=1), 0, [width - 1, height - 1])
    count = len(frame.boxes)
    truncation = np.asarray(frame.metadata.get("truncation", np.full(count, np.nan)), float)
    occlusion = np.asarray(frame.metadata.get("occlusion", np.full(count, -1)), float)
    if truncation.shape != (count,):
        truncation = np.full(count, np.nan)
    if occlusion.shape != (count,):
        occlusion = np.full(count, -1.0)
    truncation = np.where(np.isfinite(truncation), np.clip(truncation, 0, 1), 0.0)
    occlusion = np.where((occlusion >= 0) & (occlusion <= 3), occlusion, 3).astype(int)
    lines = []
    for i in range(count):
        x, y, z, length, h, w, ry = camera[i]
        lines.append(
            f"{frame.names[i]} {truncation[i]:.2f} {occlusion[i]:d} {alpha[i]:.2f} "
            f"{left_top[i, 0]:.2f} {left_top[i, 1]:.2f} {right_bottom[i, 0]:.2f} "
            f"{right_bottom[i, 1]:.2f} {h:.2f} {w:.2f} {length:.2f} {x:.2f} {y:.2f} {z:.2f} "
            f"{wrap_angle(ry):.2f}"
        )
    return lines


def frame_seed(seed: int, index: int) -> np.random.Generator:
    """The generator of frame ``index`` of a run seeded with ``seed``: independent per frame and
    independent of the order or the process frames are augmented in."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))


def augment_kitti(
    root: str | os.PathLike,
    split: str,
    transform: Transform,
    out: str | os.PathLike,
    frames: int | None = None,
    seed: int = 0,
    fov_only: bool = True,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Augment frames of a KITTI split and write them in KITTI layout under ``out``.

    Writes ``training/velodyne/*.bin`` (float32, the frame's point columns),
    ``training/label_2/*.txt`` (:func:`kitti_label_lines`), ``training/calib/*.txt`` (copied),
    ``ImageSets/<split>.txt`` and ``stats.jsonl`` (one JSON object per frame: ``frame_id``,
    ``points``, ``boxes`` per class and the transform's statistics). Everything is written to a
    temporary directory renamed to ``out`` at the end, so an interrupted run leaves nothing.

    Args:
        root: KITTI root; split: split name; transform: the augmentation.
        frames: augment the first ``frames`` frames of the split (``None``: all).
        seed: frame i uses :func:`frame_seed` ``(seed, i)``.
        fov_only: cut frames to the camera's field of view first (as OpenPCDet trains KITTI);
            frames then carry ``metadata["fov_only"] = True``.
        progress: ``progress(done, total)`` after each frame.

    Returns a summary: frames written, points and boxes per class over all frames, mean ms.
    """
    from drcpo.database import atomic_directory
    from drcpo.datasets.kitti import KittiDataset, fov_mask

    dataset = KittiDataset(root, split)
    ids = dataset.frame_ids if frames is None else dataset.frame_ids[: max(0, int(frames))]
    summary: dict[str, Any] = {"frames": len(ids), "points": 0, "boxes": {}, "ms": []}

    def write(tmp: Path) -> None:
        base = tmp / "training"
        for sub in ("velodyne", "label_2", "calib"):
            (base / sub).mkdir(parents=True)
        (tmp / "ImageSets").mkdir()
        (tmp / "ImageSets" / f"{split}.txt").write_text("".join(f"{i}\n" for i in ids))
        with (tmp / "stats.jsonl").open("w") as stats_file:
            for number, frame_id in enumerate(ids):
                frame = dataset.frame(frame_id)
                if fov_only:
                    keep = fov_mask(
                        frame.points, frame.metadata["calib"], dataset.image_shape(frame_id)
                    )
                    frame = frame.replace(
                        points=frame.points[keep], metadata={**frame.metadata, "fov_only": True}
                    )
                start = time.perf_counter()
                result = transform(frame, frame_seed(seed, number))
                elapsed = (time.perf_counter() - start) * 1000.0
                np.ascontiguousarray(result.points, np.float32).tofile(
                    base / "velodyne" / f"{frame_id}.bin"
                )
                lines = kitti_label_lines(result)
                (base / "label_2" / f"{frame_id}.txt").write_text("".join(f"{x}\n" for x in lines))
                shutil.copyfile(dataset.path("calib", frame_id), base / "calib" / f"{frame_id}.txt")
                names, counts = np.unique(result.names, return_counts=True)
                per_class = {str(n): int(c) for n, c in zip(names, counts, strict=True)}
                record = {
                    "frame_id": frame_id,
                    "seed": [int(seed), number],
                    "points_in": len(frame),
                    "points": len(result),
                    "boxes": per_class,
                    "ms": elapsed,
                    **result.metadata.get(STATS_KEY, {}),
                }
                stats_file.write(json.dumps(record) + "\n")
                summary["points"] += len(result)
                for name, count in per_class.items():
                    summary["boxes"][name] = summary["boxes"].get(name, 0) + count
                summary["ms"].append(elapsed)
                if progress is not None:
                    progress(number + 1, len(ids))

    atomic_directory(out, write, overwrite=overwrite)
    summary["mean_ms"] = float(np.mean(summary["ms"])) if summary["ms"] else 0.0
    summary["median_ms"] = float(np.median(summary["ms"])) if summary["ms"] else 0.0
    del summary["ms"]
    return summary
