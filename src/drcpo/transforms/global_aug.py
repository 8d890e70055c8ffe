"""Global augmentation: flip, rotation and scaling of the whole scene (the conventional
baseline's last stages, and DR.CPO's pipeline's)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numba as nb
import numpy as np

from drcpo.config import FlipConfig, RotationConfig, ScalingConfig, from_dict
from drcpo.frame import Frame
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
            return frame.replace(points=points, boxes=boxes)


@nb.njit(cache=True, nogil=True)
def _scale_rows(points, scale):  # pragma: no cover - numba
    # x, y, z times ``scale`` in float64, stored back (as numpy's assignment casts).
    for i in range(points.shape[0]):
        for c in range(3):
            points[i, c] = np.float64(points[i, c]) * scale
