"""Random placement of objects in a frame (DR.CPO, step 2), checked before any construction.

A pose is a heading uniform in ``[-pi, pi)`` and a position uniform over the placement area such
that the whole BEV footprint lies inside it (with ``fov_only``, also inside the camera's field of
view: every footprint corner at an azimuth ``|atan2(y, x)| <= fov_half_angle``; KITTI's camera 2
sees about 41 degrees to each side). The box bottom is put on the ground estimated from the
frame's own points (``height_mode="ground"``) or the box keeps its source height (``"source"``, the
reference implementation).

A placement is rejected, for one reason counted per attempt, when

* ``"out_of_range"``: the footprint cannot fit in the area (or field of view);
* ``"collision"``: its BEV box overlaps (area > 0) an existing box of the frame, a box placed
  earlier in this call, or an earlier box of the same batch (first come, first placed);
* ``"obstacle"``: its box holds more than ``max_nonground_points`` frame points that are more
  than ``ground_tolerance`` above the ground (walls, trees, unlabelled objects);
* ``"occluded"``: the caller's occlusion test rejects it (DR.CPO's: the box would be hidden
  behind the frame's points, see :class:`drcpo.pipeline.DRCPO`; :class:`OcclusionMap` is a
  z-buffer for such a test).

Objects are tried up to ``max_tries`` times (a fresh pose each time); the paper tries once.

The hot loops are numba kernels that reproduce the reference numpy arithmetic operation for
operation (same boxes, same verdicts, bit for bit): collisions are a separating-axis test
(:func:`bev_collisions`, interiors intersect exactly when the overlap area is positive), the
points in each box come from one pass with a coarse cell index
(:func:`drcpo.geometry.box_members`), and the z-buffer is filled only in the cells the boxes'
samples fall in.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np

from drcpo.errors import ConfigError, DataError
from drcpo.frame import Frame
from drcpo.geometry import box_members, heading_terms, in_box
from drcpo.ground import GroundModel

REASONS = ("out_of_range", "collision", "obstacle", "occluded")
HEIGHT_MODES = ("ground", "source")
#: Half of KITTI camera 2's horizontal field of view (radians), rounded up.
KITTI_FOV_HALF_ANGLE = float(np.deg2rad(41.0))
_FOV_ROUNDS = 32  # resampling rounds for positions outside the field of view


@dataclass(frozen=True)
class PlacementConfig:
    """Parameters of :func:`sample_poses` and :func:`place_objects` (paper defaults).

    Attributes:
        x_range, y_range: placement area (metres, LiDAR frame); the whole footprint stays inside.
        fov_only: restrict positions to the camera's field of view (see ``fov_half_angle``).
        fov_half_angle: largest footprint-corner azimuth ``|atan2(y, x)|`` (radians).
        height_mode: ``"ground"`` (bottom on the estimated ground) or ``"source"``.
        max_nonground_points: most non-ground frame points a placed box may hold.
        ground_tolerance: points more than this (metres) above the ground are non-ground.
        max_tries: poses tried per object.
        clearance: metres of room kept free on every side of each placed footprint (for an
            object that may grow its box by that much once built): the footprint grown by it
            must lie in the area and overlap no box, nor any other grown footprint.
    """

    x_range: tuple[float, float] = (0.0, 70.4)
    y_range: tuple[float, float] = (-40.0, 40.0)
    fov_only: bool = False
    fov_half_angle: float = KITTI_FOV_HALF_ANGLE
    height_mode: str = "ground"
    max_nonground_points: int = 10
    ground_tolerance: float = 0.2
    max_tries: int = 1
    clearance: float = 0.0

    def __post_init__(self) -> None:
        for name in ("x_range", "y_range"):
            value = tuple(float(v) for v in getattr(self, name))
            if len(value) != 2 or not np.isfinite(value).all() or not value[0] < value[1]:
                raise ConfigError(
                    f"placement.{name} must be two finite numbers (low < high), got {value}"
                )
            object.__setattr__(self, name, value)
        if not 0 < self.fov_half_angle <= np.pi:
            raise ConfigError(
                f"placement.fov_half_angle must be in (0, pi] radians, got {self.fov_half_angle}"
            )
        if self.height_mode not in HEIGHT_MODES:
            raise ConfigError(
                f"placement.height_mode must be one of {HEIGHT_MODES}, got {self.height_mode!r}"
            )
        if int(self.max_nonground_points) != self.max_nonground_points or (
            self.max_nonground_points < 0
        ):
            raise ConfigError(
                "placement.max_nonground_points must be an integer >= 0, "
                f"got {self.max_nonground_points}"
            )
        if not self.ground_tolerance >= 0:
            raise ConfigError(
                f"placement.ground_tolerance must be >= 0 metres, got {self.ground_tolerance}"
            )
        if int(self.max_tries) != self.max_tries or self.max_tries < 1:
            raise ConfigError(f"placement.max_tries must be an integer >= 1, got {self.max_tries}")
        if not (np.isfinite(self.clearance) and self.clearance >= 0):
            raise ConfigError(f"placement.clearance must be >= 0 metres, got {self.clearance}")
        object.__setattr__(self, "max_tries", int(self.max_tries))
        object.__setattr__(self, "max_nonground_points", int(self.max_nonground_points))


@dataclass(frozen=True, eq=False)
class PlacementResult:
    """Outcome of :func:`place_objects`.

    Attributes:
        boxes: ``float64 (A, 7)`` placed boxes, in the order of ``accepted``.
        accepted: ``int64 (A,)`` ascending indices (into the ``dims`` given) of placed objects.
        rejected: attempts rejected per reason (every reason in :data:`REASONS` present).
        reasons: ``(K,)`` per object: ``""`` when placed, else the reason of its last attempt.
        attempts: poses tried in all.
    """

    boxes: np.ndarray
    accepted: np.ndarray
    rejected: dict[str, int]
    reasons: np.ndarray
    attempts: int


def sample_poses(
    dims: np.ndarray, rng: np.random.Generator, config: PlacementConfig | None = None
) -> np.ndarray:
    """Random boxes ``float64 (K, 7)`` of sizes ``dims`` ``(K, 3)`` (metres).

    Heading uniform in ``[-pi, pi)``; centre uniform over the positions whose whole footprint
    lies in the area (and field of view when ``fov_only``); ``z = dz / 2`` (bottom at 0).
    Rows that cannot fit have NaN x and y.
    """
    config = config or PlacementConfig()
    dims = _check_dims(dims)
    heading = rng.uniform(-np.pi, np.pi, len(dims))
    boxes = np.column_stack([np.zeros((len(dims), 3)), dims, heading])
    boxes[:, 2] = dims[:, 2] / 2.0
    # numpy's cos and sin, as geometry.bev_corners uses them
    cos, sin = np.cos(heading), np.sin(heading)
    half_angle = float(config.fov_half_angle) if config.fov_only else -1.0
    # Each round draws the rows given and returns those whose footprint fits the area but
    # leaves the field of view (none without fov_only); they are drawn again.
    todo = _draw_round(boxes, np.arange(len(dims)), cos, sin, rng, config, half_angle)
    for _ in range(_FOV_ROUNDS):
        if len(todo) == 0:
            break
        todo = _draw_round(boxes, todo, cos, sin, rng, config, half_angle)
    boxes[todo, :2] = np.nan
    return boxes


def place_objects(
    frame: Frame | dict,
    dims: np.ndarray,
    source_boxes: np.ndarray | None,
    rng: np.random.Generator,
    config: PlacementConfig | None = None,
    ground: GroundModel | None = None,
    occluded: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> PlacementResult:
    """Place objects of sizes ``dims`` ``(K, 3)`` at random, collision- and obstacle-free.

    Args:
        frame: the :class:`Frame` (or OpenPCDet dict) receiving the objects; its boxes are
            obstacles to avoid and its points the background checked for non-ground points.
        dims: box sizes dx, dy, dz (metres) of the objects, in the order they are tried.
        source_boxes: ``(K, 7)`` the objects' original boxes; only their z is used, and only
            with ``height_mode="source"`` (may be ``None`` otherwise).
        rng: the only source of randomness.
        config: :class:`PlacementConfig` (defaults when ``None``).
        ground: the frame's :class:`GroundModel`; estimated from the frame's points (with its
            ``plane`` and ``calib`` metadata, when both are present) when ``None``.
        occluded: an occlusion test of the boxes that pass the others, ``(B, 7)``, given the
            boxes placed before them ``(P, 7)``: ``bool (B,)``, those to reject (reason
            ``"occluded"``, tried again like the others).
    """
    config = config or PlacementConfig()
    frame = Frame.from_dict(frame) if isinstance(frame, dict) else frame
    dims = _check_dims(dims)
    source_z = _source_heights(source_boxes, len(dims), config)
    if ground is None:
        ground = frame_ground(frame)
    obstacles = _Obstacles(frame.points, ground, config.ground_tolerance)
    placed = np.full((len(dims), 7), np.nan)
    verdicts = np.zeros(len(dims), dtype=np.int64)  # 0: placed, else 1 + index in REASONS
    counts = np.zeros(len(REASONS) + 1, dtype=np.int64)
    occupied = frame.boxes
    room = dims.copy()  # each footprint with its clearance: sampled and checked for collisions
    room[:, :2] += 2.0 * config.clearance
    pending = np.arange(len(dims))
    attempts = 0
    for _ in range(config.max_tries):
        if len(pending) == 0:
            break
        attempts += len(pending)
        boxes = sample_poses(room[pending], rng, config)
        verdict = _judge(boxes, pending, dims, source_z, occupied, obstacles, config)
        own = boxes.copy()  # the objects' own footprints, without the clearance
        own[:, 3:5] = dims[pending, :2]
        passed = np.flatnonzero(verdict == 0)
        if occluded is not None and len(passed):
            before = placed[np.isfinite(placed[:, 0])]
            hidden = np.asarray(occluded(own[passed], before), dtype=bool).reshape(-1)
            if len(hidden) != len(passed):
                raise ValueError(
                    f"occluded returned {len(hidden)} verdicts for {len(passed)} boxes"
                )
            verdict[passed[hidden]] = _OCCLUDED
        counts += np.bincount(verdict, minlength=len(counts))
        verdicts[pending] = verdict
        ok = verdict == 0
        occupied = np.concatenate([occupied, boxes[ok]])
        placed[pending[ok]] = own[ok]
        pending = pending[~ok]
    accepted = np.flatnonzero(verdicts == 0)
    return PlacementResult(
        boxes=placed[accepted],
        accepted=accepted.astype(np.int64),
        rejected={reason: int(n) for reason, n in zip(REASONS, counts[1:], strict=True)},
        reasons=_REASON_NAMES[verdicts].astype(str),
        attempts=attempts,
    )


_OUT_OF_RANGE, _COLLISION, _OBSTACLE, _OCCLUDED = 1, 2, 3, 4  # verdicts: 1 + index in REASONS
_REASON_NAMES = np.array(["", *REASONS], dtype=object)  # by verdict


def _judge(
    boxes: np.ndarray,
    pending: np.ndarray,
    dims: np.ndarray,
    source_z: np.ndarray | None,
    occupied: np.ndarray,
    obstacles: _Obstacles,
    config: PlacementConfig,
) -> np.ndarray:
    """Set each box's height and return its verdict ``int64 (K,)``: 0 (placed) or 1 + the
    index of its rejection reason in :data:`REASONS`. ``boxes`` are the footprints with their
    clearance; the obstacle test takes the objects' own sizes, ``dims[pending]``."""
    verdict = np.zeros(len(boxes), dtype=np.int64)
    fits = np.isfinite(boxes[:, 0])
    verdict[~fits] = _OUT_OF_RANGE
    live = np.flatnonzero(fits)
    hit = np.zeros(len(live), dtype=bool)
    if len(occupied) and len(live):
        hit = bev_collisions(boxes[live], occupied).any(axis=1)
    if config.height_mode == "ground":
        boxes[live, 2] = obstacles.ground.height_at(boxes[live, :2]) + boxes[live, 5] / 2.0
    else:
        boxes[live, 2] = source_z[pending[live]]
    verdict[live[hit]] = _COLLISION
    live = live[~hit]
    own = boxes[live]
    own[:, 3:5] = dims[pending[live], :2]
    blocked = obstacles.count(own) > config.max_nonground_points
    verdict[live[blocked]] = _OBSTACLE
    live = live[~blocked]
    # First come, first placed: a box loses against earlier boxes of the batch that were placed.
    kept = np.zeros(len(live), dtype=bool)
    if len(live):
        candidates = boxes[live]
        _first_come(candidates, *heading_terms(candidates), kept)
    verdict[live[~kept]] = _COLLISION
    return verdict


