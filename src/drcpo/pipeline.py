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
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cache, partial
from pathlib import Path
from typing import Any

import numba as nb
import numpy as np

from drcpo import construction, occlusion, placement
from drcpo.config import (
    DRCPOConfig,
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
from drcpo.frame import DICT_FIELDS, FRAME_FIELDS, Frame, validate_frame
from drcpo.geometry import (
    bev_corners,
    box_holding,
    rotate_points_z,
    wrap_angle,
)
from drcpo.index import indexed_mask
from drcpo.outputs import OutputKind, write_directory
from drcpo.placement import OcclusionMap, _facing_samples, frame_ground  # noqa: F401

FrameLike = Frame | dict[str, Any]
STATS_KEY = "augment_stats"
#: What :func:`augment_kitti` writes; ``augment.json`` (written last) marks it as drcpo's.
AUGMENT_OUTPUT = OutputKind("drcpo augment output", "augment.json", "drcpo-augmented-kitti")
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
        with stats.stage(self.name, len(frame)) as record:
            points, boxes = frame.points, frame.boxes
            record["flipped"] = [[]]
            for axis in self.config.axes:
                if rng.random() >= self.config.probability:
                    continue
                record["flipped"][0].append(axis)
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
        with stats.stage(self.name, len(frame)) as record:
            low, high = self.config.range
            angle = rng.uniform(low, high)
            record["angle"] = [float(angle)]
            points = rotate_points_z(frame.points, angle)
            boxes = rotate_points_z(frame.boxes, angle)
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
        with stats.stage(self.name, len(frame)) as record:
            low, high = self.config.range
            scale = rng.uniform(low, high)
            record["scale"] = [float(scale)]
            points = frame.points.copy()
            _scale_rows(points, float(scale))
            boxes = frame.boxes.copy()
            boxes[:, :6] *= scale
            return frame.replace(points=points, boxes=boxes)


@nb.njit(cache=True, nogil=True)
def _scale_rows(points, scale):  # pragma: no cover - numba
    # x, y, z times ``scale`` in float64, stored back (as numpy's assignment casts).
    for i in range(points.shape[0]):
        for c in range(3):
            points[i, c] = np.float64(points[i, c]) * scale


# --------------------------------------------------------------------------------------------
# Shared helpers for inserting objects
# --------------------------------------------------------------------------------------------
def _done(future: Future | None) -> Any:
    """A future's result if it has one already, else ``None``."""
    return future.result() if future is not None and future.done() else None


def _spare_core() -> bool:
    """Whether this process may use a second CPU (a forked data-loader worker pinned to one
    core may not)."""
    try:
        return len(os.sched_getaffinity(0)) > 1
    except AttributeError:  # not on Linux
        return (os.cpu_count() or 1) > 1


def _rows(array: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``array[mask]`` for a boolean row mask, through ``take`` (several times faster for
    point arrays than boolean indexing; the same rows in the same order)."""
    return array.take(np.flatnonzero(mask), axis=0)


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


def _placed_object(canonical: np.ndarray, box: np.ndarray, dim: int) -> np.ndarray:
    """``match_features(from_canonical(canonical, box), dim)`` in one compiled pass (the same
    values: the same float64 operations, with numpy's cos and sin of the heading)."""
    heading = np.float64(box[6])
    out = np.zeros((len(canonical), dim), dtype=np.float32)
    _place_rows(np.asarray(canonical, dtype=np.float32), np.cos(heading), np.sin(heading), box, out)
    return out


def _placed_objects(
    database: GroundTruthDatabase, rows: np.ndarray, boxes: np.ndarray, dim: int
) -> np.ndarray:
    """The database objects ``rows`` placed in ``boxes`` ``(S, 7)``, one after the other, as
    :func:`_placed_object` places each (``float32 (n, dim)``)."""
    objects = [database.object_points(int(row)) for row in rows]
    out = np.zeros((sum(len(canonical) for canonical in objects), dim), dtype=np.float32)
    start = 0
    for canonical, box in zip(objects, boxes, strict=True):
        heading = np.float64(box[6])
        stop = start + len(canonical)
        _place_rows(canonical, np.cos(heading), np.sin(heading), box, out[start:stop])
        start = stop
    return out


@nb.njit(cache=True, nogil=True)
def _place_rows(canonical, cos, sin, box, out):  # pragma: no cover - numba
    features = min(canonical.shape[1], out.shape[1])
    for i in range(canonical.shape[0]):
        x, y = np.float64(canonical[i, 0]), np.float64(canonical[i, 1])
        out[i, 0] = np.float32((cos * x - sin * y) + box[0])
        out[i, 1] = np.float32((sin * x + cos * y) + box[1])
        out[i, 2] = np.float32(np.float64(canonical[i, 2]) + box[2])
        for c in range(3, features):
            out[i, c] = canonical[i, c]


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
    points in the box's axis-aligned BEV bounds (a few cheap comparisons) and tests only those
    exactly, with the arithmetic and boundary rule (closed boxes) of
    :func:`drcpo.geometry.points_in_boxes`. (Sorting the points by x once instead costs more
    than it saves for the few dozen queries a frame needs.)

    Args:
        points: ``(N, 3+)`` points, metres (not copied; do not modify them while querying).
    """

    _SLACK = 1e-3  # metres; keeps the float32 pre-filter conservative

    def __init__(self, points: np.ndarray) -> None:
        self.points = points
        self._xy: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def x(self) -> np.ndarray:
        return self._columns()[0]

    @property
    def y(self) -> np.ndarray:
        return self._columns()[1]

    def _columns(self) -> tuple[np.ndarray, np.ndarray]:
        # Copied on the first single-box query only: the one-pass scans read the points.
        if self._xy is None:
            self._xy = (
                np.ascontiguousarray(self.points[:, 0]),
                np.ascontiguousarray(self.points[:, 1]),
            )
        return self._xy

    def inside(self, box: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Indices ``int64 (k,)`` (ascending) of the points in one ``(7,)`` box grown by
        ``margin`` metres."""
        box = np.asarray(box, dtype=np.float64).reshape(7)
        # numpy's cos/sin, as points_in_boxes uses them (libm may differ in the last bit).
        cos, sin = float(np.cos(box[6:7])[0]), float(np.sin(box[6:7])[0])
        length, width = box[3] + 2.0 * margin, box[4] + 2.0 * margin
        half_x = (length * abs(cos) + width * abs(sin)) / 2.0 + self._SLACK
        half_y = (length * abs(sin) + width * abs(cos)) / 2.0 + self._SLACK
        cx, cy = float(box[0]), float(box[1])
        # Python floats compare with the float32 columns without converting them to float64.
        near = np.flatnonzero(
            (self.x >= cx - half_x)
            & (self.x <= cx + half_x)
            & (self.y >= cy - half_y)
            & (self.y <= cy + half_y)
        )
        if len(near) == 0:
            return near
        delta = self.points[near, :3].astype(np.float64) - box[:3]
        half = box[3:6] / 2.0 + margin
        local_x = delta[:, 0] * cos + delta[:, 1] * sin
        local_y = -delta[:, 0] * sin + delta[:, 1] * cos
        inside = (
            (np.abs(local_x) <= half[0])
            & (np.abs(local_y) <= half[1])
            & (np.abs(delta[:, 2]) <= half[2])
        )
        return near[inside]

    def inside_any(self, boxes: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """``bool (N,)``: points in at least one of the ``(M, 7)`` boxes."""
        return self.owners(boxes, margin) >= 0

    def owners(self, boxes: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """``int64 (N,)``: the last of the ``(M, 7)`` boxes holding each point (-1: none).

        One pass over the points for all boxes (a per-box query scans every point again), with
        a coarse grid of the boxes' bounds (:func:`~drcpo.placement.box_members`); same
        arithmetic and boundary rule as :meth:`inside`.
        """
        owner = np.full(len(self.points), -1, dtype=np.int64)
        point, box = placement.box_members(self.points, boxes, margin)  # by point, then box
        last = np.flatnonzero(np.diff(point, append=len(owner)))  # a point's last box
        owner[point[last]] = box[last]
        return owner

    def counts(self, boxes: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """``int64 (M,)``: points in each box."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        box = placement.box_members(self.points, boxes, margin)[1]
        return np.bincount(box, minlength=len(boxes)).astype(np.int64)

    def own_counts(
        self, owner: np.ndarray, boxes: np.ndarray | Sequence[np.ndarray], where: np.ndarray
    ) -> np.ndarray:
        """``int64 (M,)``: per box ``m``, the points with ``owner == m`` (``int (N,)``) and
        ``where`` (``bool (N,)``) that lie in it, in one pass."""
        owner, where = np.asarray(owner), np.asarray(where, dtype=bool)
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        point, box = placement.box_members(self.points, boxes)
        own = (owner[point] == box) & where[point]
        return np.bincount(box[own], minlength=len(boxes)).astype(np.int64)


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
            # Overlap area > 0, as OpenPCDet's BEV IoU test, by separating axes (same verdicts).
            hits_existing = placement.bev_collisions(boxes, existing).any(axis=1)
            among = placement.bev_collisions(boxes, boxes)
            np.fill_diagonal(among, False)
            valid = ~hits_existing & ~among.any(axis=1)
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
        keep = ~BoxQuery(frame.points).inside_any(boxes)
        objects = _placed_objects(self.database, rows, boxes, frame.points.shape[1])
        points = np.concatenate([_rows(frame.points, keep), objects])
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
# DR.CPO
# --------------------------------------------------------------------------------------------
_CHUNK = 6  # objects built per compiled call while s-HPR works on the ones before
_FIT_PAD = 1e-4  # metres between a label's moved face and the point beyond it (see box_holding)


class _WorkQueue:
    """Jobs done, in any order, by one thread of ``pool`` whenever it is free (after
    :meth:`start`) and by the calling thread in :meth:`results`. A job's answer must not
    depend on which thread does it."""

    def __init__(self, pool: ThreadPoolExecutor | None) -> None:
        self._pool = pool
        self._jobs: deque[tuple[int, Callable[[], Any]]] = deque()
        self._results: dict[int, Any] = {}
        self._helper: Future | None = None

    def add(self, key: int, job: Callable[[], Any]) -> None:
        self._jobs.append((key, job))

    def start(self) -> None:
        """Let the pool's thread take jobs, unless it is on it already."""
        if self._pool is None or (self._helper is not None and not self._helper.done()):
            return
        if self._helper is not None:
            self._helper.result()  # (raises what a job raised there)
        self._helper = self._pool.submit(self._drain)

    def _drain(self) -> None:
        while True:
            try:
                key, job = self._jobs.popleft()  # atomic: the threads never share a job
            except IndexError:
                return
            self._results[key] = job()

    def results(self) -> dict[int, Any]:
        """Every job's answer by key, once all are done (a pool thread that has not started
        is not waited for)."""
        try:
            self._drain()
        except BaseException:
            self._jobs.clear()  # the pool's thread stops after its current job
            raise
        if self._helper is not None and not self._helper.cancel():
            self._helper.result()
        return self._results


@dataclass(frozen=True, eq=False)
class _Placed:
    """What e-HPR needs of the placed boxes alone (worked out while the objects are built):
    the boxes ``(A, 7)``; per frame point, the last box holding it (``int64 (N,)``, -1:
    none); each box's source row; their view windows."""

    boxes: np.ndarray
    owners: np.ndarray
    rows: np.ndarray  # each box's source row
    windows: tuple[np.ndarray, ...]  # _box_windows of the boxes grown by _WINDOW_SLACK

    def windows_of(self, insertions: Sequence[_Insertion]) -> tuple[np.ndarray, ...]:
        """The view windows of the boxes of ``insertions``, some of the placed objects in their
        order (a box's window does not depend on the others)."""
        index, k = [], 0
        for insertion in insertions:
            while int(self.rows[k]) != insertion.row:
                k += 1
            index.append(k)
            k += 1
        return tuple(values[np.array(index, dtype=np.int64)] for values in self.windows)


@dataclass(frozen=True, eq=False)
class _Insertion:
    """One object on its way into the frame: source row, class, placed box, its label (the
    placed box grown to hold the points, see :meth:`DRCPO._object_s_hpr`), placed points."""

    row: int
    name: str
    placed: np.ndarray
    box: np.ndarray
    points: np.ndarray


class DRCPO(Transform):
    """DR.CPO: iterative construction, random placement and HPR occlusion (Shin et al. 2023).

    Per call:

    1. **Sample** ``sample[class]`` source objects per class, without replacement, among the
       objects that the candidate index covers and that have at least ``min_points`` points.
    2. **Place** (``partition`` mode, before any construction, so that rejected objects cost
       nothing): a random heading and position, the box bottom on the frame's ground estimate
       (or at its source height); rejected for ``out_of_range``, ``collision`` (BEV overlap with
       any box) or ``obstacle`` (more than ``max_non_ground_points`` non-ground frame points in
       the box); see :mod:`drcpo.placement`. Each footprint keeps :attr:`room` free around
       it, as the object's label may grow by that much (step 4). A placed box is rejected
       too (``occluded``) when e-HPR hides at least ``placement.occluded_fraction`` (default
       1.0: all) of a 5 x 4 grid of samples on each of its sensor-facing faces behind the
       frame's points, each sample decided exactly as a point added to them (with the
       ``range_image`` mode: a z-buffer at the sensor's resolution). e-HPR would almost
       always leave such an object too few points: on the KITTI sample and synthetic frames,
       3 of 1,676 objects e-HPR kept were that hidden, against 4,182 of 4,673 it dropped (a
       z-buffer test at 95 % caught 2,655 of them). So it is not built and hides nothing.
       Each rejected object gets a fresh pose up to ``placement.attempts`` times. In
       ``whole`` mode the box grows during construction, so objects are constructed first
       and placed with their final size.
    3. **Construct** each placed object from its indexed candidates (:mod:`drcpo.construction`).
    4. **s-HPR**: hidden point removal per object from the sensor origin with
       ``R = box diagonal x radius_factor``; an object left with fewer than ``min_points`` points
       is dropped (``self_occlusion``). The object's label is its placed box with the faces
       that points lie beyond moved out to hold them: construction keeps points up to
       ``construction.margin`` outside the source box, and s-HPR keeps the outermost.
    5. **Insert**: frame points within the accepted objects' room (their placed box grown by
       :attr:`room`) are removed, the objects' points added.
    6. **e-HPR** from the detector preset's viewpoint and radius. Scope ``frame`` (the paper)
       removes every hidden point of the frame. Scope ``inserted`` (default) first removes the
       inserted points that are hidden; an object then left with fewer than
       ``min_points_after`` points in its box is dropped (see 7). It then removes the original
       points that lie behind the box of an object kept, in its view window (the azimuth and
       elevation it covers), and are hidden with the objects but visible without them.
       Visibility is decided only for those points, each exactly against the whole frame (HPR
       queries), so HPR's own errors never delete real, visible points and directions without
       inserted objects cost nothing.
    7. **Labels**: an object dropped by e-HPR goes with all its points (reason
       ``external_occlusion``), and the frame points it displaced come back (with scope
       ``inserted``, those it alone hid were never removed). An original box that lost points
       and holds fewer than ``min_points_after`` is dropped, unless it already had fewer
       before.

    Args:
        database: the ground-truth database (canonical points).
        index: its :class:`~drcpo.index.CandidateIndex`.
        config: a :class:`~drcpo.config.DRCPOConfig` (the paper defaults when ``None``) or a
            mapping of its keys.

    The transform holds only read-only state (database, index, config, per-class row pools),
    so it is safe to share with forked workers.
    """

    name = "drcpo"

    def __init__(
        self,
        database: GroundTruthDatabase,
        index: Any,
        config: DRCPOConfig | Mapping[str, Any] | None = None,
    ) -> None:
        if isinstance(config, Mapping) or config is None:
            config = from_dict(DRCPOConfig, config, "drcpo")
        if not isinstance(config, DRCPOConfig):
            raise TypeError(f"config must be a DRCPOConfig or a mapping, got {type(config)}")
        self.config: DRCPOConfig = config
        self.database = database
        self.index = index
        self._construction = construction.ConstructionConfig(
            mode=config.construction.mode,
            coverage=config.construction.coverage,
            max_iterations=config.construction.max_iterations,
            margin=config.construction.margin,
            mirrored_classes=tuple(config.construction.mirror),
            grids={k: tuple(v) for k, v in config.construction.grids.items()},
        )
        self._placement = {fov: self._placement_config(fov) for fov in (False, True)}
        classes = [name for name, count in config.sample.items() if count > 0]
        self._check_index(classes)
        indexed = indexed_mask(database, index.config)
        self._pools = {
            name: pool[indexed[pool]]
            for name, pool in _sampling_pools(
                database, classes, config.min_points, config.exclude_difficulty
            ).items()
        }
        for pool in self._pools.values():
            pool.setflags(write=False)

    def _placement_config(self, fov_only: bool) -> placement.PlacementConfig:
        p = self.config.placement
        return placement.PlacementConfig(
            x_range=tuple(p.x_range),
            y_range=tuple(p.y_range),
            fov_only=fov_only,
            height_mode=p.height,
            max_nonground_points=p.max_non_ground_points,
            ground_tolerance=p.ground_tolerance,
            max_tries=p.attempts,
            clearance=self.room,
        )

    @property
    def room(self) -> float:
        """Metres by which an object's label may exceed its placed box on any side: the
        construction margin (``partition`` mode keeps points that far outside the source box)
        and twice :data:`_FIT_PAD`. Placement keeps that much room free around each box, and
        the frame's points within it make way for the object."""
        margin = self.config.construction.margin if self._construction.mode == "partition" else 0
        return float(margin) + 2.0 * _FIT_PAD

    def _check_index(self, classes: Sequence[str]) -> None:
        """The index must partition and mirror each class as construction does."""
        if len(self.index.candidates) != len(self.database):
            raise ConfigError(
                f"the candidate index covers {len(self.index.candidates)} objects but the "
                f"database has {len(self.database)}; rebuild it with `drcpo index`"
            )
        mirrored_in_index = set(self.index.config.mirrored)
        for name in classes:
            if name not in self.index.grids:
                continue  # no indexed object of this class: it is never sampled
            grid = self._construction.grid(name)
            if tuple(self.index.grids[name]) != tuple(grid):
                raise ConfigError(
                    f"drcpo.construction.grids.{name} = {list(grid)} but the candidate index "
                    f"was built with {list(self.index.grids[name])}; use the same grid"
                )
            if (name in self._construction.mirrored_classes) != (name in mirrored_in_index):
                raise ConfigError(
                    f"drcpo.construction.mirror and the candidate index disagree on whether "
                    f"{name} is mirrored; use the same classes"
                )

    @classmethod
    def from_config(
        cls,
        data: Mapping[str, Any],
        database: GroundTruthDatabase | None = None,
        index: Any = None,
        **_: Any,
    ) -> DRCPO:
        if database is None or index is None:
            raise ConfigError("DRCPO.from_config needs database=... and index=...")
        body = _config_body(data, cls.__name__)
        body.pop("enabled", None)
        return cls(database, index, from_dict(DRCPOConfig, body, "DRCPO"))

    def to_config(self) -> dict[str, Any]:
        body = to_dict(self.config)
        body.pop("enabled")
        return {"type": type(self).__name__, **body}

    def __repr__(self) -> str:
        c = self.config
        return (
            f"DRCPO({self.database!r}, sample={c.sample}, "
            f"construction={c.construction.mode!r}, height={c.placement.height!r}, "
            f"e_hpr={c.external_occlusion.mode}:{c.external_occlusion.preset}:"
            f"{c.external_occlusion.scope})"
        )

    # The steps ------------------------------------------------------------------------------
    def apply(self, frame: Frame, rng: np.random.Generator, stats: Stats) -> Frame:
        with stats.stage("drcpo.sample", len(frame)):
            rows = self._sample(rng, stats)
        objects: list[Any] = []
        placed: Future | None = None  # of a _Placed
        with ThreadPoolExecutor(max_workers=1) as pool:
            frame_grid = self._frame_grid(frame, rows, pool)
            # s-HPR of each object, done by this thread and the pool's when it is free.
            s_hpr = _WorkQueue(pool if _spare_core() else None)
            if self.config.construction.mode == "partition":
                with stats.stage("drcpo.placement", len(frame)):
                    boxes, accepted, owners = self._place(
                        frame, rows, None, rng, stats, frame_grid, pool
                    )
                    rows = rows[accepted]
                    placed = self._placed_task(frame, boxes, rows, owners, frame_grid, pool)
                # With placement first, objects go to s-HPR chunk by chunk as they are built
                # (the answers do not depend on it); the construction stage's time then
                # includes the s-HPR work done meanwhile.
                with stats.stage("drcpo.construction", 0) as record:
                    queue = partial(self._queue_s_hpr, s_hpr, boxes, frame.points.shape[1])
                    objects = self._construct(rows, rng, stats, queue)
                    record["points_out"] = sum(len(o.points) for o in objects)
            else:  # whole: the box grows while constructing, so place with the final size
                with stats.stage("drcpo.construction", 0) as record:
                    objects = self._construct(rows, rng, stats)
                    record["points_out"] = sum(len(o.points) for o in objects)
                with stats.stage("drcpo.placement", len(frame)):
                    dims = np.array([o.dims for o in objects], dtype=np.float64).reshape(-1, 3)
                    boxes, accepted, owners = self._place(
                        frame, rows, dims, rng, stats, frame_grid, pool
                    )
                    rows, objects = rows[accepted], [objects[i] for i in accepted]
                    placed = self._placed_task(frame, boxes, rows, owners, frame_grid, pool)
                self._queue_s_hpr(s_hpr, boxes, frame.points.shape[1], 0, objects)
            points_in = sum(len(o.points) for o in objects)
            with stats.stage("drcpo.self_occlusion", points_in) as record:
                done = s_hpr.results()
                visible = [done[k] for k in range(len(rows))]
                insertions = self._insertions(rows, boxes, visible, stats)
                record["points_out"] = sum(len(i.points) for i in insertions)
            with stats.stage("drcpo.insert", len(frame)) as record:
                points, owner, cleared_by = self._insert(frame, insertions, _done(placed))
                record["points_out"] = len(points)
            with stats.stage("drcpo.external_occlusion", len(points)) as record:
                grid = frame_grid() if frame_grid is not None and insertions else None
                helper = pool if _spare_core() else None
                keep, dropped = self._external_occlusion(
                    points, owner, insertions, grid, cleared_by, helper, _done(placed)
                )
                record["points_out"] = int(keep.sum())
            with stats.stage("drcpo.labels", int(keep.sum())) as record:
                out = self._settle(
                    frame, points, owner, keep, dropped, cleared_by, insertions, stats
                )
                record["points_out"] = len(out)
        return out

    def _frame_grid(
        self, frame: Frame, rows: np.ndarray, pool: ThreadPoolExecutor
    ) -> Callable[[], occlusion.FrameGrid] | None:
        """e-HPR's grid of the frame's points (scope ``inserted``, and the ``occluded`` test
        of placement), as a call that returns it: on two cores it is built on ``pool``
        meanwhile (it does not depend on the objects), else when first asked for. ``None``
        when nothing will need it."""
        settings = self.config.external_occlusion
        needed = settings.enabled and settings.mode == "hpr"
        needed &= (
            settings.scope == "inserted" or self.config.placement.occluded_fraction is not None
        )
        if not needed or len(rows) == 0:
            return None
        radius, viewpoint = self.e_hpr_setting()
        # In this thread's memory, wherever built: the previous call's grid is done with.
        memory = occlusion.thread_grid_memory()
        build = partial(occlusion.FrameGrid.build, frame.points, viewpoint, radius, memory=memory)
        return pool.submit(build).result if _spare_core() else cache(build)

    def _placed_task(
        self,
        frame: Frame,
        boxes: np.ndarray,
        rows: np.ndarray,
        owners: np.ndarray | None,
        frame_grid: Callable[[], occlusion.FrameGrid] | None,
        pool: ThreadPoolExecutor,
    ) -> Future | None:
        """On two cores, start on ``pool`` working out the :class:`_Placed` of the placed
        ``boxes`` (of source ``rows``; ``owners``: the room each frame point lies in, if known)
        while the objects are built; its future, or ``None`` when nothing is started."""
        if frame_grid is None or len(boxes) == 0 or not _spare_core():
            return None
        _, viewpoint = self.e_hpr_setting()

        def place() -> _Placed:
            rooms = owners if owners is not None else self._room_owners(frame, boxes)
            return _Placed(boxes, rooms, rows, _box_windows(_grown(boxes), viewpoint))

        return pool.submit(place)

    def _sample(self, rng: np.random.Generator, stats: Stats) -> np.ndarray:
        """Source rows ``int64 (S,)``: per class, without replacement, from its pool."""
        chosen = []
        for name, count in self.config.sample.items():
            pool = self._pools.get(name)
            size = min(int(count), 0 if pool is None else len(pool))
            if size == 0:
                continue
            chosen.append(rng.choice(pool, size=size, replace=False))
            stats.tried(self.name, name, size)
        return np.concatenate(chosen).astype(np.int64) if chosen else np.zeros(0, np.int64)

    def _place(
        self,
        frame: Frame,
        rows: np.ndarray,
        dims: np.ndarray | None,
        rng: np.random.Generator,
        stats: Stats,
        frame_grid: Callable[[], occlusion.FrameGrid] | None = None,
        pool: ThreadPoolExecutor | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Placed boxes ``(A, 7)``, the indices (into ``rows``) of the placed objects and, when
        worked out, the room (see :attr:`room`) each frame point lies in (``int64 (N,)``, -1:
        none)."""
        if len(rows) == 0:
            return np.zeros((0, 7)), np.zeros(0, np.int64), None
        source = np.asarray(self.database.boxes[rows], dtype=np.float64)
        dims = source[:, 3:6] if dims is None else dims
        camera = self.config.placement.camera_fov
        fov = camera == "always" or (camera == "auto" and bool(frame.metadata.get("fov_only")))
        limit = self.config.placement.occluded_fraction
        check = limit is not None and self.config.external_occlusion.enabled
        last: list[tuple[int, np.ndarray, np.ndarray]] = []  # the occlusion test's last call

        def occluded(boxes: np.ndarray, before: np.ndarray) -> np.ndarray:
            everything = np.concatenate([before, boxes])
            owners = self._room_owners(frame, everything)
            hidden = self._occluded(frame, boxes, everything, owners, frame_grid, limit, pool)
            last[:] = [(len(before), owners, hidden)]
            return hidden

        # No ground given: place_objects estimates it from the frame's points. (Estimating it
        # on a second thread meanwhile measured slower on the shared cores.)
        result = placement.place_objects(
            frame, dims, source, rng, self._placement[fov], occluded=occluded if check else None
        )
        names = self.database.names[rows]
        for i in np.flatnonzero(result.reasons != ""):
            stats.rejected(self.name, names[i], str(result.reasons[i]))
        boxes, accepted = result.boxes, result.accepted
        if not last or not len(boxes):
            return boxes, accepted, None
        before, owners, hidden = last[0]
        if before or len(boxes) != int((~hidden).sum()):  # placed over several tries
            return boxes, accepted, self._room_owners(frame, boxes)
        renumber = np.full(len(hidden) + 1, -1, dtype=np.int64)  # (index -1: no room)
        renumber[np.flatnonzero(~hidden)] = np.arange(len(boxes))
        return boxes, accepted, renumber[owners]

    def _room_owners(self, frame: Frame, boxes: np.ndarray) -> np.ndarray:
        """``int64 (N,)``: the placed box whose room (see :attr:`room`) holds each frame point
        (-1: none; placement keeps the rooms apart)."""
        return BoxQuery(frame.points).owners(_grown(boxes, self.room))

    def _occluded(
        self,
        frame: Frame,
        boxes: np.ndarray,
        everything: np.ndarray,
        owners: np.ndarray,
        frame_grid: Callable[[], occlusion.FrameGrid] | None,
        limit: float,
        pool: ThreadPoolExecutor | None = None,
    ) -> np.ndarray:
        """``bool (B,)``: ``boxes`` whose sensor-facing surface e-HPR would hide behind the
        frame's points by at least ``limit``; the points in the rooms of ``everything`` placed
        (``owners``, see :meth:`_room_owners`) make way for them and hide nothing. Mode
        ``hpr``: surface samples decided exactly by HPR among the frame's points
        (:meth:`~drcpo.occlusion.FrameGrid.hidden_groups`; nothing is hidden where that test
        does not apply); ``range_image``: a z-buffer at the sensor's resolution
        (:class:`~drcpo.placement.OcclusionMap`)."""
        _, viewpoint = self.e_hpr_setting()
        if frame_grid is not None:
            samples, offsets = placement.surface_samples(boxes, viewpoint)
            helper = pool if _spare_core() else None
            hidden = frame_grid().hidden_groups(samples, offsets, owners >= 0, limit, helper)
            return hidden if hidden is not None else np.zeros(len(boxes), dtype=bool)
        z_buffer = OcclusionMap(frame.points, viewpoint)
        return z_buffer.occluded(boxes, cleared=everything) >= limit

    def _construct(
        self,
        rows: np.ndarray,
        rng: np.random.Generator,
        stats: Stats,
        on_chunk: Callable[[int, list[Any]], None] | None = None,
    ) -> list[Any]:
        """Constructed objects; with ``on_chunk``, built :data:`_CHUNK` at a time and handed to
        it as they come (see :func:`~drcpo.construction.construct_objects`)."""
        objects = construction.construct_objects(
            self.database,
            rows,
            self.index.candidates[rows],
            rng,
            self._construction,
            self.index.max_counts,
            chunk=_CHUNK if on_chunk is not None else None,
            on_chunk=on_chunk,
        )
        for name, built in zip(self.database.names[rows], objects, strict=True):
            stats.construction(str(name), built.iterations)
        return objects

    def _queue_s_hpr(
        self, work: _WorkQueue, boxes: np.ndarray, dim: int, first: int, objects: Sequence[Any]
    ) -> None:
        """Queue on ``work`` the s-HPR of ``objects`` (numbers ``first``, ``first + 1``, ... of
        ``boxes``), placed with the frame's ``dim`` columns."""
        for k, built in enumerate(objects, first):
            work.add(k, partial(self._object_s_hpr, built.points, boxes[k], dim))
        work.start()

    def _object_s_hpr(
        self, canonical: np.ndarray, box: np.ndarray, dim: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """One object's ``canonical`` points placed in ``box``, after s-HPR (one hull:
        drcpo.hull's certified one, Qhull where it gives up; much faster than the per-point
        method for objects), and its label: ``box`` with the faces that points lie beyond
        (construction keeps points up to its margin outside; s-HPR keeps the outermost ones)
        moved out to hold them, so that the label holds every point the object brings."""
        points = _placed_object(canonical, box, dim)
        settings = self.config.self_occlusion
        if settings.enabled and len(points):
            visible = occlusion.self_occlusion(
                points, box, settings.radius_factor, method="reference", workers=1
            )
            points = _rows(points, visible)
        return points, box_holding(box, points, _FIT_PAD)

    def _insertions(
        self,
        rows: np.ndarray,
        boxes: np.ndarray,
        visible: Sequence[tuple[np.ndarray, np.ndarray]],
        stats: Stats,
    ) -> list[_Insertion]:
        """The objects left with at least ``self_occlusion.min_points`` points after s-HPR
        (``visible``: each object's placed points left and its label), the others rejected."""
        minimum = self.config.self_occlusion.min_points
        insertions = []
        for row, box, (points, label) in zip(rows, boxes, visible, strict=True):
            name = str(self.database.names[row])
            if len(points) < minimum:
                stats.rejected(self.name, name, "self_occlusion")
                continue
            insertions.append(_Insertion(int(row), name, box, label, points))
        return insertions

    def _insert(
        self, frame: Frame, insertions: Sequence[_Insertion], placed: _Placed | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points after insertion (the frame's points outside the objects' room, see
        :attr:`room`, then the objects'), each point's owner (-1: an original point, else the
        insertion's number) and, per frame point, the insertion it had to make room for (-1:
        none). ``placed``: see :meth:`_placed_task`; its owners are reused when every placed
        object is inserted."""
        cleared_by = np.full(len(frame), -1, dtype=np.int64)
        if not insertions:
            return frame.points, cleared_by.copy(), cleared_by
        if placed is not None and len(placed.boxes) == len(insertions):  # the same boxes
            cleared_by = placed.owners
        else:
            cleared_by = self._room_owners(frame, np.array([i.placed for i in insertions]))
        original = cleared_by < 0
        points = np.concatenate([_rows(frame.points, original), *(i.points for i in insertions)])
        owner = np.concatenate(
            [np.full(int(original.sum()), -1)]
            + [np.full(len(i.points), j) for j, i in enumerate(insertions)]
        ).astype(np.int64)
        return points, owner, cleared_by

    def _external_occlusion(
        self,
        points: np.ndarray,
        owner: np.ndarray,
        insertions: Sequence[_Insertion],
        grid: occlusion.FrameGrid | None = None,
        cleared_by: np.ndarray | None = None,
        pool: ThreadPoolExecutor | None = None,
        placed: _Placed | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Points kept by e-HPR (or the range-image mode) under the scope rule, ``bool (N,)``,
        and the insertions left with too few points in their box, ``bool (len(insertions),)``.

        Scope ``frame``: every hidden point goes. Scope ``inserted``: the inserted points are
        decided first, each exactly against the whole frame, and hidden ones go; then, for the
        original points behind the boxes of the objects that keep enough points, in their view
        windows (the directions they cover), those hidden with the objects but visible without
        them go. With ``grid`` (the frame's :class:`~drcpo.occlusion.FrameGrid`) and
        ``cleared_by`` (see :meth:`_insert`), the frame's points are not sorted again; ``pool``
        may lend a thread; ``placed``: see :meth:`_placed_task`.
        """
        settings = self.config.external_occlusion
        inserted = owner >= 0
        keep = np.ones(len(points), dtype=bool)
        if settings.enabled and len(points) and settings.scope == "frame":
            keep = self._visible(points)
        if not settings.enabled or len(points) == 0 or settings.scope == "frame" or not insertions:
            return keep, self._dropped(points, owner, insertions, keep)
        _, viewpoint = self.e_hpr_setting()
        first = int(np.count_nonzero(~inserted))  # the original points come first
        known = placed.windows_of(insertions) if placed is not None else None
        found: dict[str, np.ndarray] = {}

        def behind_kept(removed_inserted: np.ndarray, frame_points: np.ndarray) -> np.ndarray:
            # ``frame_points``: in the grid's order and number, or the original points'.
            found["dropped"] = dropped = self._dropped(
                points[first:], owner[first:], insertions, ~removed_inserted
            )
            kept = np.flatnonzero(~dropped)
            grown = _grown([insertions[k].placed for k in kept])
            windows = _window_spans(
                grown, viewpoint, True, None if known is None else [w[kept] for w in known]
            )
            if grid is not None and len(frame_points) == grid.size:
                return grid.in_windows(windows) if windows is not None else frame_points.copy()
            return _in_windows(frame_points, windows, viewpoint)

        if settings.mode == "hpr" and grid is not None and cleared_by is not None:
            cleared = cleared_by >= 0
            result = grid.hidden_by_insertion(
                cleared,
                points[first:],
                lambda removed: behind_kept(removed, ~cleared),
                pool=pool,
            )
            if result is not None:
                keep = ~np.concatenate([result[0][~cleared], result[1]])
                return keep, found["dropped"]
        if settings.mode == "hpr":
            radius, _ = self.e_hpr_setting()
            removed = occlusion.hidden_by_insertion(
                points,
                inserted,
                lambda gone: np.append(behind_kept(gone[first:], points[:first]), inserted[first:]),
                viewpoint,
                radius,
            )
            return ~removed, found["dropped"]
        visible = self._visible(points)
        keep[inserted & ~visible] = False
        behind = behind_kept(~keep[first:], points[:first])
        suspects = np.flatnonzero(behind & ~visible[:first])
        if len(suspects):
            wanted = np.zeros(first, dtype=bool)
            wanted[suspects] = True
            # Only points visible without the inserted objects go; those hidden even without
            # them stay: HPR's own errors must not delete real points.
            before = self._visible(points[:first], query=wanted)
            keep[:first][wanted & before] = False
        return keep, found["dropped"]

    def _dropped(
        self,
        points: np.ndarray,
        owner: np.ndarray,
        insertions: Sequence[_Insertion],
        keep: np.ndarray,
    ) -> np.ndarray:
        """``bool (len(insertions),)``: objects with fewer than ``min_points_after`` of their
        points that ``keep`` (``bool (N,)``) holds in their own box (construction may leave
        some a few cm outside it)."""
        if not insertions:
            return np.zeros(0, dtype=bool)
        survivors = BoxQuery(points).own_counts(owner, [i.box for i in insertions], keep)
        return survivors < self.config.min_points_after

    def e_hpr_setting(self) -> tuple[float, np.ndarray]:
        """e-HPR radius R (metres) and viewpoint ``(3,)`` of the configured preset/overrides."""
        settings = self.config.external_occlusion
        preset = occlusion.HPR_PRESETS[settings.preset]
        radius = settings.radius if settings.radius is not None else preset.radius
        height = settings.viewpoint_z if settings.viewpoint_z is not None else preset.viewpoint_z
        return float(radius), np.array([0.0, 0.0, float(height)])

    def _visible(self, points: np.ndarray, query: np.ndarray | None = None) -> np.ndarray:
        """``bool (N,)`` visibility from the e-HPR viewpoint (``True`` outside ``query``)."""
        radius, viewpoint = self.e_hpr_setting()
        if self.config.external_occlusion.mode == "range_image":
            visible = occlusion.range_image_occlusion(points, viewpoint)
            return visible if query is None else visible | ~query
        return occlusion.hidden_point_removal(points, viewpoint, radius, query=query)

    def _settle(
        self,
        frame: Frame,
        points: np.ndarray,
        owner: np.ndarray,
        keep: np.ndarray,
        dropped: np.ndarray,
        cleared_by: np.ndarray,
        insertions: Sequence[_Insertion],
        stats: Stats,
    ) -> Frame:
        """The output frame: drop inserted objects and original boxes left with too few points.

        An inserted object of ``dropped`` goes with all its points, and the frame points it
        displaced come back (e-HPR removed frame points only behind the objects kept), so it
        leaves no trace. An original box is dropped when it lost points and is left with fewer
        than ``min_points_after``, unless it had fewer already.
        """
        original_rows = np.flatnonzero(cleared_by < 0)  # frame row of each original point
        removed = cleared_by >= 0
        if dropped.any():
            removed &= ~np.append(dropped, False)[cleared_by]  # (index -1: the frame's own)
        removed[original_rows[~keep[: len(original_rows)]]] = True
        for insertion, gone in zip(insertions, dropped, strict=True):
            if gone:
                stats.rejected(self.name, insertion.name, "external_occlusion")
            else:
                stats.added(self.name, insertion.name)
        kept = [i for i, gone in zip(insertions, dropped, strict=True) if not gone]
        drop_original = self._sparse_originals(frame, removed)
        for name in frame.names[drop_original]:
            stats.label_dropped(str(name))
        inserted_keep = keep & ~np.append(dropped, True)[owner]  # (index -1: not inserted)
        kept_boxes = np.flatnonzero(~drop_original)
        return frame.replace(
            points=np.concatenate([_rows(frame.points, ~removed), _rows(points, inserted_keep)]),
            boxes=np.concatenate([frame.boxes[kept_boxes], _grown([i.box for i in kept], 0.0)]),
            names=np.concatenate([frame.names[kept_boxes], [i.name for i in kept]]),
            metadata=update_box_metadata(
                frame.metadata,
                len(frame.boxes),
                keep=kept_boxes if drop_original.any() else None,
                added=len(kept),
            ),
        )

    def _sparse_originals(self, frame: Frame, removed: np.ndarray) -> np.ndarray:
        """``bool (M,)``: frame boxes that lost points and now hold fewer than the minimum,
        having held at least the minimum before. Only boxes holding removed points can have
        lost any, so only those are counted."""
        minimum = self.config.min_points_after
        drop = np.zeros(len(frame.boxes), dtype=bool)
        if not removed.any() or len(frame.boxes) == 0:
            return drop
        lost = BoxQuery(_rows(frame.points, removed)).counts(frame.boxes)
        touched = np.flatnonzero(lost)
        if len(touched):
            had = BoxQuery(frame.points).counts(frame.boxes[touched])
            drop[touched] = (had >= minimum) & (had - lost[touched] < minimum)
        return drop


_WINDOW_SLACK = 0.1  # metres added around inserted boxes (construction keeps points 5 cm out)


def _grown(boxes: Sequence[np.ndarray], slack: float = _WINDOW_SLACK) -> np.ndarray:
    """Boxes ``(M, 7)`` grown by ``slack`` metres on every side (for view windows)."""
    grown = np.array(boxes, dtype=np.float64).reshape(-1, 7)
    grown[:, 3:6] += 2.0 * slack
    return grown


def view_windows(
    points: np.ndarray, boxes: np.ndarray, viewpoint: np.ndarray, behind: bool = False
) -> np.ndarray:
    """``bool (N,)``: points in the view window of some box seen from ``viewpoint``.

    A box's view window is the range of azimuth (about z) and elevation its volume covers seen
    from the viewpoint; a point in none of them can be neither hidden nor revealed by the box.
    With ``behind``, only points at least as far from the viewpoint as the box's nearest point
    count (nothing nearer can be occluded by it).
    """
    return _in_windows(points, _window_spans(boxes, viewpoint, behind), viewpoint)


def _window_spans(
    boxes: np.ndarray | Sequence[np.ndarray],
    viewpoint: np.ndarray,
    behind: bool = False,
    known: tuple[np.ndarray, ...] | None = None,
) -> np.ndarray | None:
    """The view windows of ``(M, 7)`` boxes (see :func:`view_windows`; ``known``: their
    :func:`_box_windows`, if computed already) as ``(K, 5)`` rows (azimuth from, azimuth to,
    elevation from, elevation to, nearest distance), radians and metres: a window across the
    azimuth seam at +-pi is split in two, and the nearest distance is ``-inf`` unless
    ``behind``. ``None`` when the viewpoint lies inside a footprint (every direction)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    if len(boxes) == 0:
        return np.zeros((0, 5))
    if known is None:
        known = _box_windows(boxes, viewpoint)
    centre, az_low, az_high, el_low, el_high, nearest = known
    if not np.isfinite(nearest).all():
        return None
    low, high = centre + az_low, centre + az_high
    if not behind:
        nearest = np.full(len(boxes), -np.inf)
    spans = []
    for m in range(len(boxes)):
        parts = [(low[m], high[m])]
        if low[m] < -math.pi:  # the window crosses the azimuth seam at +-pi
            parts = [(-math.pi, high[m]), (low[m] + 2 * math.pi, math.pi)]
        elif high[m] > math.pi:
            parts = [(low[m], math.pi), (-math.pi, high[m] - 2 * math.pi)]
        spans += [(start, stop, el_low[m], el_high[m], nearest[m]) for start, stop in parts]
    return np.array(spans, dtype=np.float64)


def _in_windows(
    points: np.ndarray, windows: np.ndarray | None, viewpoint: np.ndarray
) -> np.ndarray:
    """``bool (N,)``: points ``(N, 3+)`` in any of ``windows`` (:func:`_window_spans`; ``None``:
    every direction) seen from ``viewpoint`` ``(3,)``."""
    if windows is None:
        return np.ones(len(points), dtype=bool)
    inside = np.zeros(len(points), dtype=bool)
    if len(points) and len(windows):
        _window_scan(np.asarray(points), np.asarray(viewpoint, dtype=np.float64), windows, inside)
    return inside


@nb.njit(cache=True, nogil=True)
def _window_scan(points, viewpoint, windows, inside):  # pragma: no cover - numba
    # Per point, its direction and distance as FrameGrid's (libm's atan2: numpy's vectorised
    # arctan2 may differ in the last bit on some CPUs), then the windows in order until one
    # holds it (radians, metres).
    for i in range(points.shape[0]):
        x = np.float64(points[i, 0]) - viewpoint[0]
        y = np.float64(points[i, 1]) - viewpoint[1]
        z = np.float64(points[i, 2]) - viewpoint[2]
        azimuth, elevation = math.atan2(y, x), math.atan2(z, math.sqrt(x * x + y * y))
        distance = math.sqrt(x * x + y * y + z * z)
        for w in range(windows.shape[0]):
            if (
                azimuth >= windows[w, 0]
                and azimuth <= windows[w, 1]
                and elevation >= windows[w, 2]
                and elevation <= windows[w, 3]
                and distance >= windows[w, 4]
            ):
                inside[i] = True
                break


def _box_windows(boxes: np.ndarray, viewpoint: np.ndarray) -> tuple[np.ndarray, ...]:
    """View windows of ``(M, 7)`` boxes seen from ``viewpoint``, each ``(M,)``: centre
    azimuth, azimuth low and high relative to it, elevation low and high (radians), and the
    distance of the box's nearest point (metres; ``inf`` when the viewpoint lies inside the
    footprint, whose window is then every direction)."""
    corners = bev_corners(boxes) - viewpoint[:2]  # (M, 4, 2)
    cos, sin = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    dx, dy = viewpoint[0] - boxes[:, 0], viewpoint[1] - boxes[:, 1]
    local = np.column_stack([dx * cos + dy * sin, -dx * sin + dy * cos])
    gap = np.maximum(np.abs(local) - boxes[:, 3:5] / 2.0, 0.0)
    near = np.hypot(gap[:, 0], gap[:, 1])  # nearest footprint point, horizontally
    far = np.hypot(corners[..., 0], corners[..., 1]).max(axis=1)
    centre = np.arctan2(boxes[:, 1] - viewpoint[1], boxes[:, 0] - viewpoint[0])
    spread = wrap_angle(np.arctan2(corners[..., 1], corners[..., 0]) - centre[:, None])
    top = boxes[:, 2] + boxes[:, 5] / 2.0 - viewpoint[2]
    bottom = boxes[:, 2] - boxes[:, 5] / 2.0 - viewpoint[2]
    el_high = np.arctan2(top, np.where(top > 0, near, far))
    el_low = np.arctan2(bottom, np.where(bottom < 0, near, far))
    vertical = np.maximum(np.maximum(bottom, 0.0), -top)
    nearest = np.where(near > 0, np.hypot(near, vertical), np.inf)
    return centre, spread.min(axis=1), spread.max(axis=1), el_low, el_high, nearest


# --------------------------------------------------------------------------------------------
# Building transforms from configs
# --------------------------------------------------------------------------------------------
TRANSFORMS: dict[str, type[Transform]] = {
    "Compose": Compose,
    "GlobalFlip": GlobalFlip,
    "GlobalRotation": GlobalRotation,
    "GlobalScaling": GlobalScaling,
    "GroundTruthSampling": GroundTruthSampling,
    "DRCPO": DRCPO,
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
def _known_occlusion(frame: Frame) -> np.ndarray:
    """KITTI occlusion levels of the frame's boxes: known levels kept, unknown ones 3."""
    levels = np.asarray(frame.metadata.get("occlusion", ()), dtype=np.int64)
    if levels.shape != (len(frame.boxes),):
        levels = np.full(len(frame.boxes), 3)
    return np.where((levels >= 0) & (levels <= 3), levels, 3)


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
    inputs: Sequence[str | os.PathLike] = (),
) -> dict[str, Any]:
    """Augment frames of a KITTI split and write them in KITTI layout under ``out``.

    Writes ``training/velodyne/*.bin`` (float32, the frame's point columns),
    ``training/label_2/*.txt`` (:func:`drcpo.datasets.kitti_writer.label_lines` through the
    frame's calibration; truncation and 2D boxes from the projection of the augmented boxes,
    occlusion levels of original boxes kept, 3 "unknown" for inserted ones),
    ``training/calib/*.txt`` (copied),
    ``ImageSets/<split>.txt`` and ``stats.jsonl`` (one JSON object per frame: ``frame_id``,
    ``points``, ``boxes`` per class and the transform's statistics), and last ``augment.json``
    (:data:`AUGMENT_OUTPUT`'s marker: the source, split, frames, seed). Everything is written to
    a temporary directory renamed to ``out`` at the end (:func:`drcpo.outputs.write_directory`),
    so an interrupted run leaves nothing; ``overwrite`` replaces only an earlier augment output.

    Args:
        root: KITTI root; split: split name; transform: the augmentation.
        frames: augment the first ``frames`` frames of the split (``None``: all).
        seed: frame i uses :func:`frame_seed` ``(seed, i)``.
        fov_only: cut frames to the camera's field of view first (as OpenPCDet trains KITTI);
            frames then carry ``metadata["fov_only"] = True``.
        progress: ``progress(done, total)`` after each frame.
        inputs: other paths the transform reads (the database): ``out`` may not be or contain
            them, nor ``root``.

    Returns a summary: frames written, points and boxes per class over all frames, mean ms.
    """
    from drcpo.datasets import kitti_writer
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
                kitti_writer.write_points(base / "velodyne" / f"{frame_id}.bin", result.points)
                lines = kitti_writer.label_lines(
                    result.boxes,
                    result.names,
                    result.metadata["calib"],
                    occlusion=_known_occlusion(result),
                    image_shape=dataset.image_shape(frame_id),
                )
                kitti_writer.write_labels(base / "label_2" / f"{frame_id}.txt", lines)
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
        marker = {
            "format": AUGMENT_OUTPUT.format,
            "format_version": 1,
            "source": str(Path(root).resolve()),
            "split": split,
            "frames": len(ids),
            "seed": int(seed),
            "fov_only": bool(fov_only),
        }
        (tmp / AUGMENT_OUTPUT.marker).write_text(json.dumps(marker, indent=2) + "\n")

    write_directory(out, write, AUGMENT_OUTPUT, overwrite, [root, *inputs])
    summary["mean_ms"] = float(np.mean(summary["ms"])) if summary["ms"] else 0.0
    summary["median_ms"] = float(np.median(summary["ms"])) if summary["ms"] else 0.0
    del summary["ms"]
    return summary


def build_pipeline(
    config: Any = None,
    database: GroundTruthDatabase | None = None,
    index: Any = None,
    kind: str | None = None,
) -> Compose:
    """The augmentation pipeline a configuration describes.

    Args:
        config: an :class:`~drcpo.config.AugmentConfig`, a mapping, a YAML path or a preset name
            (anything :func:`drcpo.config.load_config` reads); ``None``: the paper defaults.
        database: the ground-truth database (needed by ground-truth sampling and DR.CPO).
        index: its candidate index; loaded from ``database.path / "index"`` when ``None`` and
            DR.CPO is enabled.
        kind: ``"drcpo"`` (ground-truth sampling, DR.CPO, global augmentation: the paper's
            reference configuration) or ``"cda"`` (the conventional baseline: ground-truth
            sampling, global augmentation); default: the config's ``pipeline`` key.

    Stages whose ``enabled`` key is false are left out.
    """
    from drcpo.config import PIPELINES, load_config

    config = load_config(config)
    kind = kind or config.pipeline
    if kind not in PIPELINES:
        raise ConfigError(f"pipeline {kind!r} is unknown; choose one of: {', '.join(PIPELINES)}")
    needs_db = config.gt_sampling.enabled or (kind == "drcpo" and config.drcpo.enabled)
    if needs_db and database is None:
        raise ConfigError(f"the {kind} pipeline needs a ground-truth database")
    transforms: list[Transform] = []
    if config.gt_sampling.enabled:
        transforms.append(GroundTruthSampling.from_settings(config.gt_sampling, database))
    if kind == "drcpo" and config.drcpo.enabled:
        if index is None:
            from drcpo.index import load_index

            index = load_index(database)
        transforms.append(DRCPO(database, index, config.drcpo))
    aug = config.global_augmentation
    if aug.enabled:
        transforms += [
            GlobalFlip(aug.flip.probability, aug.flip.axes),
            GlobalRotation(aug.rotation.range),
            GlobalScaling(aug.scaling.range),
        ]
    return Compose(transforms)
