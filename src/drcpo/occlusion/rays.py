"""Occlusion along the sensor's rays (``external_occlusion.mode: sensor``) and the cheap
"would it be seen" check of placement.

:class:`RangeImage` holds the frame's nearest return per ray cell (beam, column) of a
:class:`~drcpo.sensor.Sensor`; :meth:`RangeImage.visible_rays` counts, per box, the rays that
reach it; :class:`PlacedView` takes a placement round's boxes in turn, first come first
served, against the frame and the boxes accepted before (kept over a call's rounds).
:func:`ray_occlusion` decides, after insertion, which points the sensor could not have
recorded: an original point behind an inserted object's surface elements along its own ray, an
inserted return behind a nearer return in its ray cell or behind another object's surface;
:class:`RayOcclusion` keeps that work, so that the verdict without the objects then dropped
costs little more. The ray cells, surface elements and their windows are those of
:mod:`~drcpo.occlusion.render`. Imports :mod:`drcpo.errors`, :mod:`drcpo.geometry`,
:mod:`drcpo.sensor` and :mod:`drcpo.occlusion.render` only.

Longer than 800 lines because its numba kernels share one slab test, one window rule and the
cell look-ups of :mod:`~drcpo.occlusion.render`, which must stay exactly the same for the
box counts and the point verdicts to agree; split, they would be copied or exported across
modules as private kernels.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from drcpo.errors import ConfigError, DataError
from drcpo.geometry import heading_terms
from drcpo.occlusion.render import (
    RADIUS_FACTOR,
    RADIUS_RANGE,
    VOXEL,
    _check_radii,
    _column_at,
    _cone,
    _lut_bin,
    _point_cells,
    _pseudo_bin,
    _voxel_radii,
    point_cells,
    sensor_tables,
)
from drcpo.sensor import Sensor

__all__ = ["PlacedView", "RangeImage", "RayOcclusion", "element_radii", "ray_occlusion"]


class RangeImage:
    """The frame's nearest return per sensor ray cell (beam, column).

    Attributes:
        sensor: the LiDAR whose cells these are.
        ranges: ``float64 (B, C)`` distance of each cell's nearest return from its beam's
            origin, metres; ``inf`` where the cell holds none (read-only).
    """

    def __init__(self, sensor: Sensor, ranges: np.ndarray) -> None:
        ranges = np.asarray(ranges, dtype=np.float64)
        if ranges.shape != (sensor.num_beams, sensor.num_columns):
            raise DataError(
                f"ranges must have shape ({sensor.num_beams}, {sensor.num_columns}) for "
                f"sensor {sensor.name!r}, got {ranges.shape}"
            )
        ranges.setflags(write=False)
        self.sensor, self.ranges = sensor, ranges

    @classmethod
    def build(cls, points: np.ndarray, sensor: Sensor) -> RangeImage:
        """The range image of ``points`` ``(N, 3+)`` (metres, LiDAR frame): each point goes to
        its cell (:meth:`Sensor.cells`); points outside every beam are left out."""
        return cls.from_cells(sensor, *point_cells(_frame_points(points), sensor))

    @classmethod
    def from_cells(
        cls, sensor: Sensor, beam: np.ndarray, column: np.ndarray, distance: np.ndarray
    ) -> RangeImage:
        """The range image of points whose cells are known (:func:`~drcpo.occlusion.render.
        point_cells`: ``beam``, ``column`` ``int64 (N,)``, -1 for none; ``distance`` from the
        beam's origin, metres): :meth:`build` of those points, without finding the cells again."""
        ranges = np.full((sensor.num_beams, sensor.num_columns), np.inf)
        _nearest_per_cell(
            np.asarray(beam, dtype=np.int64),
            np.asarray(column, dtype=np.int64),
            np.asarray(distance, dtype=np.float64),
            ranges,
        )
        return cls(sensor, ranges)

    def with_boxes(self, boxes: np.ndarray) -> RangeImage:
        """This range image with ``boxes`` ``(K, 7)`` as solids: each cell whose ray enters
        one of them keeps the nearest of its return and those entries (distances from the
        beam's origin, within the box windows of :meth:`visible_rays`)."""
        boxes = _check_boxes(boxes, "boxes")
        if len(boxes) == 0:
            return self
        combined = np.array(self.ranges, dtype=np.float64)
        geometry = sensor_tables(self.sensor).geometry
        windows = _windows(boxes, *geometry)
        cos, sin = heading_terms(boxes)
        offsets, mount, beam_cos, beam_sin, column_cos, column_sin = geometry[4:10]
        for g in range(len(boxes)):
            _paint(g, boxes, cos, sin, windows, combined, offsets, mount, beam_cos, beam_sin,
                   column_cos, column_sin)  # fmt: skip
        return RangeImage(self.sensor, combined)

    def visible_rays(
        self,
        boxes: np.ndarray,
        occluders: np.ndarray | None = None,
        tolerance: float = 0.1,
    ) -> np.ndarray:
        """``int64 (M,)``: per box ``(M, 7)``, the sensor rays that reach it.

        A ray reaches a box when it crosses the box (slab test; entering it within the
        sensor's ``max_range``), its cell's frame return, if any, is no nearer than where the
        ray enters the box minus ``tolerance`` metres, and it enters none of ``occluders``
        ``(K, 7)`` (boxes placed before) more than ``tolerance`` nearer. The cheap "would it
        be seen" check of placement, before anything is built.
        """
        boxes = _check_boxes(boxes, "boxes")
        occluders = _check_boxes(np.zeros((0, 7)) if occluders is None else occluders, "occluders")
        tolerance = _check_tolerance(tolerance)
        counts = np.zeros(len(boxes), dtype=np.int64)
        if len(boxes) == 0:
            return counts
        tables = sensor_tables(self.sensor)
        box_windows = _windows(boxes, *tables.geometry)
        occluder_windows = _windows(occluders, *tables.geometry)
        _visible_rays(
            boxes,
            *heading_terms(boxes),
            box_windows,
            occluders,
            *heading_terms(occluders),
            occluder_windows,
            self.ranges,
            np.array([tolerance, self.sensor.max_range]),
            counts,
            *tables.geometry,
        )
        return counts


class PlacedView:
    """Placement's visibility test of one frame over its rounds: boxes taken in turn, first
    come first served, each rejected when too few of the sensor's rays would reach it or when
    it would leave a box accepted before with too few.

    A box needs ``max(min_rays, ceil((1 - max_hidden) * crossing))`` rays, ``crossing`` the
    rays that cross it (within ``max_range``); a ray reaches it as in
    :meth:`RangeImage.visible_rays` with the boxes accepted before as occluders. The view keeps
    the frame's nearest return per ray cell with the accepted boxes painted in (each ray's
    nearest entry into one of them: a ray reaches a box iff that is no nearer than where it
    enters the box, minus ``tolerance``) and each accepted box's rays left, so that a box
    costs its own rays only. Only boxes whose azimuth spans (bounding circles seen from the
    mount) overlap can hide each other.

    Args:
        image: the frame's range image.
        min_rays: fewest rays a box needs.
        max_hidden: the largest share of its crossing rays that may be hidden, in ``[0, 1]``.
        placed: ``(K, 7)`` boxes accepted before (counted against each other).
        tolerance: metres, as in :meth:`RangeImage.visible_rays`.

    Attributes:
        boxes: ``float64 (A, 7)`` the boxes accepted so far, ``placed`` first.
        need: ``int64 (A,)`` the rays each needs; ``left``: ``int64 (A,)`` the rays reaching
            each now.
    """

    def __init__(
        self,
        image: RangeImage,
        min_rays: int,
        max_hidden: float,
        placed: np.ndarray | None = None,
        tolerance: float = 0.1,
    ) -> None:
        if isinstance(min_rays, bool) or not isinstance(min_rays, (int, np.integer)):
            raise ConfigError(f"min_rays must be a whole number of rays, got {min_rays!r}")
        if not (isinstance(max_hidden, (int, float)) and 0.0 <= max_hidden <= 1.0):
            raise ConfigError(f"max_hidden must be a share in [0, 1], got {max_hidden!r}")
        self._image = image
        self._tables = sensor_tables(image.sensor)
        self._settings = np.array(
            [_check_tolerance(tolerance), image.sensor.max_range, int(min_rays), max_hidden]
        )
        self._combined = np.array(image.ranges, dtype=np.float64)  # a writable copy
        self.boxes = np.zeros((0, 7))
        self.need = np.zeros(0, dtype=np.int64)
        self.left = np.zeros(0, dtype=np.int64)
        placed = _check_boxes(np.zeros((0, 7)) if placed is None else placed, "placed")
        if len(placed):
            self._admit(placed, every=True)

    def admit(
        self,
        boxes: np.ndarray,
        groups: np.ndarray | None = None,
        conflicts: np.ndarray | None = None,
    ) -> np.ndarray:
        """``bool (M,)``: which of ``boxes`` ``(M, 7)``, taken in turn after the boxes accepted
        before, are rejected; the others are accepted (appended to :attr:`boxes`).

        ``groups`` ``int (M,)``: boxes of one group are alternatives (poses of one object): once
        one is accepted, the group's later boxes are passed over (neither rejected nor
        accepted, ``False``). ``conflicts`` ``bool (M, M)``: a box conflicting with one
        accepted before is passed over too (its caller rejects it for that)."""
        boxes = _check_boxes(boxes, "boxes")
        count = len(boxes)
        groups = np.arange(count) if groups is None else np.asarray(groups)
        if groups.shape != (count,) or (
            groups.size and not np.issubdtype(groups.dtype, np.integer)
        ):
            raise DataError(f"groups must be {count} integers, one per box, got {groups!r}")
        conflicts = np.zeros((count, count), bool) if conflicts is None else np.asarray(conflicts)
        if conflicts.shape != (count, count) or conflicts.dtype != bool:
            raise DataError(f"conflicts must be bool ({count}, {count}), got {conflicts.shape}")
        return self._admit(boxes, False, groups.astype(np.int64), conflicts)

    def holds(self, boxes: np.ndarray) -> bool:
        """Whether ``boxes`` ``(K, 7)`` are the boxes accepted so far, in any order."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        if len(boxes) != len(self.boxes):
            return False
        return sorted(map(bytes, boxes)) == sorted(map(bytes, self.boxes))

    def _admit(
        self,
        boxes: np.ndarray,
        every: bool,
        groups: np.ndarray | None = None,
        conflicts: np.ndarray | None = None,
    ) -> np.ndarray:
        """Take ``boxes`` in turn (``every``: accept them all, as boxes placed before, counted
        once all are painted in); ``groups``, ``conflicts``: see :meth:`admit`."""
        hidden = np.zeros(len(boxes), dtype=bool)
        if len(boxes) == 0:
            return hidden
        if groups is None:
            groups = np.arange(len(boxes), dtype=np.int64)
        if conflicts is None:
            conflicts = np.zeros((len(boxes), len(boxes)), dtype=bool)
        taken = np.zeros(len(boxes), dtype=bool)
        first = len(self.boxes)
        boxes_all = np.concatenate([self.boxes, boxes])
        need = np.concatenate([self.need, np.zeros(len(boxes), np.int64)])
        left = np.concatenate([self.left, np.zeros(len(boxes), np.int64)])
        geometry = self._tables.geometry
        _admit(
            boxes_all,
            *heading_terms(boxes_all),
            _windows(boxes_all, *geometry),
            first,
            every,
            need,
            left,
            self._combined,
            self._settings,
            groups,
            conflicts,
            hidden,
            taken,
            *geometry,
        )
        keep = np.concatenate([np.ones(first, dtype=bool), taken])
        self.boxes, self.need, self.left = boxes_all[keep], need[keep], left[keep]
        return hidden


def ray_occlusion(
    points: np.ndarray,
    owner: np.ndarray,
    sensor: Sensor,
    radii: np.ndarray | None = None,
    tolerance: float = 0.1,
) -> np.ndarray:
    """``bool (N,)``: the points the sensor could not have recorded after insertion.

    An original point (``owner == -1``) is removed iff an inserted object's surface element
    (point ``j`` with radius ``radii[j]``) lies within ``radii[j]`` of the point's own ray (from
    its beam's origin, the mount outside every beam, through the point), more than
    ``tolerance`` nearer than the point along it. An inserted return (``owner == k >= 0``) is
    removed iff, in its ray cell (:meth:`Sensor.cells`), an original point or a return of
    another object lies more than ``tolerance`` nearer, or another object's surface element
    crosses its own ray so.

    Args:
        points: ``(N, 3+)`` the frame after insertion, metres.
        owner: ``int (N,)``: -1 for the frame's own points, ``k`` for inserted object ``k``.
        sensor: the LiDAR.
        radii: the inserted points' surface-element radii, metres: ``(N,)`` (entries of
            original points ignored) or one per inserted point in order; by default
            :func:`~drcpo.occlusion.render.surfel_radii` of each object's points.
        tolerance: metres a surface must lie nearer to hide a point.
    """
    return RayOcclusion(points, owner, sensor, radii, tolerance).removed.copy()


class RayOcclusion:
    """:func:`ray_occlusion` of one frame after insertion, with its work (cells, surface
    elements and their windows) kept, so that the verdict without some of the objects costs
    little more (:meth:`without`).

    Args: as :func:`ray_occlusion`, and ``cells``: the points' ray cells and distances
    (:func:`~drcpo.occlusion.render.point_cells` of them), when known; found here otherwise.

    Attributes:
        removed: ``bool (N,)`` :func:`ray_occlusion` of all the points (read-only).
    """

    def __init__(
        self,
        points: np.ndarray,
        owner: np.ndarray,
        sensor: Sensor,
        radii: np.ndarray | None = None,
        tolerance: float = 0.1,
        cells: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> None:
        array = _frame_points(points)
        self._owner = owner = _check_owner(owner, len(array))
        self._tolerance = _check_tolerance(tolerance)
        self._inserted = inserted = np.flatnonzero(owner >= 0)
        self._radii = _inserted_radii(array, owner, inserted, radii)
        self._tables = tables = sensor_tables(sensor)
        self._objects = int(owner.max()) + 1 if len(inserted) else 0
        known = _known_cells(cells, len(array))
        elements, columns = self._windows(array, owner, known)
        index = _ray_index(array, owner, elements[0], elements[5], *columns, *known,
                           *tables.geometry)  # fmt: skip
        if index[0] >= 0:
            raise DataError(f"points hold NaN/inf coordinates (first: row {index[0]})")
        # (as _ray_decide takes them)
        self._index = (*elements[:5], columns[0], *index[1:])
        self.removed = self._decide(np.ones(self._objects, dtype=bool), None)
        self.removed.setflags(write=False)

    def _windows(
        self, array: np.ndarray, owner: np.ndarray, known: tuple[np.ndarray, ...]
    ) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
        """The inserted points' beams, columns, distances, offsets from the mount, objects and
        windows of cells, and per column the object whose windows reach it (-2: several, -1:
        none), whether it holds inserted returns and the elevation tangents that matter
        there (:func:`_element_windows`). Raises :class:`DataError` for a non-finite inserted
        point."""
        inserted, radii, tables = self._inserted, self._radii, self._tables.geometry
        m, columns = len(inserted), len(self._tables.column_cos)
        elements = (
            np.empty(m, np.int64), np.empty(m, np.int64), np.empty(m), np.empty((m, 3)),
            np.empty(m, np.int64), np.empty((m, 4), np.int64),
        )  # fmt: skip

        own = (np.full(columns, -1, np.int64), np.zeros(columns, np.bool_),
               np.full(columns, np.inf), np.full(columns, -np.inf))  # fmt: skip
        bad = _element_windows(array, owner, inserted, radii, *known, 0, m,
                               *elements, *own, *tables)  # fmt: skip
        if bad >= 0:
            raise DataError(f"points hold NaN/inf coordinates (first: row {bad})")
        return elements, own

    def without(self, objects: np.ndarray) -> np.ndarray:
        """``bool (N,)``: what :func:`ray_occlusion` removes of the points without those of
        ``objects`` (object numbers, or ``bool`` per object), as if those had never been
        inserted; their own points are ``True`` (removed with them).

        Taking objects out only takes surfaces away, so a point kept with them is kept
        without them: only the points :attr:`removed` are decided again."""
        alive = np.ones(self._objects, dtype=bool)
        gone = np.asarray(objects)
        if gone.dtype == bool:
            if gone.shape != (self._objects,):
                raise DataError(
                    f"objects mask must have shape ({self._objects},), got {gone.shape}"
                )
            alive &= ~gone
        else:
            gone = gone.astype(np.int64, copy=False).reshape(-1)
            if gone.size and (gone.min() < 0 or gone.max() >= self._objects):
                raise DataError(f"objects must be numbers in [0, {self._objects}), got {gone}")
            alive[gone] = False
        if alive.all():
            return self.removed.copy()
        return self._decide(alive, self.removed)

    def _decide(self, alive: np.ndarray, pending: np.ndarray | None) -> np.ndarray:
        """The verdict with the objects ``alive`` only, deciding the points of ``pending``
        (``bool (N,)``; ``None``: all)."""
        removed = np.zeros(len(self._owner), dtype=bool)
        if pending is None:
            pending = np.ones(len(self._owner), dtype=bool)
        tables, index = self._tables.geometry, self._index
        nearest = _inserted_nearest(*index[:3], *index[4:5], *index[6:10], alive)
        _ray_decide(
            self._inserted,
            self._radii,
            *index,
            *nearest,
            alive,
            pending,
            self._tolerance,
            removed,
            tables[4],  # offsets
            tables[1],  # edge_lut
            tables[-1],  # constants
        )
        return removed


def element_radii(points: np.ndarray, owner: np.ndarray) -> np.ndarray:
    """``float64``: the surface-element radii :func:`ray_occlusion` gives the inserted points
    by default (:func:`~drcpo.occlusion.render.surfel_radii` of each object's points), one per
    inserted point (``owner >= 0``) in order; metres."""
    array = _frame_points(points)
    owner = _check_owner(owner, len(array))
    return _inserted_radii(array, owner, np.flatnonzero(owner >= 0), None)


def _known_cells(
    cells: tuple[np.ndarray, np.ndarray, np.ndarray] | None, count: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``cells`` (beam, column, distance of each of ``count`` points) as :func:`_ray_index`
    takes them; empty arrays (found there) when ``None``."""
    if cells is None:
        none = np.zeros(0, dtype=np.int64)
        return none, none, np.zeros(0)
    beam, column, distance = (np.asarray(part) for part in cells)
    for name, part in (("beam", beam), ("column", column), ("distance", distance)):
        if part.shape != (count,):
            raise DataError(f"cells' {name} must have shape ({count},), got {part.shape}")
    return (
        beam.astype(np.int64, copy=False),
        column.astype(np.int64, copy=False),
        distance.astype(np.float64, copy=False),
    )


def _frame_points(points: np.ndarray) -> np.ndarray:
    """The points as given when they are a real ``(N, 3+)`` array (not copied: frames are
    large; their finiteness is checked in the kernels)."""
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] < 3:
        raise DataError(f"points must have shape (N, 3 + C), got {array.shape}")
    if array.dtype not in (np.float32, np.float64):
        if not np.issubdtype(array.dtype, np.number) or np.issubdtype(
            array.dtype, np.complexfloating
        ):
            raise DataError(f"points must be real numbers, got dtype {array.dtype}")
        array = array.astype(np.float64)
    return array


