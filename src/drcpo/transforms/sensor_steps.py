"""DR.CPO's sensor-true steps: what the ``realistic`` preset changes in :class:`~drcpo.DRCPO`.

* the frame's sensor (``drcpo.sensor``: a preset, or estimated from the frame's own points);
* the ground and the sensor estimated from the frame *without* the objects earlier stages added
  (ground-truth sampling's boxes: their points were recorded in other frames);
* the cheap visibility test of a placed box, before anything is built: enough of the sensor's
  rays reach it in front of the frame's returns and of the boxes placed before
  (:meth:`~drcpo.occlusion.rays.RangeImage.visible_rays`);
* s-HPR mode ``sensor``: each object rendered through the sensor
  (:func:`~drcpo.occlusion.render.render_object`);
* e-HPR mode ``sensor``: occlusion along the rays (:func:`~drcpo.occlusion.rays.ray_occlusion`),
  with the added boxes of earlier stages as inserted objects too.

Each function returns data; :mod:`drcpo.transforms.drcpo` orders the steps.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from drcpo.errors import DataError
from drcpo.frame import Frame
from drcpo.ground import GroundModel
from drcpo.occlusion.rays import RangeImage, ray_occlusion
from drcpo.occlusion.render import render_object
from drcpo.placement import frame_ground
from drcpo.sensor import Sensor, SensorConfig
from drcpo.transforms.insertion import BOX_SOURCE, BoxQuery, take_rows

__all__ = ["SensorFrame", "added_boxes", "render", "sensor_occlusion"]

_ADDED_MARGIN = 0.2  # metres around an added box whose points count as the added object's


def added_boxes(frame: Frame) -> np.ndarray:
    """``bool (M,)``: the frame's boxes that an earlier stage added (``box_source`` not ``""``)."""
    sources = frame.metadata.get(BOX_SOURCE)
    if sources is None or np.ndim(sources) != 1 or len(sources) != len(frame.boxes):
        return np.zeros(len(frame.boxes), dtype=bool)
    return np.asarray(sources) != ""


@dataclass(eq=False)
class SensorFrame:
    """One frame as the sensor-true steps see it (built lazily, once per call).

    Args:
        frame: the frame DR.CPO receives.
        config: its ``drcpo.sensor`` section.
    """

    frame: Frame
    config: SensorConfig
    fallback: str = field(default="", init=False)

    @cached_property
    def added(self) -> np.ndarray:
        """``bool (M,)``: boxes added by earlier stages (see :func:`added_boxes`)."""
        return added_boxes(self.frame)

    @cached_property
    def added_owner(self) -> np.ndarray:
        """``int64 (N,)``: the added box (numbered among the added ones) holding each frame
        point, -1 for the frame's own points."""
        boxes = self.frame.boxes[self.added]
        if len(boxes) == 0:
            return np.full(len(self.frame), -1, dtype=np.int64)
        # (grown: a sampled object brings points up to a few cm outside its box)
        return BoxQuery(self.frame.points).owners(boxes, margin=_ADDED_MARGIN)

    @cached_property
    def own_points(self) -> np.ndarray:
        """The frame's points without those of added objects."""
        if not self.added.any():
            return self.frame.points
        return take_rows(self.frame.points, self.added_owner < 0)

    @cached_property
    def sensor(self) -> Sensor:
        """The frame's sensor (``auto``: estimated from its own points; where a frame is too
        sparse or unordered to estimate from, the model's base sensor, noted in
        :attr:`fallback`)."""
        try:
            return self.config.sensor_for(self.own_points)
        except DataError as exc:
            self.fallback = str(exc)
            return self.config.base()

    def record(self) -> dict[str, Any] | None:
        """What :attr:`sensor` was, for the statistics; ``None`` when no step needed it."""
        if "sensor" not in self.__dict__:  # cached_property keeps its value there
            return None
        sensor = self.sensor
        return {
            "model": sensor.name,
            "beams": sensor.num_beams,
            "azimuth_step_deg": round(math.degrees(sensor.azimuth_step), 6),
            "fallback": self.fallback,
        }

    @cached_property
    def ground(self) -> GroundModel:
        """The ground estimated from the frame before earlier stages added objects."""
        frame = self.frame
        if self.added.any():
            frame = frame.replace(points=self.own_points)
        return frame_ground(frame)

    @cached_property
    def range_image(self) -> RangeImage:
        """The frame's nearest return per ray cell (added objects included: they hide too)."""
        return RangeImage.build(self.frame.points, self.sensor)

    def hidden(self, boxes: np.ndarray, placed: np.ndarray, min_rays: int) -> np.ndarray:
        """``bool (B,)``: the round's ``boxes`` to reject, first come first served: a box that
        fewer than ``min_rays`` rays would reach (in front of the frame's returns and of the
        boxes accepted before it, ``placed`` and this round's), or that would leave one of
        those with fewer (objects in a row along a street would hide each other)."""
        image = self.range_image
        hidden = np.zeros(len(boxes), dtype=bool)
        accepted = np.asarray(placed, dtype=np.float64).reshape(-1, 7)
        spans = _azimuth_spans(accepted)
        for i in range(len(boxes)):
            box = boxes[i : i + 1]
            if image.visible_rays(box, occluders=accepted if len(accepted) else None)[0] < min_rays:
                hidden[i] = True
                continue
            span = _azimuth_spans(box)
            behind = np.flatnonzero(_overlapping(spans, span[0]))
            if len(behind):
                occluders = np.concatenate([accepted, box])
                if (image.visible_rays(accepted[behind], occluders=occluders) < min_rays).any():
                    hidden[i] = True
                    continue
            accepted = np.concatenate([accepted, box])
            spans = np.concatenate([spans, span])
        return hidden


