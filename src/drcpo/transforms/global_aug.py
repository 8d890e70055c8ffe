"""Global augmentation: flip, rotation and scaling of the whole scene (the conventional
baseline's last stages, and DR.CPO's pipeline's).

The boxes' velocities (``metadata["velocity"]``, ``(M, 2)``, when a frame has them) move with
the scene as OpenPCDet's ``augmentor_utils`` moves the velocity columns of its 9-value boxes:
a flip negates the flipped component, a rotation turns them, a scaling scales them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numba as nb
import numpy as np

from drcpo.config import FlipConfig, RotationConfig, ScalingConfig, from_dict
from drcpo.frame import VELOCITY, Frame, rotate_velocities
from drcpo.geometry import rotate_points_z, wrap_angle
from drcpo.transforms.base import Stats, Transform, config_body, register

__all__ = ["GlobalFlip", "GlobalRotation", "GlobalScaling"]


@register
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
        return cls(**config_body(data, cls.__name__))

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
            velocity = _velocity(frame)
            if velocity is not None and record["flipped"][0]:
                velocity = velocity.copy()
                for axis in record["flipped"][0]:
                    column = 1 if axis == "x" else 0  # the flipped coordinate's component
                    velocity[:, column] = -velocity[:, column]
                return frame.replace(
                    points=points, boxes=boxes, metadata={**frame.metadata, VELOCITY: velocity}
                )
            return frame.replace(points=points, boxes=boxes)


@register
class GlobalRotation(Transform):
    """Rotate the whole scene about z by an angle uniform in ``range`` (radians)."""

    name = "global_rotation"

    def __init__(self, range: Sequence[float] = (-math.pi / 4, math.pi / 4)) -> None:
        self.config: RotationConfig = from_dict(
            RotationConfig, {"range": list(range)}, "GlobalRotation"
        )

    @classmethod
    def from_config(cls, data: Mapping[str, Any], **_: Any) -> GlobalRotation:
        return cls(**config_body(data, cls.__name__))

    def apply(self, frame: Frame, rng: np.random.Generator, stats: Stats) -> Frame:
        with stats.stage(self.name, len(frame)) as record:
            low, high = self.config.range
            angle = rng.uniform(low, high)
            record["angle"] = [float(angle)]
            points = rotate_points_z(frame.points, angle)
            boxes = rotate_points_z(frame.boxes, angle)
            boxes[:, 6] = wrap_angle(boxes[:, 6] + angle)
            velocity = _velocity(frame)
            if velocity is not None:
                metadata = {**frame.metadata, VELOCITY: rotate_velocities(velocity, angle)}
                return frame.replace(points=points, boxes=boxes, metadata=metadata)
            return frame.replace(points=points, boxes=boxes)


@register
class GlobalScaling(Transform):
    """Scale the whole scene (points and boxes) by a factor uniform in ``range``."""

    name = "global_scaling"

    def __init__(self, range: Sequence[float] = (0.95, 1.05)) -> None:
        self.config: ScalingConfig = from_dict(
            ScalingConfig, {"range": list(range)}, "GlobalScaling"
        )

    @classmethod
    def from_config(cls, data: Mapping[str, Any], **_: Any) -> GlobalScaling:
        return cls(**config_body(data, cls.__name__))

    def apply(self, frame: Frame, rng: np.random.Generator, stats: Stats) -> Frame:
        with stats.stage(self.name, len(frame)) as record:
            low, high = self.config.range
            scale = rng.uniform(low, high)
            record["scale"] = [float(scale)]
            points = frame.points.copy()
            _scale_rows(points, float(scale))
            boxes = frame.boxes.copy()
            boxes[:, :6] *= scale
            velocity = _velocity(frame)
            if velocity is not None:
                metadata = {**frame.metadata, VELOCITY: velocity * scale}
                return frame.replace(points=points, boxes=boxes, metadata=metadata)
            return frame.replace(points=points, boxes=boxes)


def _velocity(frame: Frame) -> np.ndarray | None:
    """The frame's box velocities ``float64 (M, 2)`` when it has one row per box, else
    ``None`` (left as they are)."""
    velocity = frame.metadata.get(VELOCITY)
    if velocity is None or np.shape(velocity) != (len(frame.boxes), 2):
        return None
    return np.asarray(velocity, dtype=np.float64)


@nb.njit(cache=True, nogil=True)
def _scale_rows(points, scale):  # pragma: no cover - numba
    # x, y, z times ``scale`` in float64, stored back (as numpy's assignment casts).
    for i in range(points.shape[0]):
        for c in range(3):
            points[i, c] = np.float64(points[i, c]) * scale
