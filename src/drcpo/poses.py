"""Random poses of boxes for placement (DR.CPO, step 4): the draws, before any check.

A pose is a heading uniform in ``[-pi, pi)`` and a centre uniform over the positions whose whole
BEV footprint lies inside the placement area (with a field of view, also every footprint corner
at an azimuth ``|atan2(y, x)| <= half_angle``), drawn by :func:`draw_poses`. Positions that fit
the area but leave the field of view are drawn again (up to :data:`FOV_ROUNDS` times), which
keeps the draw uniform over the positions that fit.

The placement checks (:mod:`drcpo.placement`) decide afterwards whether a pose is kept.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from drcpo.errors import DataError
from drcpo.geometry import heading_terms

__all__ = [
    "FOV_ROUNDS",
    "check_dims",
    "draw_poses",
    "in_fov",
]

FOV_ROUNDS = 32  # resampling rounds for positions outside the field of view (or the area)


def draw_poses(
    dims: np.ndarray,
    rng: np.random.Generator,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    half_angle: float | None = None,
    own: tuple[str, float | None, np.ndarray | None] = ("random", None, None),
) -> np.ndarray:
    """Random boxes ``float64 (K, 7)`` of sizes ``dims`` ``(K, 3)`` (metres).

    Heading uniform in ``[-pi, pi)``; centre uniform over the positions whose whole footprint
    lies in the area (``x_range`` x ``y_range``, metres) and, with ``half_angle`` (radians),
    the field of view; ``z = dz / 2`` (bottom at 0). Rows that cannot fit (or found no
    fitting position in :data:`FOV_ROUNDS` + 1 draws) have NaN x and y.

    ``own`` = (location, heading range, the objects' own boxes ``(K, 7)``), the paper's
    ablations: location ``"source"`` keeps each object's own centre (NaN where its footprint
    leaves the area or the field of view); a heading range (radians) turns each object from
    its own heading by an angle uniform in ``[-range, range)``.
    """
    dims = check_dims(dims)
    location, heading_range, source = own
    if heading_range is None:
        heading = rng.uniform(-np.pi, np.pi, len(dims))
    else:
        turned = source[:, 6] + rng.uniform(-heading_range, heading_range, len(dims))
        heading = np.mod(turned + np.pi, 2.0 * np.pi) - np.pi
    boxes = np.column_stack([np.zeros((len(dims), 3)), dims, heading])
    boxes[:, 2] = dims[:, 2] / 2.0
    # numpy's cos and sin, as geometry.bev_corners uses them
    cos, sin = np.cos(heading), np.sin(heading)
    area = (*map(float, x_range), *map(float, y_range))
    half = -1.0 if half_angle is None else float(half_angle)
    if location == "source":
        return _at_own_centres(boxes, source, cos, sin, area, half)
    # Each round draws the rows given and returns those to draw again: those that fit but
    # leave the field of view (none without one).
    todo = _draw_round(boxes, np.arange(len(dims)), cos, sin, rng, area, half)
    for _ in range(FOV_ROUNDS):
        if len(todo) == 0:
            break
        todo = _draw_round(boxes, todo, cos, sin, rng, area, half)
    boxes[todo, :2] = np.nan
    return boxes


def _at_own_centres(boxes, source, cos, sin, area, half_angle) -> np.ndarray:
    boxes[:, :2] = source[:, :2]
    reach_x = (np.abs(cos) * boxes[:, 3] + np.abs(sin) * boxes[:, 4]) / 2.0
    reach_y = (np.abs(sin) * boxes[:, 3] + np.abs(cos) * boxes[:, 4]) / 2.0
    x0, x1, y0, y1 = area
    fits = (boxes[:, 0] - reach_x >= x0) & (boxes[:, 0] + reach_x <= x1)
    fits &= (boxes[:, 1] - reach_y >= y0) & (boxes[:, 1] + reach_y <= y1)
    if half_angle >= 0:
        fits &= in_fov(boxes, half_angle)
    boxes[~fits, :2] = np.nan
    return boxes


def own_poses(source_boxes: np.ndarray | None, count: int) -> np.ndarray:
    """The objects' own boxes ``float64 (count, 7)`` for placement's ``location="source"`` or
    ``heading_range``; DataError when they are missing, of another count or not finite."""
    if source_boxes is None:
        raise DataError("placement from the objects' own poses needs their boxes (None given)")
    source_boxes = np.asarray(source_boxes, dtype=np.float64).reshape(-1, 7)
    if len(source_boxes) != count:
        raise DataError(f"source_boxes has {len(source_boxes)} rows; dims has {count}")
    if not np.isfinite(source_boxes[:, [0, 1, 6]]).all():
        raise DataError("source_boxes hold a non-finite x, y or heading")
    return source_boxes


def in_fov(boxes: np.ndarray, half_angle: float) -> np.ndarray:
    """``bool (K,)``: every BEV corner of ``(K, 7)`` boxes at an azimuth within ``half_angle``
    (radians; NaN rows: False)."""
    inside = np.zeros(len(boxes), dtype=bool)
    if len(boxes):
        _fov_test(boxes, *heading_terms(boxes), float(half_angle), inside)
    return inside


def check_dims(dims: np.ndarray) -> np.ndarray:
    """``dims`` as ``float64 (K, 3)`` positive finite box sizes; DataError naming the bad row."""
    dims = np.asarray(dims, dtype=np.float64)
    if dims.size == 0:
        return dims.reshape(0, 3)
    if dims.ndim != 2 or dims.shape[1] != 3:
        raise DataError(f"dims must have shape (K, 3), got {dims.shape}")
    if not (np.isfinite(dims).all() and (dims > 0).all()):
        bad = int(np.flatnonzero(~(np.isfinite(dims) & (dims > 0)).all(axis=1))[0])
        raise DataError(f"dims[{bad}] = {dims[bad].tolist()} is not a positive finite size")
    return dims


class _Field(NamedTuple):
    """Where centres may go: the area's bounds, and the field of view's half angle (< 0: none)."""

    x0: float
    x1: float
    y0: float
    y1: float
    half_angle: float


class _Poses(NamedTuple):
    """The poses being drawn: boxes ``(M, 7)``, written in place, and their headings' terms."""

    boxes: np.ndarray
    cos: np.ndarray
    sin: np.ndarray