def _azimuth_spans(boxes: np.ndarray) -> np.ndarray:
    """``float64 (B, 2)``: each box's azimuth interval seen from the origin (centre azimuth
    +- the half angle its bounding circle covers; the whole circle when it holds the origin)."""
    centre = np.arctan2(boxes[:, 1], boxes[:, 0])
    reach = np.hypot(boxes[:, 3], boxes[:, 4]) / 2.0
    distance = np.hypot(boxes[:, 0], boxes[:, 1])
    half = np.where(
        distance > reach, np.arcsin(np.minimum(reach / np.maximum(distance, 1e-9), 1.0)), np.pi
    )
    return np.column_stack([centre, half])


def _overlapping(spans: np.ndarray, span: np.ndarray) -> np.ndarray:
    """``bool (B,)``: ``spans`` (centre, half angle) that overlap ``span``."""
    gap = np.abs((spans[:, 0] - span[0] + np.pi) % (2.0 * np.pi) - np.pi)
    return gap <= spans[:, 1] + span[1]


def render(points: np.ndarray, sensor: Sensor, seed: int) -> np.ndarray:
    """An object's placed ``points`` as ``sensor`` records them (its own generator from
    ``seed``, so the answer does not depend on which thread renders it)."""
    returns, _ = render_object(points, sensor, np.random.default_rng(seed))
    return returns


def sensor_occlusion(
    points: np.ndarray,
    owner: np.ndarray,
    added_owner: np.ndarray,
    sensor: Sensor,
    count_kept: Callable[[np.ndarray], np.ndarray],
) -> tuple[np.ndarray, np.ndarray]:
    """e-HPR along the sensor's rays: points kept ``bool (N,)`` and DR.CPO's objects dropped
    ``bool (A,)``.

    Args:
        points: the frame's points then the inserted objects' (``owner`` >= 0: object number).
        owner: ``int64 (N,)``; -1 for the frame's points.
        added_owner: ``int64 (F,)`` for the frame's ``F`` points, the earlier-added object
            holding each (-1: none); those objects occlude and are occluded like DR.CPO's.
        sensor: the frame's sensor.
        count_kept: given ``keep`` of the inserted points (``bool (N - F,)``), how many each
            DR.CPO object keeps that count for its label; objects below the minimum return
            ``True``.

    Two passes: the first decides which DR.CPO objects keep too few returns (dropped); the
    second, without them, decides every point, so a dropped object hides nothing.
    """
    first = len(added_owner)
    num_drcpo = int(owner.max()) + 1 if len(owner) > first else 0
    combined = owner.copy()
    combined[:first] = np.where(added_owner >= 0, added_owner + num_drcpo, -1)
    removed = ray_occlusion(points, combined, sensor)
    dropped = count_kept(~removed[first:])
    if dropped.any():
        live = ~((owner >= 0) & np.append(dropped, False)[owner])
        removed = np.ones(len(points), dtype=bool)
        removed[live] = ray_occlusion(take_rows(points, live), _renumbered(combined[live]), sensor)
    return ~removed, dropped


def _renumbered(owner: np.ndarray) -> np.ndarray:
    """``owner`` with its objects numbered 0, 1, ... in order (-1 stays)."""
    objects = owner >= 0
    out = owner.copy()
    out[objects] = np.unique(owner[objects], return_inverse=True)[1]
    return out
