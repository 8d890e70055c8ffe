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

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from drcpo.errors import DataError


@dataclass(frozen=True, eq=False)
class Frame:
    """One LiDAR frame: points, boxes (OpenPCDet convention) and class names.

    Attributes:
        points: ``float32 (N, 3 + C)`` x, y, z in metres, then C features.
        boxes: ``float64 (M, 7)`` x, y, z (centre), dx, dy, dz (metres), heading (radians).
        names: ``(M,)`` class names (numpy unicode array).
        metadata: free-form extras, e.g. ``frame_id``, ``calib`` (a KITTI calibration), ``plane``.
    """

    points: np.ndarray
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    names: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype="<U1"))
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        points = np.asarray(self.points)
        if points.ndim != 2 or points.shape[1] < 3:
            raise DataError(f"Frame.points must have shape (N, 3 + C), got {points.shape}")
        boxes = np.asarray(self.boxes, dtype=np.float64)
        if boxes.size == 0:
            boxes = boxes.reshape(0, 7)
        if boxes.ndim != 2 or boxes.shape[1] != 7:
            raise DataError(f"Frame.boxes must have shape (M, 7), got {boxes.shape}")
        names = np.asarray(self.names)
        if names.size == 0:
            names = np.zeros(0, dtype="<U1")
        if names.shape != (boxes.shape[0],):
            raise DataError(
                f"Frame.names must have shape ({boxes.shape[0]},) to match boxes, got {names.shape}"
            )
        object.__setattr__(self, "points", points.astype(np.float32, copy=False))
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
        """Raise :class:`DataError` naming ``source`` on NaN/inf values or non-positive sizes."""
        if not np.isfinite(self.points[:, :3]).all():
            bad = int(np.flatnonzero(~np.isfinite(self.points[:, :3]).all(axis=1))[0])
            raise DataError(f"{source}: point {bad} has a NaN or infinite coordinate")
        if not np.isfinite(self.boxes).all():
            raise DataError(f"{source}: a box holds NaN or infinite values")
        if (self.boxes[:, 3:6] <= 0).any():
            raise DataError(f"{source}: a box has a non-positive size (dx, dy, dz)")
        return self

    # OpenPCDet data-dict interop -------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """OpenPCDet-style data dict: ``points``, ``gt_boxes``, ``gt_names`` plus the metadata."""
        out: dict[str, Any] = dict(self.metadata)
        out.update(points=self.points, gt_boxes=self.boxes, gt_names=self.names)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Frame:
        """Build a frame from an OpenPCDet-style dict; other keys become metadata."""
        if "points" not in data:
            raise DataError("data dict has no 'points' key")
        metadata = {k: v for k, v in data.items() if k not in ("points", "gt_boxes", "gt_names")}
        boxes = data.get("gt_boxes", np.zeros((0, 7)))
        boxes = np.asarray(boxes, dtype=np.float64)
        if boxes.ndim == 2 and boxes.shape[1] > 7:
            # OpenPCDet appends a class column to gt_boxes in some stages; keep the first seven.
            boxes = boxes[:, :7]
        names = data.get("gt_names", np.zeros(len(boxes), dtype="<U1"))
        return cls(points=data["points"], boxes=boxes, names=np.asarray(names), metadata=metadata)