def _draw_round(
    boxes: np.ndarray,
    rows: np.ndarray,
    cos: np.ndarray,
    sin: np.ndarray,
    rng: np.random.Generator,
    area: tuple[float, float, float, float],
    half_angle: float,
) -> np.ndarray:
    """Draw centres for ``rows`` of ``boxes`` in place (NaN where the footprint cannot fit);
    the rows to draw again (``half_angle`` < 0: no field of view)."""
    u = rng.uniform(0.0, 1.0, (len(rows), 2))
    return _centres(_Poses(boxes, cos, sin), rows, u, _Field(*area, half_angle))


@numba.njit(cache=True, nogil=True, inline="always")
def _centre_bounds(poses, r, field):  # pragma: no cover - numba
    # The centres whose footprint's bounds (half extents) stay in the field's area:
    # low_x, high_x, low_y, high_y (empty when a low exceeds its high).
    box, c, s = poses.boxes[r], abs(poses.cos[r]), abs(poses.sin[r])
    reach_x = (c * box[3] + s * box[4]) / 2.0
    reach_y = (s * box[3] + c * box[4]) / 2.0
    return field.x0 + reach_x, field.x1 - reach_x, field.y0 + reach_y, field.y1 - reach_y


@numba.njit(cache=True, nogil=True, inline="always")
def _leaves_fov(poses, r, field):  # pragma: no cover - numba
    return field.half_angle >= 0 and not _corners_in_fov(
        poses.boxes[r], poses.cos[r], poses.sin[r], field.half_angle
    )


@numba.njit(cache=True, nogil=True)
def _centres(poses, rows, u, field):  # pragma: no cover - numba
    # Uniform over the centres whose footprint's bounds (half extents) stay in the area.
    boxes = poses.boxes
    outside = np.empty(rows.shape[0], np.int64)
    count = 0
    for k in range(rows.shape[0]):
        r = rows[k]
        low_x, high_x, low_y, high_y = _centre_bounds(poses, r, field)
        if low_x > high_x or low_y > high_y:
            boxes[r, 0] = boxes[r, 1] = np.nan
            continue
        boxes[r, 0] = low_x + u[k, 0] * (high_x - low_x)
        boxes[r, 1] = low_y + u[k, 1] * (high_y - low_y)
        if _leaves_fov(poses, r, field):
            outside[count] = r
            count += 1
    return outside[:count].copy()


@numba.njit(cache=True, nogil=True)
def _fov_test(boxes, cos, sin, half_angle, inside):  # pragma: no cover - numba
    for m in range(boxes.shape[0]):
        inside[m] = np.isfinite(boxes[m, 0]) and _corners_in_fov(
            boxes[m], cos[m], sin[m], half_angle
        )


@numba.njit(cache=True, nogil=True, inline="always")
def _corners_in_fov(box, cos, sin, half_angle):  # pragma: no cover - numba
    # The corners as geometry.bev_corners computes them (counter-clockwise from front-left).
    for corner_x, corner_y in ((0.5, 0.5), (-0.5, 0.5), (-0.5, -0.5), (0.5, -0.5)):
        local_x, local_y = corner_x * box[3], corner_y * box[4]
        x = (cos * local_x - sin * local_y) + box[0]
        y = (sin * local_x + cos * local_y) + box[1]
        if not abs(math.atan2(y, x)) <= half_angle:
            return False
    return True
