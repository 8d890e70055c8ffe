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
  than ``ground_tolerance`` above the ground (walls, trees, unlabelled objects).

Objects are tried up to ``max_tries`` times (a fresh pose each time); the paper tries once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drcpo.errors import ConfigError, DataError
from drcpo.frame import Frame
from drcpo.geometry import bev_corners, bev_overlap_area, points_in_boxes
from drcpo.ground import GroundModel

REASONS = ("out_of_range", "collision", "obstacle")
HEIGHT_MODES = ("ground", "source")
#: Half of KITTI camera 2's horizontal field of view (radians), rounded up.
KITTI_FOV_HALF_ANGLE = float(np.deg2rad(41.0))
_FOV_ROUNDS = 32  # resampling rounds for positions outside the field of view
_OBSTACLE_CELL = 1.0  # metres; BEV cells used to preselect frame points near candidate boxes


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
    """

    x_range: tuple[float, float] = (0.0, 70.4)
    y_range: tuple[float, float] = (-40.0, 40.0)
    fov_only: bool = False
    fov_half_angle: float = KITTI_FOV_HALF_ANGLE
    height_mode: str = "ground"
    max_nonground_points: int = 10
    ground_tolerance: float = 0.2
    max_tries: int = 1

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
    _draw_positions(boxes, np.arange(len(dims)), rng, config)
    if config.fov_only:
        todo = np.flatnonzero(~_in_fov(boxes, config.fov_half_angle))
        for _ in range(_FOV_ROUNDS):
            todo = todo[np.isfinite(boxes[todo, 0])]
            if len(todo) == 0:
                break
            _draw_positions(boxes, todo, rng, config)
            todo = todo[~_in_fov(boxes[todo], config.fov_half_angle)]
        boxes[todo, :2] = np.nan
    return boxes


def place_objects(
    frame: Frame | dict,
    dims: np.ndarray,
    source_boxes: np.ndarray | None,
    rng: np.random.Generator,
    config: PlacementConfig | None = None,
    ground: GroundModel | None = None,
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
    """
    config = config or PlacementConfig()
    frame = Frame.from_dict(frame) if isinstance(frame, dict) else frame
    dims = _check_dims(dims)
    source_z = _source_heights(source_boxes, len(dims), config)
    if ground is None:
        ground = frame_ground(frame)
    obstacles = _Obstacles(frame.points, ground, config, dims)
    placed = np.full((len(dims), 7), np.nan)
    reasons = np.full(len(dims), "", dtype=object)
    rejected = dict.fromkeys(REASONS, 0)
    occupied = frame.boxes
    pending = np.arange(len(dims))
    attempts = 0
    for _ in range(config.max_tries):
        if len(pending) == 0:
            break
        attempts += len(pending)
        boxes = sample_poses(dims[pending], rng, config)
        verdict = _judge(boxes, pending, source_z, occupied, obstacles, ground, config)
        for reason in REASONS:
            rejected[reason] += int((verdict == reason).sum())
        reasons[pending] = verdict
        ok = verdict == ""
        placed[pending[ok]] = boxes[ok]
        occupied = np.concatenate([occupied, boxes[ok]])
        pending = pending[~ok]
    accepted = np.flatnonzero(reasons == "")
    return PlacementResult(
        boxes=placed[accepted],
        accepted=accepted.astype(np.int64),
        rejected=rejected,
        reasons=reasons.astype(str),
        attempts=attempts,
    )


def _judge(
    boxes: np.ndarray,
    pending: np.ndarray,
    source_z: np.ndarray | None,
    occupied: np.ndarray,
    obstacles: _Obstacles,
    ground: GroundModel,
    config: PlacementConfig,
) -> np.ndarray:
    """Set each box's height and return its verdict: ``""`` (placed) or a rejection reason."""
    verdict = np.full(len(boxes), "", dtype=object)
    fits = np.isfinite(boxes[:, 0])
    verdict[~fits] = "out_of_range"
    live = np.flatnonzero(fits)
    if config.height_mode == "ground":
        boxes[live, 2] = ground.height_at(boxes[live, :2]) + boxes[live, 5] / 2.0
    else:
        boxes[live, 2] = source_z[pending[live]]
    if len(occupied) and len(live):
        hit = (bev_overlap_area(boxes[live], occupied) > 0).any(axis=1)
        verdict[live[hit]] = "collision"
        live = live[~hit]
    blocked = obstacles.count(boxes[live]) > config.max_nonground_points
    verdict[live[blocked]] = "obstacle"
    live = live[~blocked]
    # First come, first placed: a box loses against earlier boxes of the batch that were placed.
    overlap = bev_overlap_area(boxes[live]) > 0
    kept = np.zeros(len(live), dtype=bool)
    for i in range(len(live)):
        kept[i] = not (overlap[i, :i] & kept[:i]).any()
    verdict[live[~kept]] = "collision"
    return verdict