def _check_owner(owner: np.ndarray, count: int) -> np.ndarray:
    array = np.asarray(owner)
    if array.shape != (count,):
        raise DataError(f"owner must have shape ({count},), one per point, got {array.shape}")
    if array.size and not np.issubdtype(array.dtype, np.integer):
        raise DataError(f"owner must hold integers (-1: original point), got dtype {array.dtype}")
    array = array.astype(np.int64, copy=False)
    if array.size and array.min() < -1:
        raise DataError(f"owner must be -1 (original point) or >= 0, got {int(array.min())}")
    return array


def _check_boxes(boxes: np.ndarray, name: str) -> np.ndarray:
    array = np.asarray(boxes)
    if array.ndim != 2 or array.shape[1] != 7:
        raise DataError(f"{name} must have shape (M, 7), got {array.shape}")
    array = np.ascontiguousarray(array, dtype=np.float64)
    bad = ~np.isfinite(array).all(axis=1) | (array[:, 3:6] <= 0).any(axis=1)
    if bad.any():
        raise DataError(
            f"{name} must be finite with positive sizes; row {int(np.flatnonzero(bad)[0])} is not"
        )
    return array


def _check_tolerance(tolerance: float) -> float:
    if not (isinstance(tolerance, (int, float)) and math.isfinite(tolerance) and tolerance >= 0):
        raise ConfigError(f"tolerance must be a finite number of metres >= 0, got {tolerance!r}")
    return float(tolerance)


