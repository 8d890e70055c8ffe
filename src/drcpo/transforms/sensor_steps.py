"""DR.CPO's sensor-true steps: what the ``realistic`` preset changes in :class:`~drcpo.DRCPO`.

* :func:`frame_sensor`: the frame's sensor (``drcpo.sensor``: a preset, or estimated from the
  frame's own points);
* :func:`own_ground`: the ground estimated from the frame *without* the objects earlier stages
  added (ground-truth sampling's boxes: their points were recorded in other frames), for
  ``placement.height: observed``;
* :func:`render`: s-HPR mode ``sensor``, each object rendered through the sensor
  (:func:`~drcpo.occlusion.render.render_object`).

Each function takes data and returns data; :mod:`drcpo.transforms.drcpo` orders the steps.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from drcpo.errors import DataError
from drcpo.frame import Frame
from drcpo.ground import GroundModel
from drcpo.occlusion.render import render_object
from drcpo.placement import frame_ground
from drcpo.sensor import Sensor
from drcpo.sensor_config import SensorConfig
from drcpo.transforms.insertion import BOX_SOURCE, BoxQuery, take_rows

__all__ = ["added_boxes", "frame_sensor", "own_ground", "own_points", "render"]

_ADDED_MARGIN = 0.2  # metres around an added box whose points count as the added object's


def added_boxes(frame: Frame) -> np.ndarray:
    """``bool (M,)``: the frame's boxes that an earlier stage added (``box_source`` not ``""``)."""
    sources = frame.metadata.get(BOX_SOURCE)
    if sources is None or np.ndim(sources) != 1 or len(sources) != len(frame.boxes):
        return np.zeros(len(frame.boxes), dtype=bool)
    return np.asarray(sources) != ""


def own_points(frame: Frame) -> np.ndarray:
    """The frame's points without those of objects earlier stages added (a sampled object
    brings points up to a few cm outside its box, so its box is grown by ``_ADDED_MARGIN``)."""
    added = added_boxes(frame)
    if not added.any():
        return frame.points
    owner = BoxQuery(frame.points).owners(frame.boxes[added], margin=_ADDED_MARGIN)
    return take_rows(frame.points, owner < 0)


def frame_sensor(points: np.ndarray, config: SensorConfig) -> tuple[Sensor, dict[str, Any]]:
    """The sensor that recorded ``points`` (the frame's own, see :func:`own_points`) and what
    it was, for the statistics. ``auto`` estimates it from the points; where they are too
    sparse or unordered to estimate from, the model's base sensor, the reason in
    ``fallback``."""
    fallback = ""
    try:
        sensor = config.sensor_for(points)
    except DataError as exc:
        fallback = str(exc)
        sensor = config.base()
    used = {
        "model": sensor.name,
        "beams": sensor.num_beams,
        "azimuth_step_deg": round(math.degrees(sensor.azimuth_step), 6),
        "fallback": fallback,
    }
    return sensor, used


def own_ground(frame: Frame, points: np.ndarray) -> GroundModel:
    """The ground estimated from ``points``, the frame's own (see :func:`own_points`)."""
    return frame_ground(frame if points is frame.points else frame.replace(points=points))


def render(
    points: np.ndarray, sensor: Sensor, seed: int, max_radius: float | None = None
) -> np.ndarray:
    """An object's placed ``points`` as ``sensor`` records them (its own generator from
    ``seed``, so the answer does not depend on when it is rendered); ``max_radius``: the
    upper clip of its surface elements' radii (see :func:`~drcpo.occlusion.render.radius_cap`)."""
    rng = np.random.default_rng(seed)
    returns, _ = render_object(points, sensor, rng, max_radius=max_radius)
    return returns
