"""What every transform that inserts database objects into a frame shares: placing canonical
points in a box, box queries on the frame's points, keeping per-box metadata in step, and the
per-class pools of objects to draw from."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numba as nb
import numpy as np

from drcpo.config import per_class
from drcpo.database import GroundTruthDatabase
from drcpo.errors import DataError
from drcpo.frame import VELOCITY
from drcpo.geometry import box_members, heading_terms, rows_in_box

__all__ = [
    "BOX_SOURCE",
    "PER_BOX_METADATA",
    "STALE_WHEN_BOXES_CHANGE",
    "TIME_LAG",
    "BoxQuery",
    "key_sweep",
    "match_features",
    "placed_object",
    "placed_objects",
    "road_plane_heights",
    "sampling_pools",
    "take_rows",
    "time_lag_column",
    "update_box_metadata",
    "with_box_sources",
]


def take_rows(array: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``array[mask]`` for a boolean row mask, through ``take`` (faster for point arrays
    than boolean indexing; the same rows in the same order)."""
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


#: Name of the point feature holding each point's sweep time lag (seconds; 0: the key sweep).
TIME_LAG = "time_lag"


def time_lag_column(frame: Any) -> int | None:
    """The column of ``frame.points`` holding the sweep time lag, from the feature names in
    ``metadata["point_features"]`` (``None`` when it names none)."""
    names = frame.metadata.get("point_features")
    if names is None or TIME_LAG not in list(names):
        return None
    column = 3 + list(names).index(TIME_LAG)
    return column if column < frame.points.shape[1] else None


def key_sweep(points: np.ndarray, frame: Any, start: int = 0) -> np.ndarray:
    """``points`` (rows ``start:`` inserted into ``frame``) with their time lag 0, in place:
    an inserted object is seen in the key sweep, whatever sweep its database points came
    from (and a point's time lag names its sweep, see ``metadata["sweep_time_lags"]``).
    Unchanged when the frame has no time-lag column."""
    column = time_lag_column(frame)
    if column is not None and len(points) > start:
        points[start:, column] = 0.0
    return points


def placed_object(canonical: np.ndarray, box: np.ndarray, dim: int) -> np.ndarray:
    """``match_features(from_canonical(canonical, box), dim)`` in one compiled pass (the same
    values: the same float64 operations, with numpy's cos and sin of the heading)."""
    heading = np.float64(box[6])
    out = np.zeros((len(canonical), dim), dtype=np.float32)
    _place_rows(np.asarray(canonical, dtype=np.float32), np.cos(heading), np.sin(heading), box, out)
    return out