def _inserted_radii(
    points: np.ndarray, owner: np.ndarray, inserted: np.ndarray, radii: np.ndarray | None
) -> np.ndarray:
    """``float64`` radii of the inserted points (in the order of ``inserted``)."""
    if radii is not None:
        radii = np.asarray(radii)
        if radii.shape == (len(points),):
            radii = radii[inserted]
        return _check_radii(radii, len(inserted))
    by_object = np.argsort(owner[inserted], kind="stable")
    order = inserted[by_object]
    xyz = np.ascontiguousarray(points[order, :3], dtype=np.float64)
    if not np.isfinite(xyz).all():
        row = int(order[np.flatnonzero(~np.isfinite(xyz).all(axis=1))[0]])
        raise DataError(f"points hold NaN/inf coordinates (first: row {row})")
    sizes = np.bincount(owner[order])
    starts = np.concatenate([[0], np.cumsum(sizes[sizes > 0])]).astype(np.int64)
    sorted_radii = np.empty(len(order))
    _voxel_radii(xyz, starts, VOXEL, RADIUS_FACTOR, *RADIUS_RANGE, sorted_radii)
    radii = np.empty(len(inserted))
    radii[by_object] = sorted_radii
    return radii


@numba.njit(cache=True, nogil=True)
def _nearest_per_cell(beam, column, distance, ranges):  # pragma: no cover - numba
    # ranges[b, c] = the least distance of the points of cell (b, c); -1: no cell
    for i in range(beam.shape[0]):
        b, c = beam[i], column[i]
        if b >= 0 and c >= 0 and distance[i] < ranges[b, c]:
            ranges[b, c] = distance[i]