class _Obstacles:
    """Counts of non-ground frame points in candidate boxes.

    The points in each box are found in one pass over the frame (a coarse BEV grid of the
    boxes' bounding squares, see :func:`drcpo.geometry.box_members`); only those are tested
    against the ground, with :meth:`GroundModel.is_ground`.
    """

    def __init__(self, points: np.ndarray, ground: GroundModel, tolerance: float) -> None:
        self.points = points
        self.ground = ground
        self.tolerance = tolerance

    def count(self, boxes: np.ndarray) -> np.ndarray:
        """Non-ground frame points inside each of ``boxes`` ``(M, 7)``: ``int64 (M,)``."""
        if len(boxes) == 0 or len(self.points) == 0:
            return np.zeros(len(boxes), dtype=np.int64)
        point, box = box_members(self.points, boxes)
        above = ~self.ground.is_ground(self.points.take(point, axis=0), self.tolerance)
        return np.bincount(box[above], minlength=len(boxes)).astype(np.int64)


# The z-buffer kernels below (moving to drcpo.occlusion) still call the rule by these names.
_heading_terms, _inside = heading_terms, in_box


def bev_collisions(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """``bool (A, B)``: whether the BEV footprints of ``(A, 7)`` and ``(B, 7)`` boxes overlap,
    i.e. their interiors intersect (:func:`drcpo.geometry.bev_overlap_area` ``> 0``; boxes that
    only touch do not collide).

    A separating-axis test on the four edge normals, exact up to float rounding (footprints
    within about 1e-12 m of touching may go either way, as the overlap area's own rounding does).
    """
    boxes_a = np.asarray(boxes_a, dtype=np.float64).reshape(-1, 7)
    boxes_b = np.asarray(boxes_b, dtype=np.float64).reshape(-1, 7)
    out = np.zeros((len(boxes_a), len(boxes_b)), dtype=bool)
    if out.size:
        _collisions(boxes_a, *heading_terms(boxes_a), boxes_b, *heading_terms(boxes_b), out)
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _projected_half(u_x, u_y, length, width, c, s):  # pragma: no cover - numba
    # Half the extent along the unit axis (u_x, u_y) of a length x width footprint whose
    # length runs along (c, s).
    return length / 2.0 * abs(u_x * c + u_y * s) + width / 2.0 * abs(-u_x * s + u_y * c)


@numba.njit(cache=True, nogil=True, inline="always")
def _overlap(ax, ay, al, aw, ca, sa, bx, by, bl, bw, cb, sb):  # pragma: no cover - numba
    # Interiors intersect <=> on every edge normal of either footprint the projections overlap
    # by more than zero (convex polygons: a separating line can be taken along an edge).
    dx, dy = bx - ax, by - ay
    reach = math.sqrt(al * al + aw * aw) / 2.0 + math.sqrt(bl * bl + bw * bw) / 2.0
    if dx * dx + dy * dy >= reach * reach:
        return False
    if abs(dx * ca + dy * sa) >= al / 2.0 + _projected_half(ca, sa, bl, bw, cb, sb):
        return False
    if abs(-dx * sa + dy * ca) >= aw / 2.0 + _projected_half(-sa, ca, bl, bw, cb, sb):
        return False
    if abs(dx * cb + dy * sb) >= bl / 2.0 + _projected_half(cb, sb, al, aw, ca, sa):
        return False
    return abs(-dx * sb + dy * cb) < bw / 2.0 + _projected_half(-sb, cb, al, aw, ca, sa)


@numba.njit(cache=True, nogil=True)
def _collisions(a, ca, sa, b, cb, sb, out):  # pragma: no cover - numba
    for i in range(a.shape[0]):
        for j in range(b.shape[0]):
            out[i, j] = _overlap(
                a[i, 0], a[i, 1], a[i, 3], a[i, 4], ca[i], sa[i],
                b[j, 0], b[j, 1], b[j, 3], b[j, 4], cb[j], sb[j],
            )  # fmt: skip


@numba.njit(cache=True, nogil=True)
def _first_come(boxes, cos, sin, kept):  # pragma: no cover - numba
    # Each box is kept unless it overlaps an earlier box that was kept.
    for i in range(boxes.shape[0]):
        kept[i] = True
        for j in range(i):
            if kept[j] and _overlap(
                boxes[i, 0], boxes[i, 1], boxes[i, 3], boxes[i, 4], cos[i], sin[i],
                boxes[j, 0], boxes[j, 1], boxes[j, 3], boxes[j, 4], cos[j], sin[j],
            ):  # fmt: skip
                kept[i] = False
                break


def _draw_round(
    boxes: np.ndarray,
    rows: np.ndarray,
    cos: np.ndarray,
    sin: np.ndarray,
    rng: np.random.Generator,
    config: PlacementConfig,
    half_angle: float,
) -> np.ndarray:
    """Draw centres for ``rows`` of ``boxes`` in place (NaN where the footprint cannot fit);
    the rows drawn that fit but leave the field of view (``half_angle`` < 0: none)."""
    u = rng.uniform(0.0, 1.0, (len(rows), 2))
    (x0, x1), (y0, y1) = config.x_range, config.y_range
    return _centres(boxes, rows, cos, sin, u, x0, x1, y0, y1, half_angle)


@numba.njit(cache=True, nogil=True)
def _centres(boxes, rows, cos, sin, u, x0, x1, y0, y1, half_angle):  # pragma: no cover - numba
    # Uniform over the centres whose footprint's bounds (half extents) stay in the area.
    outside = np.empty(rows.shape[0], np.int64)
    count = 0
    for k in range(rows.shape[0]):
        r = rows[k]
        c, s = abs(cos[r]), abs(sin[r])
        reach_x = (c * boxes[r, 3] + s * boxes[r, 4]) / 2.0
        reach_y = (s * boxes[r, 3] + c * boxes[r, 4]) / 2.0
        low_x, low_y = x0 + reach_x, y0 + reach_y
        high_x, high_y = x1 - reach_x, y1 - reach_y
        if low_x > high_x or low_y > high_y:
            boxes[r, 0] = boxes[r, 1] = np.nan
            continue
        boxes[r, 0] = low_x + u[k, 0] * (high_x - low_x)
        boxes[r, 1] = low_y + u[k, 1] * (high_y - low_y)
        if half_angle >= 0 and not _corners_in_fov(boxes[r], cos[r], sin[r], half_angle):
            outside[count] = r
            count += 1
    return outside[:count].copy()


def _in_fov(boxes: np.ndarray, half_angle: float) -> np.ndarray:
    """``bool (K,)``: every BEV corner at an azimuth within ``half_angle`` (NaN rows: False)."""
    inside = np.zeros(len(boxes), dtype=bool)
    if len(boxes):
        _fov_test(boxes, *heading_terms(boxes), float(half_angle), inside)
    return inside


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


def _check_dims(dims: np.ndarray) -> np.ndarray:
    dims = np.asarray(dims, dtype=np.float64)
    if dims.size == 0:
        return dims.reshape(0, 3)
    if dims.ndim != 2 or dims.shape[1] != 3:
        raise DataError(f"dims must have shape (K, 3), got {dims.shape}")
    if not (np.isfinite(dims).all() and (dims > 0).all()):
        bad = int(np.flatnonzero(~(np.isfinite(dims) & (dims > 0)).all(axis=1))[0])
        raise DataError(f"dims[{bad}] = {dims[bad].tolist()} is not a positive finite size")
    return dims


def _source_heights(
    source_boxes: np.ndarray | None, count: int, config: PlacementConfig
) -> np.ndarray | None:
    if config.height_mode != "source":
        return None
    if source_boxes is None:
        raise DataError('height_mode "source" needs the source boxes (source_boxes is None)')
    source_boxes = np.asarray(source_boxes, dtype=np.float64).reshape(-1, 7)
    if len(source_boxes) != count:
        raise DataError(f"source_boxes has {len(source_boxes)} rows; dims has {count}")
    if not np.isfinite(source_boxes[:, 2]).all():
        raise DataError("source_boxes hold a non-finite z")
    return source_boxes[:, 2]


def frame_ground(frame: Frame) -> GroundModel:
    """The frame's ground estimate (with its KITTI road plane when it has one and a calib).

    Uses a fixed RANSAC seed, so a frame always gets the same ground.
    """
    plane, calib = frame.metadata.get("plane"), frame.metadata.get("calib")
    if plane is not None and calib is not None:
        return GroundModel.from_points(frame.points, plane=plane, calib=calib)
    return GroundModel.from_points(frame.points)


# Occlusion by the frame ----------------------------------------------------------------------
class OcclusionMap:
    """Nearest range per (azimuth, elevation) cell of a point cloud seen from a viewpoint: a
    z-buffer used to reject placements hidden behind the frame before anything is built.

    Cells are ``0.2 x 0.4`` degrees (about a KITTI HDL-64E's resolution). A box sample counts
    as occluded when its cell holds a point at least ``depth_tolerance`` metres nearer; cells
    without points occlude nothing, so gaps in the frame keep boxes visible. Non-finite points
    occlude nothing either.

    The buffer is filled lazily, only in the cells the queried boxes' samples fall in, and only
    with the points that may hide a sample there: one pass over the points per query, most of
    them set aside by their direction (a pseudo-angle bin and a slope, no trigonometry) before
    their cell is computed. :meth:`prepare` computes those directions once (say, on a thread
    that would otherwise wait); :meth:`occluded` does when they are missing.

    Args:
        points: ``(N, 3+)`` points, metres (not copied; do not modify them while querying).
        viewpoint: ``(3,)`` sensor position, metres.
        depth_tolerance: metres a point must lie in front of a sample to hide it.
    """

    AZIMUTH_STEP = math.radians(0.2)
    ELEVATION_STEP = math.radians(0.4)

    COLUMNS = math.ceil(2 * math.pi / AZIMUTH_STEP)
    ROWS = math.ceil(math.pi / ELEVATION_STEP) + 1

    def __init__(
        self, points: np.ndarray, viewpoint: np.ndarray, depth_tolerance: float = 0.5
    ) -> None:
        self.points = np.asarray(points)
        if self.points.ndim != 2 or self.points.shape[1] < 3:
            raise DataError(f"points must have shape (N, 3+), got {self.points.shape}")
        self.viewpoint = np.asarray(viewpoint, dtype=np.float64).reshape(3)
        self.tolerance = depth_tolerance
        # The cell arithmetic is float32, as the azimuth and elevation always were.
        self._constants = np.array(
            [
                math.pi,
                math.pi / 2,
                self.AZIMUTH_STEP,
                self.ELEVATION_STEP,
                depth_tolerance,
                *self.viewpoint,
            ],
            dtype=np.float32,
        )
        self._directions: tuple[np.ndarray, np.ndarray] | None = None

    def prepare(self) -> OcclusionMap:
        """Compute each point's direction bin and slope (see :meth:`occluded`); returns self."""
        if self._directions is None:
            bins = np.empty(len(self.points), np.int16)
            slopes = np.empty(len(self.points), np.float32)
            _point_directions(self.points, self._constants, bins, slopes)
            self._directions = bins, slopes
        return self

    def occluded(self, boxes: np.ndarray, cleared: np.ndarray | None = None) -> np.ndarray:
        """``float64 (M,)``: share of each ``(M, 7)`` box's sensor-facing surface samples
        occluded, leaving out the points inside the ``cleared`` boxes ``(C, 7)`` (the frame's
        points inside placed boxes are removed to make room for the objects)."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        cleared = np.asarray(np.zeros((0, 7)) if cleared is None else cleared, np.float64)
        cleared = cleared.reshape(-1, 7)
        share = np.zeros(len(boxes))
        if len(boxes) == 0:
            return share
        bins, slopes = self.prepare()._directions
        _occluded_share(
            self.points,
            bins,
            slopes,
            cleared,
            *_heading_terms(cleared),
            boxes,
            *_heading_terms(boxes),
            self.viewpoint,
            _FACE_GRIDS,
            _FACE_AXES,
            _FACE_SIGNS,
            self._constants,
            _DIRECTIONS,
            _AZIMUTH_FIRST,
            _AZIMUTH_SECOND,
            share,
        )
        return share


@numba.njit(cache=True, nogil=True)
def _point_directions(points, constants, bins, slopes):  # pragma: no cover - numba
    # Per point: its azimuth's pseudo-angle bin (-1: not finite, occludes nothing; -2: straight
    # above or below the viewpoint, always tested in full) and its slope z / horizontal, as
    # slope * |slope|.
    vx, vy, vz = constants[5], constants[6], constants[7]
    for i in range(points.shape[0]):
        x = np.float64(np.float32(points[i, 0]) - vx)
        y = np.float64(np.float32(points[i, 1]) - vy)
        z = np.float64(np.float32(points[i, 2]) - vz)
        if not np.isfinite(x + y + z):
            bins[i] = -1
        elif x == 0.0 and y == 0.0:
            bins[i] = -2
        else:
            bins[i] = min(int(_pseudo_angle(x, y) * (_BINS / 4.0)), _BINS - 1)
            slopes[i] = z * abs(z) / (x * x + y * y)  # slope * |slope|: monotone, no sqrt


def _face_templates(steps: tuple[int, int] = (12, 8)) -> tuple[np.ndarray, np.ndarray]:
    """Unit-box grids on the four sides and the top: ``(5, K, 3)`` and the faces' outward
    ``(axis, sign)`` pairs ``(5, 2)`` (the bottom rests on the ground, no one sees it)."""
    u, v = np.meshgrid(np.linspace(-0.5, 0.5, steps[0]), np.linspace(-0.5, 0.5, steps[1]))
    faces = ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0), (2, 1.0))
    grids = np.zeros((len(faces), u.size, 3))
    for f, (axis, sign) in enumerate(faces):
        u_axis, v_axis = (a for a in range(3) if a != axis)
        grids[f, :, u_axis], grids[f, :, v_axis], grids[f, :, axis] = (
            u.ravel(),
            v.ravel(),
            0.5 * sign,
        )
    return grids, np.array(faces)


_FACE_GRIDS, _FACES = _face_templates()
# 5 x 4 from edge to edge: an object e-HPR keeps often shows only a rim above an occluder.
_SURFACE_GRIDS = _face_templates((5, 4))[0]
_FACE_AXES, _FACE_SIGNS = _FACES[:, 0].astype(np.int64), _FACES[:, 1].copy()


def surface_samples(boxes: np.ndarray, viewpoint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points on the faces of each ``(M, 7)`` box that look towards ``viewpoint`` ``(3,)``:
    a 5 x 4 grid from edge to edge on each such side or top, ``(S, 3)`` metres, box ``m``'s
    being rows ``offsets[m]:offsets[m + 1]`` of ``offsets`` ``int64 (M + 1,)``."""
    world, facing = _facing_samples(boxes, viewpoint, _SURFACE_GRIDS)
    counts = facing.sum(axis=1) * _SURFACE_GRIDS.shape[1]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return world[facing].reshape(-1, 3), offsets


def _facing_samples(
    boxes: np.ndarray, viewpoint: np.ndarray, grids: np.ndarray = _FACE_GRIDS
) -> tuple[np.ndarray, np.ndarray]:
    """Samples ``(M, 5, K, 3)`` on the sides and top of each box in the LiDAR frame (the unit
    ``grids``, ``(5, K, 3)``), and which of those faces look towards ``viewpoint``:
    ``bool (M, 5)``.

    :meth:`OcclusionMap.occluded` computes the same samples (the facing ones only) in numba.
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    cos, sin = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    rel = viewpoint - boxes[:, :3]
    view = np.column_stack(
        [rel[:, 0] * cos + rel[:, 1] * sin, -rel[:, 0] * sin + rel[:, 1] * cos, rel[:, 2]]
    )
    axes, signs = _FACES[:, 0].astype(int), _FACES[:, 1]
    facing = signs * view[:, axes] > boxes[:, 3:6][:, axes] / 2.0
    local = grids[None] * boxes[:, None, None, 3:6]
    world = np.empty_like(local)
    c, s_ = cos[:, None, None], sin[:, None, None]
    world[..., 0] = c * local[..., 0] - s_ * local[..., 1] + boxes[:, None, None, 0]
    world[..., 1] = s_ * local[..., 0] + c * local[..., 1] + boxes[:, None, None, 1]
    world[..., 2] = local[..., 2] + boxes[:, None, None, 2]
    return world, facing


_ANGLE_SLACK = 1e-5  # radians; far above the float32 cell arithmetic's error (~1e-6)
_BINS = 8192  # pseudo-angle bins of each direction table; narrower than a cell (< 1e-3 rad)


def _direction_table(
    edges: np.ndarray, step: float, offset: float, count: int
) -> tuple[np.ndarray, ...]:
    """Per pseudo-angle bin (between consecutive angles of ``edges``, radians): the first cell
    ``floor((angle + offset) / step)`` (float32 constants) its directions may fall in, give or
    take the slack, and whether a cell boundary lies in it (0 or 1; -1: undecided, a seam).
    Also the unit vectors (cos, sin) of the ``count + 1`` cell boundaries."""
    step64, offset64 = float(np.float32(step)), float(np.float32(offset))
    low = np.floor((edges[:-1] - _ANGLE_SLACK + offset64) / step64).astype(np.int64)
    high = np.floor((edges[1:] + _ANGLE_SLACK + offset64) / step64).astype(np.int64)
    crosses = high - low
    crosses[(crosses < 0) | (crosses > 1)] = -1
    bound = np.arange(count + 1) * step64 - offset64
    return low, crosses, np.cos(bound), np.sin(bound)


def _azimuth_table() -> tuple[np.ndarray, ...]:
    p = np.arange(_BINS + 1) * (4.0 / _BINS)  # the inverse of _pseudo_angle at the bin edges
    x = np.select([p < 1, p < 2, p < 3], [1 - p, 1 - p, p - 3], p - 3)
    y = np.select([p < 1, p < 2, p < 3], [p, 2 - p, 2 - p], p - 4)
    edges = np.arctan2(y, x)
    edges[-1] = 0.0  # a full turn: the last bin ends just below azimuth 0
    return _direction_table(edges, OcclusionMap.AZIMUTH_STEP, math.pi, OcclusionMap.COLUMNS)


def _elevation_table() -> tuple[np.ndarray, ...]:
    q = np.arange(_BINS + 1) * (2.0 / _BINS) - 1.0  # the inverse of z / (h + |z|)
    edges = np.arctan2(q, np.where(q < 0, 1 + q, 1 - q))
    return _direction_table(edges, OcclusionMap.ELEVATION_STEP, math.pi / 2, OcclusionMap.ROWS)


@numba.njit(cache=True, nogil=True, inline="always")
def _pseudo_angle(x, y):  # pragma: no cover - numba
    # Monotone in the angle of (x, y) from +x counter-clockwise, in [0, 4); no trigonometry,
    # and selects rather than branches (the quadrants of a sweep's points are unpredictable).
    share = abs(y) / (abs(x) + abs(y))
    base = 0.0 if x >= 0.0 and y >= 0.0 else (4.0 if x >= 0.0 else 2.0)
    return base + share if (x >= 0.0) == (y >= 0.0) else base - share


@numba.njit(cache=True, nogil=True)
def _cell_of(x, y, z, constants, columns, rows):  # pragma: no cover - numba
    # Row and column of one float32 offset from the viewpoint by float32 trigonometry (libm's
    # atan2 and hypot, then the float32 cell arithmetic), as numpy computes them on float32
    # arrays up to its vectorised arctan2's last bit on some CPUs.
    azimuth = np.float32(math.atan2(y, x))
    elevation = np.float32(math.atan2(z, np.float32(np.hypot(x, y))))
    column = math.floor(np.float32(np.float32(azimuth + constants[0]) / constants[2]))
    row = math.floor(np.float32(np.float32(elevation + constants[1]) / constants[3]))
    return min(max(row, 0), rows - 1), column % columns


@numba.njit(cache=True, nogil=True, inline="always")
def _side(first, crosses, bound_cos, bound_sin, a, b, length):  # pragma: no cover - numba
    # The cell of direction (a, b) (angle atan2(b, a)) among first and first + 1, given the
    # unit vector of the boundary between them when one may lie in the direction's bin
    # (crosses); -1 when the direction lies within the slack of that boundary.
    if crosses == 0:
        return first
    if crosses < 0:
        return -1
    turn = bound_cos * b - bound_sin * a  # > 0: past the boundary
    margin = _ANGLE_SLACK * length
    if turn > margin:
        return first + 1
    if turn < -margin:
        return first
    return -1


@numba.njit(cache=True, nogil=True)
def _cells(
    offsets, az_low, az_cross, az_cos, az_sin, el_low, el_cross, el_cos, el_sin, constants, rows
):  # pragma: no cover - numba
    # Row and column ``int64 (n, 2)`` of float32 offsets ``(n, 3)`` from the viewpoint, as
    # _cell_of computes them, through the pseudo-angle tables and at most one boundary test
    # per angle; _cell_of decides the directions within the slack of a boundary.
    columns = az_cos.shape[0] - 1
    out = np.empty((offsets.shape[0], 2), np.int64)
    for i in range(offsets.shape[0]):
        x, y, z = offsets[i, 0], offsets[i, 1], offsets[i, 2]
        fx, fy, fz = np.float64(x), np.float64(y), np.float64(z)
        horizontal = math.sqrt(fx * fx + fy * fy)
        row = column = -1
        if horizontal > 0.0:
            b = min(int(_pseudo_angle(fx, fy) * (_BINS / 4.0)), _BINS - 1)
            first = az_low[b]
            column = _side(
                first, az_cross[b], az_cos[first + 1], az_sin[first + 1], fx, fy, horizontal
            )
            e = min(int((fz / (horizontal + abs(fz)) + 1.0) * (_BINS / 2.0)), _BINS - 1)
            first = el_low[e]
            length = math.sqrt(fx * fx + fy * fy + fz * fz)
            row = _side(
                first, el_cross[e], el_cos[first + 1], el_sin[first + 1], horizontal, fz, length
            )
        if column >= 0 and 0 < row < rows - 1:
            out[i, 0], out[i, 1] = row, column % columns
        else:
            out[i, 0], out[i, 1] = _cell_of(x, y, z, constants, columns, rows)
    return out


@numba.njit(cache=True, nogil=True)
def _occluded_share(
    points,
    bins,
    slopes,
    cleared,
    cleared_cos,
    cleared_sin,
    boxes,
    cos,
    sin,
    viewpoint,
    grids,
    axes,
    signs,
    constants,
    tables,
    az_first,
    az_second,
    share,
):  # pragma: no cover - numba
    columns, rows = tables[2].shape[0] - 1, tables[6].shape[0] - 1
    # 1. The samples of the faces that look at the viewpoint: offset and range of each.
    count, per_face = boxes.shape[0], grids.shape[1]
    sample_box = np.empty(count * grids.shape[0] * per_face, np.int64)
    offsets = np.empty((sample_box.shape[0], 3), np.float32)
    total = 0
    vx, vy, vz = constants[5], constants[6], constants[7]
    for m in range(count):
        rel_x, rel_y = viewpoint[0] - boxes[m, 0], viewpoint[1] - boxes[m, 1]
        view = (
            rel_x * cos[m] + rel_y * sin[m],
            -rel_x * sin[m] + rel_y * cos[m],
            viewpoint[2] - boxes[m, 2],
        )
        for f in range(grids.shape[0]):
            if not signs[f] * view[axes[f]] > boxes[m, 3 + axes[f]] / 2.0:
                continue
            for k in range(per_face):
                local_x = grids[f, k, 0] * boxes[m, 3]
                local_y = grids[f, k, 1] * boxes[m, 4]
                local_z = grids[f, k, 2] * boxes[m, 5]
                x = cos[m] * local_x - sin[m] * local_y + boxes[m, 0]
                y = sin[m] * local_x + cos[m] * local_y + boxes[m, 1]
                offsets[total, 0] = np.float32(x) - vx
                offsets[total, 1] = np.float32(y) - vy
                offsets[total, 2] = np.float32(local_z + boxes[m, 2]) - vz
                sample_box[total] = m
                total += 1
    if total == 0:
        return
    offsets = offsets[:total]
    sample_cell = _cells(offsets, *tables, constants, rows)
    # 2. Per column, the rows wanted and the range within which a point may hide a sample;
    #    the wanted cells get consecutive slots, column by column.
    low = np.full(columns, rows, np.int64)
    high = np.full(columns, -1, np.int64)
    reach = np.full(columns, -1.0)  # squared
    sample_range = np.empty(total, np.float32)
    depth = max(-np.float64(constants[4]), 0.0) + 1e-3
    el_offset, el_step = np.float64(constants[1]), np.float64(constants[3])
    for t in range(total):
        x, y, z = offsets[t, 0], offsets[t, 1], offsets[t, 2]
        sample_range[t] = np.float32(math.sqrt(x * x + y * y + z * z))  # as einsum sums
        r, c = sample_cell[t, 0], sample_cell[t, 1]
        low[c] = min(low[c], r)
        high[c] = max(high[c], r)
        reach[c] = max(reach[c], (np.float64(sample_range[t]) + depth) ** 2)
    slot = np.zeros(columns, np.int64)
    slope_low = np.full(columns, np.inf)  # elevations of the wanted rows (see slopes)
    slope_high = np.full(columns, -np.inf)
    slots = 0
    for c in range(columns):
        slot[c] = slots
        if high[c] < 0:
            continue
        slots += high[c] - low[c] + 1
        down = low[c] * el_step - el_offset - _ANGLE_SLACK
        up = (high[c] + 1) * el_step - el_offset + _ANGLE_SLACK
        slope_low[c] = -np.inf if low[c] == 0 or down <= -math.pi / 2 else math.tan(down)
        slope_high[c] = np.inf if high[c] >= rows - 2 or up >= math.pi / 2 else math.tan(up)
        # as the points' slopes are stored: slope * |slope|
        slope_low[c] *= abs(slope_low[c])
        slope_high[c] *= abs(slope_high[c])
    # 3. The points that may hide a sample: in a wanted column's direction bin, within its
    #    rows' elevations and near enough (no trigonometry: most points stop here).
    candidate = np.empty(points.shape[0], np.int64)
    near = np.empty((points.shape[0], 3), np.float32)
    found = 0
    for i in range(points.shape[0]):
        b = bins[i]
        if b == -1:
            continue
        # Seam bins (first < 0) and points straight above or below (b = -2): no shortcut.
        first = az_first[b] if b >= 0 else -1
        second = az_second[b] if b >= 0 else -1
        if first >= 0:
            if high[first] < 0 and high[second] < 0:
                continue
            slope = np.float64(slopes[i])
            if slope < min(slope_low[first], slope_low[second]):
                continue
            if slope > max(slope_high[first], slope_high[second]):
                continue
        x = np.float32(points[i, 0]) - vx
        y = np.float32(points[i, 1]) - vy
        z = np.float32(points[i, 2]) - vz
        if first >= 0:
            fx, fy, fz = np.float64(x), np.float64(y), np.float64(z)
            if fx * fx + fy * fy + fz * fz > max(reach[first], reach[second]):
                continue
        candidate[found] = i
        near[found, 0], near[found, 1], near[found, 2] = x, y, z
        found += 1
    # 4. Their cells, and the nearest range in each wanted cell of the points not cleared
    #    (the cleared boxes' BEV bounds, with slack, set most of them aside cheaply).
    bounds = np.empty((cleared.shape[0], 2))
    for k in range(cleared.shape[0]):
        c, s = abs(cleared_cos[k]), abs(cleared_sin[k])
        bounds[k, 0] = (cleared[k, 3] * c + cleared[k, 4] * s) / 2.0 + 1e-6
        bounds[k, 1] = (cleared[k, 3] * s + cleared[k, 4] * c) / 2.0 + 1e-6
    near = near[:found]
    cell = _cells(near, *tables, constants, rows)
    nearest = np.full(slots, np.inf, np.float32)
    for n in range(found):
        r, c = cell[n, 0], cell[n, 1]
        if not low[c] <= r <= high[c]:
            continue
        w = slot[c] + r - low[c]
        x, y, z = near[n, 0], near[n, 1], near[n, 2]
        distance = np.float32(math.sqrt(x * x + y * y + z * z))
        if distance >= nearest[w]:
            continue
        i = candidate[n]
        px, py, pz = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        gone = False
        for k in range(cleared.shape[0]):
            if abs(px - cleared[k, 0]) > bounds[k, 0] or abs(py - cleared[k, 1]) > bounds[k, 1]:
                continue
            if _inside(
                px,
                py,
                pz,
                cleared[k, 0],
                cleared[k, 1],
                cleared[k, 2],
                cleared[k, 3],
                cleared[k, 4],
                cleared[k, 5],
                cleared_cos[k],
                cleared_sin[k],
                0.0,
            ):
                gone = True
                break
        if not gone:
            nearest[w] = distance
    # 5. Each box's share of hidden samples.
    hidden = np.zeros(count, np.int64)
    seen = np.zeros(count, np.int64)
    tolerance = constants[4]
    for t in range(total):
        m = sample_box[t]
        seen[m] += 1
        r, c = sample_cell[t, 0], sample_cell[t, 1]
        if np.float32(nearest[slot[c] + r - low[c]] + tolerance) < sample_range[t]:
            hidden[m] += 1
    for m in range(count):
        if seen[m] > 0:
            share[m] = hidden[m] / seen[m]


_DIRECTIONS = (*_azimuth_table(), *_elevation_table())
# The columns of each azimuth bin (first -1: a seam bin), wrapped, for the points' quick test.
_AZIMUTH_FIRST = np.where(_DIRECTIONS[1] >= 0, _DIRECTIONS[0] % OcclusionMap.COLUMNS, -1)
_AZIMUTH_SECOND = (_DIRECTIONS[0] + np.maximum(_DIRECTIONS[1], 0)) % OcclusionMap.COLUMNS