class _Obstacles:
    """Non-ground frame points near candidate boxes, selected through a coarse BEV grid.

    The grid covers the placement area grown by the largest box's reach, plus a border row of
    cells on every side that collects the points outside it and is never selected.
    """

    def __init__(
        self, points: np.ndarray, ground: GroundModel, config: PlacementConfig, dims: np.ndarray
    ) -> None:
        self.points = points
        self.ground = ground
        self.tolerance = config.ground_tolerance
        reach = float(np.hypot(dims[:, 0], dims[:, 1]).max(initial=0.0)) / 2.0 + _OBSTACLE_CELL
        self.origin = np.array([config.x_range[0] - reach, config.y_range[0] - reach])
        span = np.array([config.x_range[1] + reach, config.y_range[1] + reach]) - self.origin
        inner = np.ceil(span / _OBSTACLE_CELL).astype(int)
        self.shape = (int(inner[0]) + 2, int(inner[1]) + 2)
        self._cells: np.ndarray | None = None

    def _point_cells(self) -> np.ndarray:
        """Flat cell ``int32 (N,)`` of every frame point, computed once, in place.

        Temporaries the size of a sweep cost about a millisecond each of page faults on small
        VMs, hence the in-place arithmetic in the points' own dtype.
        """
        if self._cells is None:
            scaled = np.subtract(self.points[:, 0], float(self.origin[0]))
            self._cells = self._axis_cells(scaled, self.shape[0])
            np.subtract(self.points[:, 1], float(self.origin[1]), out=scaled)
            self._cells *= self.shape[1]
            self._cells += self._axis_cells(scaled, self.shape[1])
        return self._cells

    @staticmethod
    def _axis_cells(scaled: np.ndarray, count: int) -> np.ndarray:
        """Cells 1 .. count - 2 inside, 0 and count - 1 outside (NaN goes to cell 0)."""
        scaled *= 1.0 / _OBSTACLE_CELL
        np.floor(scaled, out=scaled)
        scaled += 1.0
        # fmax/fmin drop NaN in favour of the bound, so non-finite points land in the border.
        np.fmax(scaled, 0.0, out=scaled)
        np.fmin(scaled, count - 1, out=scaled)
        return scaled.astype(np.int32)

    def count(self, boxes: np.ndarray) -> np.ndarray:
        """Non-ground frame points inside each of ``boxes`` ``(M, 7)``: ``int64 (M,)``."""
        if len(boxes) == 0 or len(self.points) == 0:
            return np.zeros(len(boxes), dtype=np.int64)
        cells = self._point_cells()
        wanted = np.zeros(self.shape, dtype=bool)
        radius = np.hypot(boxes[:, 3], boxes[:, 4]) / 2.0
        low = np.floor((boxes[:, :2] - radius[:, None] - self.origin) / _OBSTACLE_CELL) + 1
        high = np.floor((boxes[:, :2] + radius[:, None] - self.origin) / _OBSTACLE_CELL) + 2
        inner = np.array(self.shape) - 1
        low = np.clip(low, 1, inner).astype(np.int64)
        high = np.clip(high, 1, inner).astype(np.int64)
        for (x0, y0), (x1, y1) in zip(low, high, strict=True):
            wanted[x0:x1, y0:y1] = True
        # take: several times faster than boolean indexing of point rows
        candidates = self.points.take(np.flatnonzero(wanted.reshape(-1)[cells]), axis=0)
        above = candidates[~self.ground.is_ground(candidates, self.tolerance)]
        return points_in_boxes(above, boxes).sum(axis=0).astype(np.int64)


def _draw_positions(
    boxes: np.ndarray, rows: np.ndarray, rng: np.random.Generator, config: PlacementConfig
) -> None:
    """Draw centres for ``rows`` of ``boxes`` in place (NaN where the footprint cannot fit)."""
    cos, sin = np.abs(np.cos(boxes[rows, 6])), np.abs(np.sin(boxes[rows, 6]))
    dx, dy = boxes[rows, 3], boxes[rows, 4]
    extent = np.column_stack([cos * dx + sin * dy, sin * dx + cos * dy]) / 2.0
    low = np.array([config.x_range[0], config.y_range[0]]) + extent
    high = np.array([config.x_range[1], config.y_range[1]]) - extent
    u = rng.uniform(0.0, 1.0, (len(rows), 2))
    centre = low + u * (high - low)
    centre[(low > high).any(axis=1)] = np.nan
    boxes[rows, :2] = centre


def _in_fov(boxes: np.ndarray, half_angle: float) -> np.ndarray:
    """``bool (K,)``: every BEV corner at an azimuth within ``half_angle`` (NaN rows: False)."""
    corners = bev_corners(np.nan_to_num(boxes))
    azimuth = np.abs(np.arctan2(corners[..., 1], corners[..., 0]))
    return (azimuth <= half_angle).all(axis=1) & np.isfinite(boxes[:, 0])


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