@numba.njit(cache=True, nogil=True)
def _windows(
    boxes,
    edge_slopes,
    edge_lut,
    beam_slopes,
    beam_lut,
    offsets,
    mount,
    beam_cos,
    beam_sin,
    column_cos,
    column_sin,
    first,
    crosses,
    bound_cos,
    bound_sin,
    constants,
):  # pragma: no cover - numba
    # Per box: the beams (first, last; none when first > last) and columns (first, count,
    # counter-clockwise) whose rays may cross it. Columns: the azimuths of its footprint's
    # corners around the centre's, a column more on each side (all of them when the mount
    # lies above or below the footprint); beams: the elevations, from the lowest and the
    # highest beam origin, of its top and bottom at the footprint's nearest and farthest
    # horizontal distance.
    columns, step, phase = column_cos.shape[0], constants[0], constants[1]
    lut_start, lut_scale, lut_bins = constants[7], constants[8], beam_lut.shape[0]
    out = np.empty((boxes.shape[0], 4), np.int64)
    for m in range(boxes.shape[0]):
        cx, cy = boxes[m, 0] - mount[0], boxes[m, 1] - mount[1]
        cos, sin = math.cos(boxes[m, 6]), math.sin(boxes[m, 6])
        hx, hy = boxes[m, 3] / 2.0, boxes[m, 4] / 2.0
        lx, ly = -cx * cos - cy * sin, cx * sin - cy * cos  # the mount in the box's frame
        gap_x, gap_y = max(abs(lx) - hx, 0.0), max(abs(ly) - hy, 0.0)
        nearest = math.sqrt(gap_x * gap_x + gap_y * gap_y)
        farthest = math.sqrt((abs(lx) + hx) ** 2 + (abs(ly) + hy) ** 2)
        if nearest <= 1e-9:
            out[m, 2], out[m, 3] = 0, columns
        else:
            centre = math.atan2(cy, cx)
            low, high = 0.0, 0.0
            for sx in (-1.0, 1.0):
                for sy in (-1.0, 1.0):
                    px = cx + sx * hx * cos - sy * hy * sin
                    py = cy + sx * hx * sin + sy * hy * cos
                    turn = math.atan2(py, px) - centre
                    turn = (turn + math.pi) % (2.0 * math.pi) - math.pi
                    low, high = min(low, turn), max(high, turn)
            lo = math.floor((centre + low - phase) / step + 0.5) - 1
            hi = math.floor((centre + high - phase) / step + 0.5) + 1
            out[m, 2] = lo % columns
            out[m, 3] = min(hi - lo + 1, columns)
        top, bottom = -np.inf, np.inf
        for offset in (constants[2], constants[3]):
            up = boxes[m, 2] + boxes[m, 5] / 2.0 - mount[2] - offset
            down = boxes[m, 2] - boxes[m, 5] / 2.0 - mount[2] - offset
            top = max(top, math.atan2(up, nearest if up > 0.0 else farthest))
            bottom = min(bottom, math.atan2(down, nearest if down < 0.0 else farthest))
        high_slope = math.tan(min(top + 1e-9, 1.5707963))
        low_slope = math.tan(max(bottom - 1e-9, -1.5707963))
        k = _lut_bin(high_slope, lut_start, lut_scale, lut_bins)
        if k < 0:
            b0 = offsets.shape[0]
        elif k >= lut_bins:
            b0 = 0
        else:
            b0 = int(beam_lut[k, 0]) + (beam_lut[k, 1] > high_slope)
            b0 += beam_lut[k, 2] > high_slope
        b1 = b0 - 1
        while b1 + 1 < beam_slopes.shape[0] and beam_slopes[b1 + 1] >= low_slope:
            b1 += 1
        out[m, 0], out[m, 1] = b0, b1
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _slab(ox, oy, oz, dx, dy, dz, cx, cy, cz, hx, hy, hz, cos, sin):  # pragma: no cover
    # Where the ray o + t d (t >= 0) enters and leaves the box (centre c, half sizes h,
    # heading terms): (enter, leave), enter > leave when it misses.
    rx, ry, rz = ox - cx, oy - cy, oz - cz
    lo = (rx * cos + ry * sin, -rx * sin + ry * cos, rz)
    ld = (dx * cos + dy * sin, -dx * sin + dy * cos, dz)
    half = (hx, hy, hz)
    enter, leave = 0.0, np.inf
    for axis in range(3):
        if ld[axis] == 0.0:
            if abs(lo[axis]) > half[axis]:
                return 1.0, 0.0
            continue
        t1 = (-half[axis] - lo[axis]) / ld[axis]
        t2 = (half[axis] - lo[axis]) / ld[axis]
        enter = max(enter, min(t1, t2))
        leave = min(leave, max(t1, t2))
    return enter, leave


