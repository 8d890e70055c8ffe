"""Ground-truth sampling (OpenPCDet's ``gt_sampling``): the conventional baseline's insertion."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from drcpo.collisions import bev_collisions
from drcpo.config import GTSamplingConfig, from_dict, to_dict
from drcpo.database import GroundTruthDatabase
from drcpo.errors import ConfigError
from drcpo.frame import VELOCITY, Frame
from drcpo.transforms.base import Stats, Transform, config_body, register
from drcpo.transforms.insertion import (
    BOX_SOURCE,
    BoxQuery,
    key_sweep,
    placed_objects,
    road_plane_heights,
    sampling_pools,
    take_rows,
    update_box_metadata,
    with_box_sources,
)

__all__ = ["GroundTruthSampling"]


@register
class GroundTruthSampling(Transform):
    """OpenPCDet's ground-truth sampling (``gt_sampling``).

    For each class, in the order of ``targets``: draw ``max(0, target - objects of that class in
    the frame)`` database objects without replacement (only objects with at least
    ``min_points`` points and a difficulty not in ``exclude_difficulty``), at their original
    place and heading. A drawn box whose BEV footprint overlaps an existing box, a box kept
    earlier, or another box drawn in the same round is dropped (as OpenPCDet does, both boxes of
    a colliding drawn pair go). With a KITTI road plane in ``frame.metadata["plane"]`` and a
    calibration in ``metadata["calib"]``, kept boxes are moved vertically so that their bottom
    lies on the plane; otherwise they keep their original height. Frame points inside kept boxes
    are removed and the objects' points appended, with the database's point features (a frame
    column the database lacks is 0, and a ``time_lag`` column 0: the key sweep). With velocities
    in the frame (``metadata["velocity"]``), an added box gets its object's own (the heading is
    unchanged), or 0 when the database has none.

    Args:
        database: the ground-truth database to draw from.
        targets: objects per class after sampling (existing ones count), e.g. ``{"Car": 20}``.
        min_points: fewest points an object must have to be drawn (one number, or per class).
        exclude_difficulty: difficulty codes never drawn (OpenPCDet's ``filter_by_difficulty``).
        use_road_plane: put boxes on the road plane when the frame has one.
    """

    name = "gt_sampling"

    def __init__(
        self,
        database: GroundTruthDatabase,
        targets: Mapping[str, int] | None = None,
        min_points: int | Mapping[str, int] = 5,
        exclude_difficulty: Sequence[int] = (),
        use_road_plane: bool = True,
    ) -> None:
        params: dict[str, Any] = {
            "min_points": min_points if isinstance(min_points, int) else dict(min_points),
            "exclude_difficulty": list(exclude_difficulty),
            "use_road_plane": use_road_plane,
        }
        if targets is not None:
            params["targets"] = dict(targets)
        self.config: GTSamplingConfig = from_dict(GTSamplingConfig, params, "GroundTruthSampling")
        self.database = database
        self._pools = sampling_pools(
            database,
            list(self.config.targets),
            self.config.min_points,
            self.config.exclude_difficulty,
        )

    @classmethod
    def from_settings(
        cls, config: GTSamplingConfig, database: GroundTruthDatabase
    ) -> GroundTruthSampling:
        return cls(
            database,
            targets=config.targets,
            min_points=config.min_points,
            exclude_difficulty=config.exclude_difficulty,
            use_road_plane=config.use_road_plane,
        )

    @classmethod
    def from_config(
        cls, data: Mapping[str, Any], database: GroundTruthDatabase | None = None, **_: Any
    ) -> GroundTruthSampling:
        if database is None:
            raise ConfigError("GroundTruthSampling.from_config needs database=...")
        body = config_body(data, cls.__name__)
        body.pop("enabled", None)
        return cls.from_settings(from_dict(GTSamplingConfig, body, "GroundTruthSampling"), database)

    def to_config(self) -> dict[str, Any]:
        body = to_dict(self.config)
        body.pop("enabled")
        return {"type": type(self).__name__, **body}

    def __repr__(self) -> str:
        body = self.to_config()
        body.pop("type")
        params = ", ".join(f"{k}={v!r}" for k, v in body.items())
        return f"GroundTruthSampling({self.database!r}, {params})"

    def apply(self, frame: Frame, rng: np.random.Generator, stats: Stats) -> Frame:
        with stats.stage(self.name, len(frame)) as record:
            rows, boxes = self._draw(frame, rng, stats)
            out = self._insert(frame, rows, boxes)
            record["points_out"] = len(out)
            return out

    def _draw(
        self, frame: Frame, rng: np.random.Generator, stats: Stats
    ) -> tuple[np.ndarray, np.ndarray]:
        """Rows and boxes ``(S, 7)`` of the drawn objects that survive the collision checks."""
        kept_boxes = [frame.boxes]
        kept_rows = []
        for name, target in self.config.targets.items():
            pool = self._pools[name]
            wanted = max(0, int(target) - int(np.count_nonzero(frame.names == name)))
            count = min(wanted, len(pool))
            if count == 0:
                continue
            rows = rng.choice(pool, size=count, replace=False)
            boxes = self.database.boxes[rows]
            stats.tried(self.name, name, count)
            existing = np.concatenate(kept_boxes)
            # Overlap area > 0, as OpenPCDet's BEV IoU test, by separating axes (same verdicts).
            hits_existing = bev_collisions(boxes, existing).any(axis=1)
            among = bev_collisions(boxes, boxes)
            np.fill_diagonal(among, False)
            valid = ~hits_existing & ~among.any(axis=1)
            stats.rejected(self.name, name, "collision", int(np.count_nonzero(~valid)))
            stats.added(self.name, name, int(np.count_nonzero(valid)))
            kept_boxes.append(boxes[valid])
            kept_rows.append(rows[valid])
        rows = np.concatenate(kept_rows) if kept_rows else np.zeros(0, dtype=np.int64)
        boxes = np.array(self.database.boxes[rows], dtype=np.float64).reshape(-1, 7)
        return rows, boxes

    def _insert(self, frame: Frame, rows: np.ndarray, boxes: np.ndarray) -> Frame:
        if len(rows) == 0:
            return frame
        plane, calib = frame.metadata.get("plane"), frame.metadata.get("calib")
        if self.config.use_road_plane and plane is not None and calib is not None:
            bottoms = boxes[:, 2] - boxes[:, 5] / 2.0
            boxes[:, 2] += road_plane_heights(plane, calib, boxes[:, :3]) - bottoms
        keep = ~BoxQuery(frame.points).inside_any(boxes)
        objects = key_sweep(
            placed_objects(self.database, rows, boxes, frame.points.shape[1]), frame
        )
        points = np.concatenate([take_rows(frame.points, keep), objects])
        names = np.concatenate([frame.names, self.database.names[rows].astype(str)])
        db = self.database
        added_values = {
            "difficulty": db.difficulty[rows],
            "occlusion": db.occlusion[rows],
            "truncation": db.truncation[rows],
            "num_points_in_gt": db.num_points[rows],
            BOX_SOURCE: np.full(len(rows), "gt_sampling"),
        }
        if frame.metadata.get(VELOCITY) is not None and db.velocity is not None:
            added_values[VELOCITY] = db.velocities(rows, boxes[:, 6])
        metadata = update_box_metadata(
            with_box_sources(frame.metadata, len(frame.boxes)),
            len(frame.boxes),
            added=len(rows),
            added_values=added_values,
        )
        return frame.replace(
            points=points,
            boxes=np.concatenate([frame.boxes, boxes]),
            names=names,
            metadata=metadata,
        )
