"""The :class:`Frame`: one LiDAR sweep with its labelled boxes.

Coordinate conventions (used everywhere in drcpo)
-------------------------------------------------
* LiDAR frame: x forward, y left, z up, metres; the sensor sits at the origin.
* Points: ``float32 (N, 3 + C)``; columns x, y, z, then C features (KITTI: C = 1, intensity).
* Boxes: ``(M, 7)`` rows ``x, y, z, dx, dy, dz, heading``: ``(x, y, z)`` is the box *centre*,
  ``dx`` the length (along the heading), ``dy`` the width, ``dz`` the height, ``heading`` the yaw in
  radians about +z, measured from +x towards +y. This is OpenPCDet's ``gt_boxes`` convention, so
  boxes pass between drcpo and OpenPCDet unchanged.
* Canonical pose of an object: box centre at the origin, heading 0, length along x.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from drcpo.errors import DataError

__all__ = [
    "DICT_FIELDS",
    "FRAME_FIELDS",
    "MAX_COORDINATE",
    "VELOCITY",
    "Frame",
    "FrameSequence",
    "rotate_velocities",
    "validate_frame",
]

#: Metadata key of the boxes' velocities: ``float64 (M, 2)`` vx, vy in the LiDAR frame, m/s
#: (nuScenes; 0 where unknown). OpenPCDet's and MMDetection3D's 9-value boxes are ``boxes``
#: followed by these two columns.
VELOCITY = "velocity"


@dataclass(frozen=True, eq=False)
class Frame:
    """One LiDAR frame: points, boxes (OpenPCDet convention) and class names.

    Attributes:
        points: ``float32 (N, 3 + C)`` x, y, z in metres, then C features.
        boxes: ``float64 (M, 7)`` x, y, z (centre), dx, dy, dz (metres), heading (radians).
        names: ``(M,)`` class names (numpy unicode array).
        metadata: free-form extras, e.g. ``frame_id``, ``calib`` (a KITTI calibration), ``plane``.

    Points and boxes are held C-contiguous and writeable (copied when given otherwise, e.g.
    Fortran-ordered, sliced or read-only; never when already so), the one layout the compiled
    kernels see, so that :func:`drcpo.warmup` loads every kernel a later call needs.
    """

    points: np.ndarray
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    names: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype="<U1"))
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        points = _real_array(self.points, "points")
        if points.ndim != 2 or points.shape[1] < 3:
            raise DataError(f"Frame.points must have shape (N, 3 + C), got {points.shape}")
        boxes = _kernel_array(_real_array(self.boxes, "boxes"), np.float64)
        if boxes.size == 0:
            boxes = boxes.reshape(0, 7)
        if boxes.ndim != 2 or boxes.shape[1] != 7:
            raise DataError(f"Frame.boxes must have shape (M, 7), got {boxes.shape}")
        names = _name_array(self.names)
        if names.size == 0:
            names = np.zeros(0, dtype="<U1")
        if names.shape != (boxes.shape[0],):
            raise DataError(
                f"Frame.names must have shape ({boxes.shape[0]},) to match boxes, got {names.shape}"
            )
        with np.errstate(over="ignore"):  # values beyond float32 become inf: validate_frame
            object.__setattr__(self, "points", _kernel_array(points, np.float32))
        object.__setattr__(self, "boxes", boxes)
        object.__setattr__(self, "names", names.astype(str, copy=False))

    @property
    def frame_id(self) -> str | None:
        return self.metadata.get("frame_id")

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def replace(self, **changes: Any) -> Frame:
        """A new frame with some fields replaced (arrays are not copied)."""
        return replace(self, **changes)

    def validate(self, source: str = "frame") -> Frame:
        """This frame, after :func:`validate_frame` (raises :class:`DataError` naming
        ``source``)."""
        return validate_frame(self, source)

    # OpenPCDet data-dict interop -------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """OpenPCDet-style data dict: ``points``, ``gt_boxes``, ``gt_names`` plus the metadata."""
        out: dict[str, Any] = dict(self.metadata)
        out.update(points=self.points, gt_boxes=self.boxes, gt_names=self.names)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Frame:
        """Build a frame from an OpenPCDet-style dict; other keys become metadata.

        ``gt_boxes`` of 9 columns (nuScenes: x, y, z, dx, dy, dz, heading, vx, vy) give their
        velocities to ``metadata["velocity"]`` (:data:`VELOCITY`) unless the dict has that key;
        other columns after the seventh are dropped (OpenPCDet appends a class column in some
        stages)."""
        if "points" not in data:
            raise DataError("data dict has no 'points' key")
        metadata = {k: v for k, v in data.items() if k not in ("points", "gt_boxes", "gt_names")}
        boxes = _real_array(data.get("gt_boxes", np.zeros((0, 7))), "gt_boxes")
        boxes = boxes.astype(np.float64, copy=False)
        if boxes.ndim == 2 and boxes.shape[1] == 9 and metadata.get(VELOCITY) is None:
            metadata[VELOCITY] = np.array(boxes[:, 7:9])
        if boxes.ndim == 2 and boxes.shape[1] > 7:
            boxes = boxes[:, :7]
        names = data.get("gt_names", np.zeros(len(boxes), dtype="<U1"))
        return cls(points=data["points"], boxes=boxes, names=np.asarray(names), metadata=metadata)


class FrameSequence(ABC):
    """A data set as a sequence of frames: ``len``, indexing and iteration over ``frame_ids``
    through ``frame(frame_id)`` (the data sets' protocol; the readers derive from it)."""

    frame_ids: list[str]

    @abstractmethod
    def frame(self, frame_id: str) -> Frame:
        """The frame ``frame_id`` (one of :attr:`frame_ids`)."""

    def __len__(self) -> int:
        return len(self.frame_ids)

    def __getitem__(self, index: int) -> Frame:
        return self.frame(self.frame_ids[index])

    def __iter__(self) -> Iterator[Frame]:
        return (self.frame(frame_id) for frame_id in self.frame_ids)


#: Largest coordinate (and box size) accepted, metres. LiDAR ranges stay below a few hundred
#: metres; at a million metres float32 keeps about 6 cm of resolution, and the grids and
#: squared ranges of the geometry kernels stay far from overflow.
MAX_COORDINATE = 1e6

#: Field names in messages, for a :class:`Frame` and for an OpenPCDet data dict.
FRAME_FIELDS = ("points", "boxes", "names")
DICT_FIELDS = ("points", "gt_boxes", "gt_names")


def validate_frame(
    frame: Frame, source: str = "frame", fields: tuple[str, str, str] = FRAME_FIELDS
) -> Frame:
    """Check a frame's values; return it unchanged or raise :class:`DataError`.

    Shapes, dtypes and the names' length are checked when a :class:`Frame` is made; this adds
    the values: every point value (x, y, z and features) and every box value finite, point
    coordinates and box values within :data:`MAX_COORDINATE`, box sizes ``dx, dy, dz``
    positive, a road plane in ``metadata["plane"]`` (when not ``None``) four
    finite numbers, and velocities in ``metadata["velocity"]`` (:data:`VELOCITY`, when not
    ``None``) real numbers of shape ``(M, 2)``, all finite. The message names ``source``, the
    field (``fields``: the names of points, boxes and names to use, e.g.
    :data:`DICT_FIELDS`), the first bad row and its values.

    Cheap enough to run on every frame: whole-array checks first (one pass each), the row is
    looked for only once one has failed.
    """
    points, boxes = frame.points, frame.boxes
    # One pass for the usual case: every value finite and within the limit (NaN fails it).
    if len(points) and not np.abs(points).max() <= MAX_COORDINATE:
        _check_rows(points, source, fields[0])
    if len(boxes) and not np.abs(boxes).max() <= MAX_COORDINATE:
        _check_rows(boxes, source, fields[1], boxes.shape[1])
    if len(boxes) and not (boxes[:, 3:6] > 0).all():
        row = int(np.flatnonzero(~(boxes[:, 3:6] > 0).all(axis=1))[0])
        raise DataError(
            f"{source}: {fields[1]} row {row} (class {str(frame.names[row])!r}) has a "
            f"non-positive size (dx, dy, dz) = {boxes[row, 3:6].tolist()}"
        )
    plane = frame.metadata.get("plane")
    if plane is not None:
        _check_plane(plane, source)
    velocity = frame.metadata.get(VELOCITY)
    if velocity is not None:
        _check_velocity(velocity, len(boxes), source)
    return frame


def _check_rows(values: np.ndarray, source: str, field: str, bounded: int = 3) -> None:
    """The slow path of :func:`validate_frame`: raise on the first row of ``values`` holding a
    NaN/inf value or, in its first ``bounded`` columns, a value beyond :data:`MAX_COORDINATE`
    (point features may be large)."""
    finite = np.isfinite(values).all(axis=1)
    if not finite.all():
        row = int(np.flatnonzero(~finite)[0])
        raise DataError(
            f"{source}: {field} row {row} holds a NaN or infinite value: {values[row].tolist()}"
        )
    near = (np.abs(values[:, :bounded]) <= MAX_COORDINATE).all(axis=1)
    if not near.all():
        row = int(np.flatnonzero(~near)[0])
        raise DataError(
            f"{source}: {field} row {row} holds a value beyond {MAX_COORDINATE:g} (metres): "
            f"{values[row].tolist()}"
        )


def _real_array(values: Any, field: str) -> np.ndarray:
    """``values`` as a numpy array of real numbers (integer or float), else :class:`DataError`
    naming ``field`` (strings, objects, booleans and complex numbers are refused)."""
    try:
        array = np.asarray(values)
    except (TypeError, ValueError) as exc:  # ragged nested lists
        raise DataError(f"{field}: not a rectangular array of numbers ({exc})") from None
    if array.dtype.kind not in "fiu":
        raise DataError(f"{field}: must hold real numbers, got dtype {array.dtype}")
    return array


def _kernel_array(values: np.ndarray, dtype: type) -> np.ndarray:
    """``values`` as a C-contiguous, writeable ``dtype`` array, copied only when it is not one.

    numba compiles (or loads from its cache) one kernel per argument type, and an array's type
    includes its layout (C, F or strided) and whether it is read-only: a Fortran-ordered,
    sliced or read-only input would make each process load another specialisation of every
    kernel it reaches (mmdet3d's ``LoadPointsFromFile`` gives Fortran-ordered points), which
    :func:`drcpo.warmup` could not have loaded for it. The values are unchanged.
    """
    if values.dtype == dtype and values.flags.c_contiguous and values.flags.writeable:
        return values
    return np.array(values, dtype=dtype, order="C")


def _name_array(values: Any) -> np.ndarray:
    """Class names as a numpy array of strings, else :class:`DataError`."""
    try:
        names = np.asarray(values)
    except (TypeError, ValueError) as exc:
        raise DataError(f"names: not a flat list of class names ({exc})") from None
    if names.size and names.dtype.kind not in "US":
        if names.dtype.kind != "O" or not all(isinstance(n, str) for n in names.ravel()):
            raise DataError(f"names: must be strings, got dtype {names.dtype}")
    return names


def _check_plane(plane: Any, source: str) -> None:
    try:
        values = np.asarray(plane, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{source}: metadata plane must be 4 numbers, got {plane!r}") from None
    if values.shape != (4,) or not np.isfinite(values).all():
        raise DataError(f"{source}: metadata plane must be 4 finite numbers, got {plane!r}")


def _check_velocity(velocity: Any, num_boxes: int, source: str) -> None:
    """``metadata["velocity"]``: real numbers, shape ``(num_boxes, 2)``, finite."""
    try:
        values = np.asarray(velocity)
    except (TypeError, ValueError):  # ragged nested lists
        values = None
    if values is None or values.dtype.kind not in "fiu":
        raise DataError(
            f"{source}: metadata {VELOCITY!r} must be real numbers (vx, vy per box, m/s), got "
            f"{type(velocity).__name__} of dtype {getattr(values, 'dtype', None)}"
        )
    if values.shape != (num_boxes, 2):
        raise DataError(
            f"{source}: metadata {VELOCITY!r} must have shape ({num_boxes}, 2) (vx, vy per "
            f"box), got {values.shape}"
        )
    finite = np.isfinite(values).all(axis=1)
    if not finite.all():
        row = int(np.flatnonzero(~finite)[0])
        raise DataError(
            f"{source}: metadata {VELOCITY!r} row {row} holds a NaN or infinite value: "
            f"{values[row].tolist()}"
        )


def rotate_velocities(velocity: np.ndarray, angle: np.ndarray | float) -> np.ndarray:
    """Velocities ``(S, 2)`` (vx, vy, m/s) turned by ``angle`` radians about z (one angle, or
    ``(S,)``: one per row): ``R(angle) v``, ``float64 (S, 2)``.

    An object stored in canonical pose (heading 0) with velocity ``v`` and placed at heading
    ``h`` moves with ``R(h) v``; the database stores ``R(-h0) v0`` for an object cut out at
    heading ``h0``.
    """
    v = np.asarray(velocity, dtype=np.float64).reshape(-1, 2)
    angle = np.asarray(angle, dtype=np.float64)
    cos, sin = np.cos(angle), np.sin(angle)
    return np.column_stack([cos * v[:, 0] - sin * v[:, 1], sin * v[:, 0] + cos * v[:, 1]])