@numba.njit(cache=True, nogil=True)
def _visible_rays(
    boxes,
    box_cos,
    box_sin,
    box_windows,
    occluders,
    occluder_cos,
    occluder_sin,
    occluder_windows,
    ranges,
    settings,
    counts,
    edge_slopes,
    edge_lut,
    beam_slopes,
    beam_lut,
    offsets,
    mount,
    beam_cos,
    beam_sin,
    column_cos,
    column_sin,
    first,
    crosses,
    bound_cos,
    bound_sin,
    constants,
):  # pragma: no cover - numba
    columns = column_cos.shape[0]
    tolerance, max_range = settings[0], settings[1]
    candidates = np.empty(occluders.shape[0], np.int64)
    for m in range(boxes.shape[0]):
        b0, b1 = box_windows[m, 0], box_windows[m, 1]
        c0, width = box_windows[m, 2], box_windows[m, 3]
        cx, cy, cz = boxes[m, 0], boxes[m, 1], boxes[m, 2]
        hx, hy, hz = boxes[m, 3] / 2.0, boxes[m, 4] / 2.0, boxes[m, 5] / 2.0
        # the occluders whose windows overlap this one's
        found = 0
        for k in range(occluders.shape[0]):
            if occluder_windows[k, 0] > b1 or occluder_windows[k, 1] < b0:
                continue
            if occluder_windows[k, 0] > occluder_windows[k, 1]:
                continue
            into = (occluder_windows[k, 2] - c0) % columns
            back = (c0 - occluder_windows[k, 2]) % columns
            if into < width or back < occluder_windows[k, 3]:
                candidates[found] = k
                found += 1
        for b in range(b0, b1 + 1):
            ox, oy, oz = mount[0], mount[1], mount[2] + offsets[b]
            c = c0
            for _ in range(width):
                dx = beam_cos[b] * column_cos[c]
                dy = beam_cos[b] * column_sin[c]
                dz = beam_sin[b]
                enter, leave = _slab(
                    ox, oy, oz, dx, dy, dz, cx, cy, cz, hx, hy, hz, box_cos[m], box_sin[m]
                )
                reaches = enter <= leave and enter <= max_range
                if reaches and ranges[b, c] >= enter - tolerance:
                    for n in range(found):
                        k = candidates[n]
                        near, far = _slab(
                            ox,
                            oy,
                            oz,
                            dx,
                            dy,
                            dz,
                            occluders[k, 0],
                            occluders[k, 1],
                            occluders[k, 2],
                            occluders[k, 3] / 2.0,
                            occluders[k, 4] / 2.0,
                            occluders[k, 5] / 2.0,
                            occluder_cos[k],
                            occluder_sin[k],
                        )
                        if near <= far and near < enter - tolerance:
                            reaches = False
                            break
                    if reaches:
                        counts[m] += 1
                c = c + 1 if c + 1 < columns else 0


@numba.njit(cache=True, nogil=True)
def _admit(
    boxes,
    cos,
    sin,
    windows,
    first,
    every,
    need,
    left,
    combined,
    settings,
    groups,
    conflicts,
    hidden,
    taken,
    edge_slopes,
    edge_lut,
    beam_slopes,
    beam_lut,
    offsets,
    mount,
    beam_cos,
    beam_sin,
    column_cos,
    column_sin,
    first_column,
    crosses,
    bound_cos,
    bound_sin,
    constants,
):  # pragma: no cover - numba
    # PlacedView._admit: `boxes` are the accepted ones (rows < first; their need and left
    # given), then the candidates, whose need, left (when accepted) and hidden[m] (row
    # first + m) and taken[m] (accepted) it sets; `combined` (B, C): the frame's nearest return
    # per cell with the accepted boxes' entries painted in. every: accept all the candidates,
    # painted in first and counted after. A candidate whose group (groups[m]) had one taken,
    # or that conflicts with one taken (conflicts[m, m']), is passed over.
    tolerance, max_range = settings[0], settings[1]
    min_rays, share = settings[2], settings[3]
    columns = column_cos.shape[0]
    total = boxes.shape[0]
    # each box's azimuth span (centre, half angle) of its bounding circle seen from the mount
    spans = np.empty((total, 2))
    for m in range(total):
        x, y = boxes[m, 0] - mount[0], boxes[m, 1] - mount[1]
        reach = math.hypot(boxes[m, 3], boxes[m, 4]) / 2.0
        distance = math.hypot(x, y)
        spans[m, 0] = math.atan2(y, x)
        half = math.asin(min(reach / max(distance, 1e-9), 1.0))
        spans[m, 1] = half if distance > reach else np.pi
    if every:
        for g in range(first, total):
            _paint(g, boxes, cos, sin, windows, combined, offsets, mount, beam_cos, beam_sin,
                   column_cos, column_sin)  # fmt: skip
    accepted = np.empty(total, np.int64)
    accepted[:first] = np.arange(first)
    count = first
    near = np.empty(total, np.int64)
    lost = np.zeros(total, np.int64)
    # where each ray of a candidate's window enters it (inf: it misses), found once for its
    # count, the boxes it may hide and its painting
    size = 0
    for g in range(first, total):
        size = max(size, (windows[g, 1] - windows[g, 0] + 1) * windows[g, 3])
    entry = np.empty(size)
    for g in range(first, total):
        if not every:
            done = False
            for n in range(first, count):
                done |= groups[accepted[n] - first] == groups[g - first]
                done |= conflicts[g - first, accepted[n] - first]
            if done:
                continue
        b0, b1, c0, width = windows[g, 0], windows[g, 1], windows[g, 2], windows[g, 3]
        crossing, seen, k = 0, 0, 0
        for b in range(b0, b1 + 1):
            ox, oy, oz = mount[0], mount[1], mount[2] + offsets[b]
            c = c0
            for _ in range(width):
                dx, dy = beam_cos[b] * column_cos[c], beam_cos[b] * column_sin[c]
                enter, leave = _slab(
                    ox, oy, oz, dx, dy, beam_sin[b], boxes[g, 0], boxes[g, 1], boxes[g, 2],
                    boxes[g, 3] / 2.0, boxes[g, 4] / 2.0, boxes[g, 5] / 2.0, cos[g], sin[g],
                )  # fmt: skip
                entry[k] = enter if enter <= leave else np.inf
                k += 1
                if enter <= leave and enter <= max_range:
                    crossing += 1
                    if combined[b, c] >= enter - tolerance:
                        seen += 1
                c = c + 1 if c + 1 < columns else 0
        need[g] = max(min_rays, math.ceil((1.0 - share) * crossing))
        if every:
            left[g] = seen
            taken[g - first] = True
            continue
        if seen < need[g]:
            hidden[g - first] = True
            continue
        found = 0  # the accepted boxes whose spans overlap: the only ones it may hide
        for n in range(count):
            a = accepted[n]
            gap = abs((spans[a, 0] - spans[g, 0] + np.pi) % (2.0 * np.pi) - np.pi)
            if gap <= spans[a, 1] + spans[g, 1]:
                near[found] = a
                lost[found] = 0
                found += 1
        if found:
            k = 0
            for b in range(b0, b1 + 1):
                ox, oy, oz = mount[0], mount[1], mount[2] + offsets[b]
                c = c0
                for _ in range(width):
                    dx, dy = beam_cos[b] * column_cos[c], beam_cos[b] * column_sin[c]
                    dz = beam_sin[b]
                    into = entry[k]
                    k += 1
                    if into < np.inf:  # the ray enters it: it hides what lies beyond
                        for n in range(found):
                            a = near[n]
                            enter, leave = _slab(
                                ox, oy, oz, dx, dy, dz, boxes[a, 0], boxes[a, 1], boxes[a, 2],
                                boxes[a, 3] / 2.0, boxes[a, 4] / 2.0, boxes[a, 5] / 2.0, cos[a],
                                sin[a],
                            )  # fmt: skip
                            if (
                                enter <= leave
                                and enter <= max_range
                                and combined[b, c] >= enter - tolerance
                                and into < enter - tolerance
                            ):
                                lost[n] += 1
                    c = c + 1 if c + 1 < columns else 0
            short = False
            for n in range(found):
                short |= left[near[n]] - lost[n] < need[near[n]]
            if short:
                hidden[g - first] = True
                continue
            for n in range(found):
                left[near[n]] -= lost[n]
        k = 0  # painted in: its entry distance into each cell its rays cross, where nearer
        for b in range(b0, b1 + 1):
            c = c0
            for _ in range(width):
                combined[b, c] = min(combined[b, c], entry[k])
                k += 1
                c = c + 1 if c + 1 < columns else 0
        left[g] = seen
        taken[g - first] = True
        accepted[count] = g
        count += 1