def placed_objects(
    database: GroundTruthDatabase, rows: np.ndarray, boxes: np.ndarray, dim: int
) -> np.ndarray:
    """The database objects ``rows`` placed in ``boxes`` ``(S, 7)``, one after the other, as
    :func:`placed_object` places each (``float32 (n, dim)``)."""
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
    :class:`~drcpo.datasets.kitti_coordinates.Calibration`. Same arithmetic as OpenPCDet's
    ``put_boxes_on_road_planes``: project the point into the camera frame, solve the plane for y
    there, and map the result back to LiDAR.
    """
    a, b, c, d = (float(v) for v in np.asarray(plane, dtype=np.float64).reshape(4))
    if abs(b) < 1e-9:
        shown = np.asarray(plane, dtype=np.float64).reshape(4).tolist()
        raise DataError(f"road plane {shown} is vertical (b = 0); cannot put boxes on it")
    rect = np.asarray(calib.lidar_to_rect(np.asarray(xyz, dtype=np.float32)), dtype=np.float32)
    rect[:, 1] = (-d - a * rect[:, 0] - c * rect[:, 2]) / b
    return np.asarray(calib.rect_to_lidar(rect))[:, 2].astype(np.float64)


class BoxQuery:
    """Repeated "which points lie in this box" queries on one point array.

    Holds contiguous float32 copies of the x and y columns so each query first selects the
    points in the box's axis-aligned BEV bounds (a few cheap comparisons) and tests only those
    exactly, with the points-in-box rule :func:`drcpo.geometry.in_box` (closed boxes). The
    pre-filter is a speed device only: its float32 bounds are widened by ``_SLACK``. (Sorting
    the points by x once instead costs more than it saves for the few dozen queries a frame
    needs.)

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
        cos, sin = (float(terms[0]) for terms in heading_terms(box))
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
        return rows_in_box(self.points, near, box, margin)

    def inside_any(self, boxes: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """``bool (N,)``: points in at least one of the ``(M, 7)`` boxes."""
        return self.owners(boxes, margin) >= 0

    def owners(self, boxes: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """``int64 (N,)``: the last of the ``(M, 7)`` boxes holding each point (-1: none).

        One pass over the points for all boxes (a per-box query scans every point again), with
        a coarse grid of the boxes' bounds (:func:`~drcpo.geometry.box_members`); the same
        rule as :meth:`inside`.
        """
        owner = np.full(len(self.points), -1, dtype=np.int64)
        point, box = box_members(self.points, boxes, margin)  # by point, then box
        last = np.flatnonzero(np.diff(point, append=len(owner)))  # a point's last box
        owner[point[last]] = box[last]
        return owner

    def counts(self, boxes: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """``int64 (M,)``: points in each box."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        box = box_members(self.points, boxes, margin)[1]
        return np.bincount(box, minlength=len(boxes)).astype(np.int64)

    def own_counts(
        self, owner: np.ndarray, boxes: np.ndarray | Sequence[np.ndarray], where: np.ndarray
    ) -> np.ndarray:
        """``int64 (M,)``: per box ``m``, the points with ``owner == m`` (``int (N,)``) and
        ``where`` (``bool (N,)``) that lie in it, in one pass."""
        owner, where = np.asarray(owner), np.asarray(where, dtype=bool)
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        point, box = box_members(self.points, boxes)
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
    "box_source": "",  # see BOX_SOURCE
    VELOCITY: 0.0,  # (M, 2) vx, vy: an added box whose source gives none stands still
}
#: Metadata key of a ``str (M,)`` array saying which stage added each box: ``""`` for the
#: frame's own, ``"gt_sampling"``, ``"drcpo"`` (multi-sweep frames and the benchmarks tell the
#: boxes apart by it).
BOX_SOURCE = "box_source"
#: Metadata that describes the original boxes as a whole and is dropped once they change.
STALE_WHEN_BOXES_CHANGE = ("labels",)


def with_box_sources(metadata: Mapping[str, Any], num_boxes: int) -> dict[str, Any]:
    """``metadata`` with a :data:`BOX_SOURCE` array for its ``num_boxes`` boxes (the frame's
    own, ``""``, when it has none or one of another length)."""
    out = dict(metadata)
    value = out.get(BOX_SOURCE)
    if value is None or np.ndim(value) != 1 or len(value) != num_boxes:
        out[BOX_SOURCE] = np.full(num_boxes, "", dtype="<U11")
    return out


def update_box_metadata(
    metadata: Mapping[str, Any],
    num_boxes: int,
    keep: np.ndarray | None = None,
    added: int = 0,
    added_values: Mapping[str, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Metadata with its per-box arrays (:data:`PER_BOX_METADATA`) matching new boxes.

    A per-box array has one row per box: ``(M,)`` or ``(M, k)`` (the velocities, ``(M, 2)``);
    one of another length is left as it is.

    Args:
        metadata: the frame's metadata (not modified).
        num_boxes: boxes before the change.
        keep: indices of the boxes kept, in order (``None``: all).
        added: boxes appended after the kept ones.
        added_values: values of the appended boxes per key, ``(added,)`` or ``(added, k)``
            (default: the fill value in every column).
    """
    if keep is None and added == 0:
        return dict(metadata)
    out = {k: v for k, v in metadata.items() if k not in STALE_WHEN_BOXES_CHANGE}
    for key, fill in PER_BOX_METADATA.items():
        value = metadata.get(key)
        if value is None or np.ndim(value) < 1 or len(value) != num_boxes:
            continue
        value = np.asarray(value)
        kept = value if keep is None else value[keep]
        extra = (added_values or {}).get(key)
        if extra is None:
            extra = np.full((added, *value.shape[1:]), fill)
        extra = np.asarray(extra).reshape(added, *value.shape[1:])
        out[key] = np.concatenate([kept, extra]).astype(
            np.result_type(value.dtype, np.asarray(fill).dtype), copy=False
        )
    return out


def sampling_pools(
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
