"""DR.CPO (Shin et al. 2023) as one transform: sample, place, construct, s-HPR, insert, e-HPR and
settle the labels; each step's work lives in its own module (:mod:`drcpo.placement`,
:mod:`drcpo.construction`, :mod:`drcpo.occlusion`, :mod:`drcpo.transforms.drcpo_insertion`),
this one orders them."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from functools import cache, partial
from typing import Any

import numpy as np

from drcpo import construction, occlusion, placement
from drcpo.config import DRCPOConfig, from_dict, to_dict
from drcpo.database import GroundTruthDatabase
from drcpo.errors import ConfigError
from drcpo.frame import VELOCITY, Frame
from drcpo.geometry import box_holding
from drcpo.index_build import indexed_mask
from drcpo.occlusion.view_windows import grown_boxes, surface_samples
from drcpo.transforms import drcpo_insertion, sweeps
from drcpo.transforms.base import Stats, Transform, config_body, register
from drcpo.transforms.drcpo_insertion import Inserted, Insertion
from drcpo.transforms.insertion import (
    BOX_SOURCE,
    BoxQuery,
    placed_object,
    sampling_pools,
    take_rows,
)

__all__ = [
    "DRCPO",
]


_FIT_PAD = 1e-4  # metres between a label's moved face and the point beyond it (see box_holding)


@register
class DRCPO(Transform):
    """DR.CPO: iterative construction, random placement and HPR occlusion (Shin et al. 2023).

    Per call:

    1. **Sample** ``sample[class]`` source objects per class, without replacement, among the
       objects that the candidate index covers and that have at least ``min_points`` points.
    2. **Place** (before any construction, so that rejected objects cost nothing): a random
       heading and position, the box bottom on the frame's ground estimate; rejected for
       ``out_of_range``, ``collision`` (BEV overlap with any box) or ``obstacle`` (more than
       ``max_non_ground_points`` non-ground frame points in
       the box); see :mod:`drcpo.placement`. Each footprint keeps :attr:`room` free around
       it, as the object's label may grow by that much (step 4). A placed box is rejected
       too (``occluded``) when e-HPR hides at least ``placement.occluded_fraction`` (default
       1.0: all) of a 5 x 4 grid of samples on each of its sensor-facing faces behind the
       frame's points, each sample decided exactly as a point added to them. e-HPR would almost
       always leave such an object too few points (the counts: ``docs/measurements.md``), so
       it is not built and hides nothing. Each object gets one pose, as in the paper.
    3. **Construct** each placed object from its indexed candidates (:mod:`drcpo.construction`).
    4. **s-HPR**: hidden point removal per object from the sensor origin with
       ``R = box diagonal x radius_factor``; an object left with fewer than ``min_points`` points
       is dropped (``self_occlusion``). The object's label is its placed box with the faces
       that points lie beyond moved out to hold them: construction keeps points up to
       ``construction.margin`` outside the source box, and s-HPR keeps the outermost.
    5. **Insert**: frame points within the accepted objects' room (their placed box grown by
       :attr:`room`) are removed, the objects' points added.
    6. **e-HPR** from the detector preset's viewpoint and radius, scoped to the inserted objects
       (the paper runs it over the whole frame, which drops the sampled objects that others hide
       and trains a worse detector, ``docs/detection.md``). It first removes the
       inserted points that are hidden; an object then left with fewer than
       ``min_points_after`` points in its box is dropped (see 7). It then removes the original
       points that lie behind the box of an object kept, in its view window (the azimuth and
       elevation it covers), and are hidden with the objects but visible without them.
       Visibility is decided only for those points, each exactly against the whole frame (HPR
       queries), so HPR's own errors never delete real, visible points and directions without
       inserted objects cost nothing.
    7. **Labels**: an object dropped by e-HPR goes with all its points (reason
       ``external_occlusion``), and the frame points it displaced come back (those it alone
       hid were never removed). An original box that lost points
       and holds fewer than ``min_points_after`` is dropped, unless it already had fewer
       before.

    Args:
        database: the ground-truth database (canonical points).
        index: its :class:`~drcpo.index.CandidateIndex`.
        config: a :class:`~drcpo.config.DRCPOConfig` (the paper defaults when ``None``) or a
            mapping of its keys.

    The transform holds only read-only state (database, index, config, per-class row pools),
    so it is safe to share with forked workers.
    """

    name = "drcpo"

    def __init__(
        self,
        database: GroundTruthDatabase,
        index: Any,
        config: DRCPOConfig | Mapping[str, Any] | None = None,
    ) -> None:
        if isinstance(config, Mapping) or config is None:
            config = from_dict(DRCPOConfig, config, "drcpo")
        if not isinstance(config, DRCPOConfig):
            raise TypeError(f"config must be a DRCPOConfig or a mapping, got {type(config)}")
        self.config: DRCPOConfig = config
        self.database = database
        self.index = index
        # Per frame, placement inside the camera's view or not; always with room for the label.
        self._placement = {
            fov: dataclasses.replace(config.placement, fov_only=fov, clearance=self.room)
            for fov in (False, True)
        }
        classes = [name for name, count in config.sample.items() if count > 0]
        index.check_matches(database, config.construction, classes)
        indexed = indexed_mask(database, index.config)
        self._pools = {
            name: pool[indexed[pool]]
            for name, pool in sampling_pools(
                database, classes, config.min_points, config.exclude_difficulty
            ).items()
        }
        for pool in self._pools.values():
            pool.setflags(write=False)

    @property
    def room(self) -> float:
        """Metres by which an object's label may exceed its placed box on any side: the
        construction margin (construction keeps points that far outside the source box)
        and twice :data:`_FIT_PAD`. Placement keeps that much room free around each box, and
        the frame's points within it make way for the object."""
        built = self.config.construction
        return float(built.margin) + 2.0 * _FIT_PAD

    @classmethod
    def from_config(
        cls,
        data: Mapping[str, Any],
        database: GroundTruthDatabase | None = None,
        index: Any = None,
        **_: Any,
    ) -> DRCPO:
        if database is None or index is None:
            raise ConfigError("DRCPO.from_config needs database=... and index=...")
        body = config_body(data, cls.__name__)
        body.pop("enabled", None)
        return cls(database, index, from_dict(DRCPOConfig, body, "DRCPO"))

    def to_config(self) -> dict[str, Any]:
        body = to_dict(self.config)
        body.pop("enabled")
        return {"type": type(self).__name__, **body}

    def __repr__(self) -> str:
        c = self.config
        return (
            f"DRCPO({self.database!r}, sample={c.sample}, "
            f"e_hpr_radius={c.external_occlusion.radius:g})"
        )

    # The steps ------------------------------------------------------------------------------
    def apply(self, frame: Frame, rng: np.random.Generator, stats: Stats) -> Frame:
        split = sweeps.split_sweeps(frame)
        if split is None:
            return self._apply(frame, rng, stats)
        # Multi-sweep: the steps on the key sweep, the others settled from their own origins.
        out = self._apply(split.key, rng, stats)
        settings = self.config.external_occlusion
        setting = settings if settings.enabled else None
        return split.join(out, "drcpo", self.room, setting)

    def _apply(self, frame: Frame, rng: np.random.Generator, stats: Stats) -> Frame:
        with stats.stage("drcpo.sample", len(frame)):
            rows = self._sample(rng, stats)
        dim = frame.points.shape[1]
        frame_grid = self._frame_grid(frame, rows)
        with stats.stage("drcpo.placement", len(frame)):
            boxes, accepted = self._place(frame, rows, rng, stats, frame_grid)
            rows = rows[accepted]
        with stats.stage("drcpo.construction", 0) as record:
            objects = self._construct(rows, rng, stats)
            record["points_out"] = sum(len(o.points) for o in objects)
        points_in = sum(len(o.points) for o in objects)
        with stats.stage("drcpo.self_occlusion", points_in) as record:
            visible = [
                self._object_s_hpr(built.points, box, dim)
                for box, built in zip(boxes, objects, strict=True)
            ]
            insertions = self._insertions(rows, boxes, visible, stats)
            record["points_out"] = sum(len(i.points) for i in insertions)
        with stats.stage("drcpo.insert", len(frame)) as record:
            inserted = drcpo_insertion.insert(frame, insertions, self.room)
            record["points_out"] = len(inserted.points)
        with stats.stage("drcpo.external_occlusion", len(inserted.points)) as record:
            grid = frame_grid() if frame_grid is not None and insertions else None
            setting = self.e_hpr_setting() if self.config.external_occlusion.enabled else None
            keep, dropped = drcpo_insertion.scoped_e_hpr(
                inserted, insertions, setting, self.config.min_points_after, grid
            )
            record["points_out"] = int(keep.sum())
        with stats.stage("drcpo.labels", int(keep.sum())) as record:
            out = self._labels(frame, inserted, keep, dropped, insertions, stats)
            record["points_out"] = len(out)
        return out

    def _frame_grid(
        self, frame: Frame, rows: np.ndarray
    ) -> Callable[[], occlusion.FrameGrid] | None:
        """e-HPR's grid of the frame's points (e-HPR, and the ``occluded`` test of placement),
        as a call that builds it when first asked for and then returns it; ``None`` when
        nothing will need it."""
        settings = self.config.external_occlusion
        if not settings.enabled or len(rows) == 0:
            return None
        radius, viewpoint = self.e_hpr_setting()
        # In this thread's memory: the previous call's grid is done with.
        memory = occlusion.thread_grid_memory()
        return cache(
            partial(occlusion.FrameGrid.build, frame.points, viewpoint, radius, memory=memory)
        )

    def _sample(self, rng: np.random.Generator, stats: Stats) -> np.ndarray:
        """Source rows ``int64 (S,)``: per class, without replacement, from its pool."""
        chosen = []
        for name, count in self.config.sample.items():
            pool = self._pools.get(name)
            size = min(int(count), 0 if pool is None else len(pool))
            if size == 0:
                continue
            chosen.append(rng.choice(pool, size=size, replace=False))
            stats.tried(self.name, name, size)
        return np.concatenate(chosen).astype(np.int64) if chosen else np.zeros(0, np.int64)

    def _place(
        self,
        frame: Frame,
        rows: np.ndarray,
        rng: np.random.Generator,
        stats: Stats,
        frame_grid: Callable[[], occlusion.FrameGrid] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Placed boxes ``(A, 7)`` and the indices (into ``rows``) of the placed objects, each
        checked by placement (:mod:`drcpo.placement`), then by the ``occluded`` test."""
        if len(rows) == 0:
            return np.zeros((0, 7)), np.zeros(0, np.int64)
        source = np.asarray(self.database.boxes[rows], dtype=np.float64)
        dims = source[:, 3:6]
        camera = self.config.placement.camera_fov
        fov = camera == "always" or (camera == "auto" and bool(frame.metadata.get("fov_only")))
        limit = self.config.placement.occluded_fraction
        check = limit is not None and self.config.external_occlusion.enabled
        result = placement.place_objects(frame, dims, source, rng, self._placement[fov])
        if check and len(result.boxes):
            owners = self._room_owners(frame, result.boxes)
            hidden = self._occluded(result.boxes, owners, frame_grid(), limit)
            result = result.reject(hidden, "occluded")
        return self._placement_result(result, rows, stats)

    def _placement_result(
        self, result: placement.PlacementResult, rows: np.ndarray, stats: Stats
    ) -> tuple[np.ndarray, np.ndarray]:
        """The placed boxes and the indices of their objects; the others' reasons recorded."""
        names = self.database.names[rows]
        for i in np.flatnonzero(result.reasons != ""):
            stats.rejected(self.name, names[i], str(result.reasons[i]))
        return result.boxes, result.accepted

    def _room_owners(self, frame: Frame, boxes: np.ndarray) -> np.ndarray:
        """``int64 (N,)``: the placed box whose room (see :attr:`room`) holds each frame point
        (-1: none; placement keeps the rooms apart)."""
        return BoxQuery(frame.points).owners(grown_boxes(boxes, self.room))

    def _occluded(
        self,
        boxes: np.ndarray,
        owners: np.ndarray,
        grid: occlusion.FrameGrid,
        limit: float,
    ) -> np.ndarray:
        """``bool (B,)``: ``boxes`` whose sensor-facing surface e-HPR would hide behind the
        frame's points (``grid``) by at least ``limit``; the points in the rooms of the boxes
        placed (``owners``, see :meth:`_room_owners`) make way for them and hide nothing.
        Surface samples are decided exactly by HPR among the frame's points
        (:meth:`~drcpo.occlusion.FrameGrid.hidden_groups`; nothing is hidden where that test
        does not apply, see :meth:`~drcpo.occlusion.FrameGrid.groups_apply`)."""
        _, viewpoint = self.e_hpr_setting()
        samples, offsets = surface_samples(boxes, viewpoint)
        if not grid.groups_apply(samples):
            return np.zeros(len(boxes), dtype=bool)
        return grid.hidden_groups(samples, offsets, owners >= 0, limit)

    def _construct(self, rows: np.ndarray, rng: np.random.Generator, stats: Stats) -> list[Any]:
        """The sampled objects of source ``rows`` constructed."""
        objects = construction.construct_objects(
            self.database,
            rows,
            self.index.candidates[rows],
            rng,
            self.config.construction,
            self.index.max_counts,
        )
        for name, built in zip(self.database.names[rows], objects, strict=True):
            stats.construction(str(name), built.iterations)
        return objects

    def _object_s_hpr(
        self,
        canonical: np.ndarray,
        box: np.ndarray,
        dim: int,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One object's ``canonical`` points placed in ``box``, after s-HPR (one hull: the
        certified hull of drcpo.occlusion.hull, Qhull where it gives up; much faster than the
        per-point method), and its label: ``box`` with the faces points lie beyond (construction
        keeps points up to its margin outside) moved out to hold every point the object brings."""
        points = placed_object(canonical, box, dim)
        settings = self.config.self_occlusion
        if settings.enabled and len(points):
            visible = occlusion.self_occlusion(
                points, box, settings.radius_factor, method="reference"
            )
            points = take_rows(points, visible)
        return points, box_holding(box, points, _FIT_PAD)

    def _insertions(
        self,
        rows: np.ndarray,
        boxes: np.ndarray,
        visible: Sequence[tuple[np.ndarray, np.ndarray]],
        stats: Stats,
    ) -> list[Insertion]:
        """The objects left with at least ``self_occlusion.min_points`` points after s-HPR
        (``visible``: each object's placed points left and its label), the others rejected."""
        minimum = self.config.self_occlusion.min_points
        insertions = []
        for row, box, (points, label) in zip(rows, boxes, visible, strict=True):
            name = str(self.database.names[row])
            if len(points) < minimum:
                stats.rejected(self.name, name, "self_occlusion")
                continue
            insertions.append(Insertion(int(row), name, box, label, points))
        return insertions

    def e_hpr_setting(self) -> tuple[float, np.ndarray]:
        """e-HPR radius R (metres) and viewpoint ``(3,)``: ``viewpoint_z`` above the LiDAR
        frame's origin (``drcpo.external_occlusion``)."""
        setting = self.config.external_occlusion
        return float(setting.radius), np.array([0.0, 0.0, float(setting.viewpoint_z)])

    def _labels(
        self,
        frame: Frame,
        inserted: Inserted,
        keep: np.ndarray,
        dropped: np.ndarray,
        insertions: Sequence[Insertion],
        stats: Stats,
    ) -> Frame:
        """The output frame (:func:`~drcpo.transforms.drcpo_insertion.settle`), each object's
        fate and each original box dropped recorded."""
        for insertion, gone in zip(insertions, dropped, strict=True):
            if gone:
                stats.rejected(self.name, insertion.name, "external_occlusion")
            else:
                stats.added(self.name, insertion.name)
        kept = [i for i, gone in zip(insertions, dropped, strict=True) if not gone]
        added_values = {BOX_SOURCE: np.full(len(kept), "drcpo")}
        if kept and frame.metadata.get(VELOCITY) is not None and self.database.velocity is not None:
            # The source's canonical velocity turned to the new heading (a mirrored
            # construction keeps the source's: mirroring fills the shape, not the motion).
            headings = [i.box[6] for i in kept]
            added_values[VELOCITY] = self.database.velocities([i.row for i in kept], headings)
        out, drop_original = drcpo_insertion.settle(
            frame, inserted, keep, dropped, insertions, self.config.min_points_after, added_values
        )
        for name in frame.names[drop_original]:
            stats.label_dropped(str(name))
        return out