@numba.njit(cache=True, nogil=True)
def _paint(
    g,
    boxes,
    cos,
    sin,
    windows,
    combined,
    offsets,
    mount,
    beam_cos,
    beam_sin,
    column_cos,
    column_sin,
):  # pragma: no cover - numba
    # Box g's entry distance into each cell of `combined` its rays cross, where nearer.
    columns = column_cos.shape[0]
    for b in range(windows[g, 0], windows[g, 1] + 1):
        ox, oy, oz = mount[0], mount[1], mount[2] + offsets[b]
        c = windows[g, 2]
        for _ in range(windows[g, 3]):
            enter, leave = _slab(
                ox, oy, oz, beam_cos[b] * column_cos[c], beam_cos[b] * column_sin[c],
                beam_sin[b], boxes[g, 0], boxes[g, 1], boxes[g, 2], boxes[g, 3] / 2.0,
                boxes[g, 4] / 2.0, boxes[g, 5] / 2.0, cos[g], sin[g],
            )  # fmt: skip
            if enter <= leave and enter < combined[b, c]:
                combined[b, c] = enter
            c = c + 1 if c + 1 < columns else 0


@numba.njit(cache=True, nogil=True)
def _element_windows(
    points,
    owner,
    inserted,
    radii,
    known_beam,
    known_column,
    known_distance,
    lo,
    hi,
    own_beam,
    own_column,
    own_distance,
    rel,
    element_owner,
    window,
    covered,
    wanted,
    slope_lo,
    slope_hi,
    edge_slopes,
    edge_lut,
    beam_slopes,
    beam_lut,
    offsets,
    mount,
    beam_cos,
    beam_sin,
    column_cos,
    column_sin,
    first,
    crosses,
    bound_cos,
    bound_sin,
    constants,
):  # pragma: no cover - numba
    # The first steps of _ray_index for the inserted points lo..hi - 1 (elements j): their
    # cells, distances and offsets from the mount, and each element's window of cells, into
    # the shared per-element arrays at j; per column, this part's own `covered`, `wanted`,
    # `slope_lo` and `slope_hi` (see _ray_index; RayOcclusion._windows merges the parts).
    # Returns the first row with a non-finite coordinate, or -1.
    beams, columns, bins = offsets.shape[0], column_cos.shape[0], first.shape[0]
    step, phase, per_radian = constants[0], constants[1], constants[4]
    lut_start, lut_scale, lut_bins = constants[5], constants[6], edge_lut.shape[0]
    # 1. The inserted points: their cells, distances and offsets from the mount.
    if known_beam.shape[0] == points.shape[0]:  # (_point_cells' answer, found before)
        part_beam, part_column, part_distance, part_rel, bad = _known_cells_of(
            points, inserted[lo:hi], known_beam, known_column, known_distance, mount
        )
    else:
        part_beam, part_column, part_distance, part_rel, bad = _point_cells(
            points,
            inserted[lo:hi],
            edge_slopes,
            edge_lut,
            beam_slopes,
            beam_lut,
            offsets,
            mount,
            beam_cos,
            beam_sin,
            column_cos,
            column_sin,
            first,
            crosses,
            bound_cos,
            bound_sin,
            constants,
        )
    if bad >= 0:
        return bad
    # 2. Each element's window of cells: rows 0..B + 1 (above, in and below the beams) of the
    #    edges' tangents its cone spans, columns from one end of its azimuths to the other.
    #    Per column: the object whose windows reach it (-2: several, -1: none), whether it
    #    holds inserted returns, and the elevation tangents (from any beam origin) an
    #    original point needs to matter: within some element's cone, or in the beam of an
    #    inserted return.
    for q in range(hi - lo):
        j = lo + q
        own_beam[j], own_column[j], own_distance[j] = part_beam[q], part_column[q], part_distance[q]
        rel[j, 0], rel[j, 1], rel[j, 2] = part_rel[q, 0], part_rel[q, 1], part_rel[q, 2]
        owner_j = element_owner[j] = owner[inserted[j]]
        if own_beam[j] >= 0:
            c = own_column[j]
            wanted[c] = True
            slope_lo[c] = min(slope_lo[c], edge_slopes[own_beam[j] + 1])
            slope_hi[c] = max(slope_hi[c], edge_slopes[own_beam[j]])
        x, y, z = rel[j, 0], rel[j, 1], rel[j, 2]
        half, low, high = _cone(x, y, z, radii[j], per_radian, constants[2], constants[3])
        row_lo, row_hi = 0, beams + 1
        k = _lut_bin(high, lut_start, lut_scale, lut_bins)
        if k < 0:
            row_lo = beams + 1
        elif k < lut_bins:
            row_lo = int(edge_lut[k, 0]) + (edge_lut[k, 1] > high) + (edge_lut[k, 2] > high)
        k = _lut_bin(low, lut_start, lut_scale, lut_bins)
        if k >= lut_bins:
            row_hi = 0
        elif k >= 0:
            row_hi = int(edge_lut[k, 0]) + (edge_lut[k, 1] > low) + (edge_lut[k, 2] > low)
        if half * 2.0 + 3.0 >= columns:
            c0, count = 0, columns
        else:
            horizontal = math.sqrt(x * x + y * y)
            s = min((radii[j] * (1.0 + 1e-9) + 1e-12) / horizontal, 1.0)
            co = math.sqrt(1.0 - s * s)
            ux, uy = x / horizontal, y / horizontal
            ex, ey = ux * co + uy * s, uy * co - ux * s  # turned clockwise by asin(s)
            k = _pseudo_bin(ex, ey, bins)
            c0 = _column_at(
                ex, ey, first[k], crosses[k], bound_cos[k], bound_sin[k], columns, step, phase
            )
            ex, ey = ux * co - uy * s, uy * co + ux * s  # counter-clockwise
            k = _pseudo_bin(ex, ey, bins)
            end = _column_at(
                ex, ey, first[k], crosses[k], bound_cos[k], bound_sin[k], columns, step, phase
            )
            count = end - c0 + 1
            if count <= 0:
                count += columns
        window[j, 0], window[j, 1], window[j, 2], window[j, 3] = row_lo, row_hi, c0, count
        c = c0
        for _ in range(count):
            covered[c] = owner_j if covered[c] == -1 or covered[c] == owner_j else -2
            slope_lo[c], slope_hi[c] = min(slope_lo[c], low), max(slope_hi[c], high)
            c = c + 1 if c + 1 < columns else 0
    return -1


@numba.njit(cache=True, nogil=True)
def _ray_index(
    points,
    owner,
    own_beam,
    window,
    covered,
    wanted,
    slope_lo,
    slope_hi,
    known_beam,
    known_column,
    known_distance,
    edge_slopes,
    edge_lut,
    beam_slopes,
    beam_lut,
    offsets,
    mount,
    beam_cos,
    beam_sin,
    column_cos,
    column_sin,
    first,
    crosses,
    bound_cos,
    bound_sin,
    constants,
):  # pragma: no cover - numba
    # The work of ray_occlusion that does not depend on which objects are kept, once the
    # elements' windows and the columns' `covered`, `wanted`, `slope_lo` and `slope_hi` are
    # known (_element_windows): the cells' slots, the elements of each cell, the original
    # points that may matter and the frame's nearest return per cell (see _ray_decide).
    # First: the first original row with a non-finite coordinate, or -1 (then the rest is
    # empty). Then: slot, used, top, bottom, entries, start, candidates, their beam, column,
    # distance and offset from the mount, and frame.
    beams, columns, bins = offsets.shape[0], column_cos.shape[0], first.shape[0]
    m = own_beam.shape[0]
    # the rows any window or own cell reaches: the per-cell arrays cover those only
    top, bottom = beams + 1, 0
    for j in range(m):
        top, bottom = min(top, window[j, 0]), max(bottom, window[j, 1])
        if own_beam[j] >= 0:
            top, bottom = min(top, own_beam[j] + 1), max(bottom, own_beam[j] + 1)
    rows = max(bottom - top + 1, 0)
    slot = np.full(columns, -1, np.int64)
    used = 0
    for c in range(columns):
        if covered[c] != -1 or wanted[c]:
            slot[c] = used
            used += 1
    # 3. The elements of each cell of the used columns in one array, cell by cell. Each
    #    window is a rectangle of slots (its columns are all used, so their slots run on,
    #    but where it wraps past the last column): the counts per cell are the 2-d prefix
    #    sums of its corners' +-1 (a pass over the windows and one over the cells).
    corners = np.zeros((rows + 1, used + 1), np.int64)
    for j in range(m):
        r0, r1 = window[j, 0] - top, window[j, 1] + 1 - top
        if r1 <= r0:
            continue
        c0, c1 = window[j, 2], window[j, 2] + window[j, 3] - 1
        if c1 >= columns:  # wraps: from c0 to the last column, then from column 0
            _add_rectangle(corners, r0, r1, slot[c0], slot[columns - 1] + 1)
            c0, c1 = 0, c1 - columns
        _add_rectangle(corners, r0, r1, slot[c0], slot[c1] + 1)
    start = np.zeros(rows * used + 1, np.int64)
    above = np.zeros(used, np.int64)  # per slot, the corners' sum over the rows so far
    total = 0
    for r in range(rows):
        count = 0
        for s in range(used):
            above[s] += corners[r, s]
            count += above[s]  # the windows holding cell (r, s)
            total += count
            start[r * used + s + 1] = total
    entries = np.empty(start[-1], np.int32)
    fill = start[:-1].copy()
    for j in range(m):
        for r in range(window[j, 0] - top, window[j, 1] + 1 - top):
            c = window[j, 2]
            for _ in range(window[j, 3]):
                cell = r * used + slot[c]
                entries[fill[cell]] = j
                fill[cell] += 1
                c = c + 1 if c + 1 < columns else 0
    # 4. The original points: most set aside by their azimuth's pseudo-angle bin and their
    #    elevation's tangent alone; the others give their cell's frame distance and are
    #    tested against the elements.
    bin_lo = np.full(bins, np.inf)  # the tangents that matter per pseudo-angle bin
    bin_hi = np.full(bins, -np.inf)
    for k in range(bins):
        c = first[k]
        after = c + 1 if c + 1 < columns else 0
        if crosses[k] < 0:
            bin_lo[k], bin_hi[k] = -np.inf, np.inf
        elif slot[c] >= 0 or (crosses[k] > 0 and slot[after] >= 0):
            bin_lo[k], bin_hi[k] = slope_lo[c], slope_hi[c]
            if crosses[k] > 0:
                bin_lo[k] = min(bin_lo[k], slope_lo[after])
                bin_hi[k] = max(bin_hi[k], slope_hi[after])
    candidates = np.empty(points.shape[0], np.int64)
    found = 0
    for i in range(points.shape[0]):
        if owner[i] >= 0:
            continue
        x = np.float64(points[i, 0]) - mount[0]
        y = np.float64(points[i, 1]) - mount[1]
        z = np.float64(points[i, 2]) - mount[2]
        if not np.isfinite(x + y + z):
            return _no_index(i)
        if x == 0.0 and y == 0.0:
            continue
        k = _pseudo_bin(x, y, bins)
        if not bin_lo[k] <= bin_hi[k]:
            continue
        # its tangent from some beam origin, (z - offset) / horizontal, within the bin's
        horizontal = math.sqrt(x * x + y * y)
        if (
            z - constants[2] >= bin_lo[k] * horizontal
            and z - constants[3] <= bin_hi[k] * horizontal
        ):
            candidates[found] = i
            found += 1
    candidates = candidates[:found]
    # (no row left is non-finite: every candidate was checked above)
    if known_beam.shape[0] == points.shape[0]:  # (_point_cells' answer, found before)
        beam, column, distance, near, _ = _known_cells_of(
            points, candidates, known_beam, known_column, known_distance, mount
        )
    else:
        beam, column, distance, near, _ = _point_cells(
            points,
            candidates,
            edge_slopes,
            edge_lut,
            beam_slopes,
            beam_lut,
            offsets,
            mount,
            beam_cos,
            beam_sin,
            column_cos,
            column_sin,
            first,
            crosses,
            bound_cos,
            bound_sin,
            constants,
        )
    frame = np.full(rows * used, np.inf)
    for q in range(found):
        if beam[q] >= 0 and wanted[column[q]] and top <= beam[q] + 1 <= bottom:
            cell = (beam[q] + 1 - top) * used + slot[column[q]]
            frame[cell] = min(frame[cell], distance[q])
    return (
        -1, slot, used, top, bottom, entries, start, candidates, beam, column, distance, near,
        frame,
    )  # fmt: skip


@numba.njit(cache=True, nogil=True, inline="always")
def _add_rectangle(corners, r0, r1, s0, s1):  # pragma: no cover - numba
    # One window's corners, rows r0..r1 - 1 by slots s0..s1 - 1, in the 2-d difference array.
    corners[r0, s0] += 1
    corners[r0, s1] -= 1
    corners[r1, s0] -= 1
    corners[r1, s1] += 1


@numba.njit(cache=True, nogil=True)
def _known_cells_of(
    points, index, known_beam, known_column, known_distance, mount
):  # pragma: no cover - numba
    # _point_cells of points[index] from the known cells of every point: their cells and
    # distances taken, their offsets from the mount found (and non-finite rows caught).
    n = index.shape[0]
    beam = np.empty(n, np.int64)
    column = np.empty(n, np.int64)
    distance = np.empty(n)
    rel = np.empty((n, 3))
    for q in range(n):
        i = index[q]
        x = np.float64(points[i, 0]) - mount[0]
        y = np.float64(points[i, 1]) - mount[1]
        z = np.float64(points[i, 2]) - mount[2]
        if not np.isfinite(x + y + z):
            return beam, column, distance, rel, i
        rel[q, 0], rel[q, 1], rel[q, 2] = x, y, z
        beam[q], column[q], distance[q] = known_beam[i], known_column[i], known_distance[i]
    return beam, column, distance, rel, -1


@numba.njit(cache=True, nogil=True)
def _no_index(bad):  # pragma: no cover - numba
    # _ray_index's answer for a non-finite row: the row, then empty arrays.
    none, empty = np.zeros(0, np.int64), np.zeros(0)
    return (
        bad, none, 0, 0, -1, np.zeros(0, np.int32), none, none, none, none, empty,
        np.zeros((0, 3)), empty,
    )  # fmt: skip


@numba.njit(cache=True, nogil=True)
def _inserted_nearest(
    own_beam, own_column, own_distance, element_owner, slot, used, top, bottom, alive
):  # pragma: no cover - numba
    # Per cell of the used columns: the nearest inserted return of the objects `alive`, its
    # object, and the nearest of another object.
    rows = max(bottom - top + 1, 0)
    nearest = np.full(rows * used, np.inf)
    nearest_owner = np.full(rows * used, -1, np.int64)
    other = np.full(rows * used, np.inf)
    for j in range(own_beam.shape[0]):
        if own_beam[j] < 0 or not alive[element_owner[j]]:
            continue
        cell = (own_beam[j] + 1 - top) * used + slot[own_column[j]]
        distance_j, k = own_distance[j], element_owner[j]
        if distance_j < nearest[cell]:
            if nearest_owner[cell] != k:
                other[cell] = nearest[cell]
            nearest[cell], nearest_owner[cell] = distance_j, k
        elif k != nearest_owner[cell] and distance_j < other[cell]:
            other[cell] = distance_j
    return nearest, nearest_owner, other


@numba.njit(cache=True, nogil=True)
def _ray_decide(
    inserted,
    radii,
    own_beam,
    own_column,
    own_distance,
    rel,
    element_owner,
    covered,
    slot,
    used,
    top,
    bottom,
    entries,
    start,
    candidates,
    beam,
    column,
    distance,
    near,
    frame,
    nearest,
    nearest_owner,
    other,
    alive,
    pending,
    tolerance,
    removed,
    offsets,
    edge_lut,
    constants,
):  # pragma: no cover - numba
    # Sets `removed` of the points of `pending` from _ray_index's work, with the objects
    # `alive` only (the points of the others are removed). The windows and original points
    # that _ray_index kept for all the objects cover those of any of them: a column's `covered`
    # may name several objects where one is left, which only costs a look. nearest,
    # nearest_owner, other: per cell, _inserted_nearest of the objects alive.
    m = inserted.shape[0]
    # The original points: behind an element along their own ray.
    found = candidates.shape[0]
    ask = np.zeros(found, np.bool_)
    for q in range(found):
        ask[q] = pending[candidates[q]]
    hidden = _behind_elements(
        near, beam, column, distance, np.full(found, -1, np.int64), ask, alive, covered, slot,
        used, top, bottom, offsets, rel, radii, element_owner, entries, start, tolerance,
        edge_lut, constants,
    )  # fmt: skip
    for q in range(found):
        if ask[q]:
            removed[candidates[q]] = hidden[q]
    # The inserted returns: behind the frame or another object in their cell, or else behind
    # another object's elements along their ray.
    ask = np.zeros(m, np.bool_)
    for j in range(m):
        i = inserted[j]
        if not alive[element_owner[j]]:
            removed[i] = True
            continue
        if not pending[i]:
            continue
        if own_beam[j] >= 0:
            cell = (own_beam[j] + 1 - top) * used + slot[own_column[j]]
            distance_j = own_distance[j]
            rival = other[cell] if nearest_owner[cell] == element_owner[j] else nearest[cell]
            if frame[cell] < distance_j - tolerance or rival < distance_j - tolerance:
                removed[i] = True
                continue
        ask[j] = True
    hidden = _behind_elements(
        rel, own_beam, own_column, own_distance, element_owner, ask, alive, covered, slot,
        used, top, bottom, offsets, rel, radii, element_owner, entries, start, tolerance,
        edge_lut, constants,
    )  # fmt: skip
    for j in range(m):
        if ask[j]:
            removed[inserted[j]] = hidden[j]


@numba.njit(cache=True, nogil=True)
def _behind_elements(
    queries,
    beam,
    column,
    distance,
    skip,
    ask,
    alive,
    covered,
    slot,
    used,
    top,
    bottom,
    offsets,
    rel,
    radii,
    element_owner,
    entries,
    start,
    tolerance,
    edge_lut,
    constants,
):  # pragma: no cover - numba
    # Per query point q (offset from the mount, beam, column, distance from its beam's
    # origin; covered: the object whose elements reach each column, -2 several, -1 none;
    # slot: each column's place among the `used` ones; elements in rows top..bottom only):
    # whether an element not of object skip[q] lies within its radius of the ray from that
    # origin (the mount outside every beam) through the point, more than `tolerance` nearer
    # along it. The elements looked at are those of the cell of the ray's direction (its row
    # among the beam edges, seen from that origin). Only the queries `ask`ed, against the
    # elements of the objects `alive`.
    lut_start, lut_scale, lut_bins = constants[5], constants[6], edge_lut.shape[0]
    beams = offsets.shape[0]
    hidden = np.zeros(queries.shape[0], np.bool_)
    for q in range(queries.shape[0]):
        c = column[q]
        if not ask[q] or c < 0 or covered[c] == -1 or covered[c] == skip[q]:
            continue  # no element, or only the query's own object's
        lift = offsets[beam[q]] if beam[q] >= 0 else 0.0
        x, y, dz = queries[q, 0], queries[q, 1], queries[q, 2] - lift
        slope = dz / math.sqrt(x * x + y * y)
        k = _lut_bin(slope, lut_start, lut_scale, lut_bins)
        if k < 0:
            row = beams + 1
        elif k >= lut_bins:
            row = 0
        else:
            row = int(edge_lut[k, 0]) + (edge_lut[k, 1] > slope) + (edge_lut[k, 2] > slope)
        if row < top or row > bottom:
            continue  # no element reaches this row
        cell = (row - top) * used + slot[c]
        limit = distance[q] - tolerance
        inverse = 1.0 / distance[q]
        ux, uy, uz = x * inverse, y * inverse, dz * inverse
        for e in range(start[cell], start[cell + 1]):
            j = entries[e]
            if element_owner[j] == skip[q] or not alive[element_owner[j]]:
                continue
            vx, vy, vz = rel[j, 0], rel[j, 1], rel[j, 2] - lift
            t = vx * ux + vy * uy + vz * uz
            if t <= 0.0 or t >= limit:
                continue
            if vx * vx + vy * vy + vz * vz - t * t <= radii[j] * radii[j]:
                hidden[q] = True
                break
    return hidden
