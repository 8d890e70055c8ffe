"""DR.CPO's sensor-true steps: what the ``realistic`` preset changes in :class:`~drcpo.DRCPO`.

* the frame's sensor (``drcpo.sensor``: a preset, or estimated from the frame's own points);
* the ground and the sensor estimated from the frame *without* the objects earlier stages added
  (ground-truth sampling's boxes: their points were recorded in other frames);
* the cheap visibility test of a placed box, before anything is built: enough of the sensor's
  rays reach it in front of the frame's returns and of the boxes placed before
  (:meth:`~drcpo.occlusion.rays.RangeImage.visible_rays`);
* s-HPR mode ``sensor``: each object rendered through the sensor
  (:func:`~drcpo.occlusion.render.render_object`);
* e-HPR mode ``sensor``: occlusion along the rays (:class:`~drcpo.occlusion.rays.RayOcclusion`),
  with the added boxes of earlier stages as inserted objects too;
* with ``placement.drop_hidden_added``: before placing, the added objects of earlier stages that
  the frame's rays leave with too few points dropped with their points
  (:meth:`SensorFrame.without_hidden_added`), so that they hold no room the last step frees.

Each function returns data; :mod:`drcpo.transforms.drcpo` orders the steps.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cache, cached_property, partial
from typing import Any

import numba
import numpy as np

from drcpo.collisions import bev_collisions
from drcpo.errors import DataError
from drcpo.frame import Frame
from drcpo.geometry import box_members
from drcpo.ground import GroundModel
from drcpo.occlusion.rays import PlacedView, RangeImage, RayOcclusion, element_radii
from drcpo.occlusion.render import point_cells, render_object
from drcpo.occlusion.sightlines import sight_lines_cross
from drcpo.occlusion.silhouettes import silhouette_gaps
from drcpo.placement import (
    PlacementConfig,
    PlacementResult,
    PlacementRounds,
    frame_ground,
)
from drcpo.poses import CentreCells
from drcpo.sensor import Sensor
from drcpo.sensor_config import SensorConfig
from drcpo.transforms.insertion import BOX_SOURCE, BoxQuery, take_rows, update_box_metadata

__all__ = [
    "Placing",
    "SensorFrame",
    "added_boxes",
    "displace_added",
    "place_along_rays",
    "place_clear_of",
    "render",
    "sensor_occlusion",
    "visible_returns",
]

_ADDED_MARGIN = 0.2  # metres around an added box whose points count as the added object's
_REPOSE_PASSES = 2  # new poses for the objects hidden once rendered: passes at most


def added_boxes(frame: Frame) -> np.ndarray:
    """``bool (M,)``: the frame's boxes that an earlier stage added (``box_source`` not ``""``)."""
    sources = frame.metadata.get(BOX_SOURCE)
    if sources is None or np.ndim(sources) != 1 or len(sources) != len(frame.boxes):
        return np.zeros(len(frame.boxes), dtype=bool)
    return np.asarray(sources) != ""


@dataclass(eq=False)
class SensorFrame:
    """One frame as the sensor-true steps see it (built lazily, once per call).

    Args:
        frame: the frame DR.CPO receives.
        config: its ``drcpo.sensor`` section.
    """

    frame: Frame
    config: SensorConfig
    fallback: str = field(default="", init=False)
    #: the frame placement left (:func:`displace_added`: without the objects displaced)
    after_placing: SensorFrame | None = field(default=None, init=False, repr=False)
    #: the placement of the call (kept through :meth:`without_added`, for its new poses)
    placing: Placing | None = field(default=None, init=False, repr=False)
    _view: tuple[tuple[int, float], PlacedView] | None = field(default=None, init=False, repr=False)

    @cached_property
    def added(self) -> np.ndarray:
        """``bool (M,)``: boxes added by earlier stages (see :func:`added_boxes`)."""
        return added_boxes(self.frame)

    @cached_property
    def added_owner(self) -> np.ndarray:
        """``int64 (N,)``: the added box (numbered among the added ones) holding each frame
        point, -1 for the frame's own points."""
        boxes = self.frame.boxes[self.added]
        if len(boxes) == 0:
            return np.full(len(self.frame), -1, dtype=np.int64)
        # (grown: a sampled object brings points up to a few cm outside its box)
        return BoxQuery(self.frame.points).owners(boxes, margin=_ADDED_MARGIN)

    @cached_property
    def _added_members(self) -> tuple[np.ndarray, np.ndarray]:
        """``(point, box)`` pairs of the frame's points inside added boxes (numbered among
        the added ones), found once for every :meth:`added_counts`."""
        return box_members(self.frame.points, self.frame.boxes[self.added])

    def added_counts(self, keep: np.ndarray) -> np.ndarray:
        """``int64 (K,)``: the frame's points of ``keep`` (``bool (N,)``) that lie in each
        added box."""
        point, box = self._added_members
        count = int(np.count_nonzero(self.added))
        return np.bincount(box[keep[point]], minlength=count).astype(np.int64)

    def boxes_with(self, boxes: Sequence[np.ndarray]) -> np.ndarray:
        """``float64 (K + A, 7)``: ``boxes`` (DR.CPO's objects, numbered first) then the
        added ones, in the numbering of :func:`sensor_occlusion`."""
        return np.concatenate([np.reshape(boxes, (-1, 7)), self.frame.boxes[self.added]])

    @cached_property
    def own_points(self) -> np.ndarray:
        """The frame's points without those of added objects."""
        if not self.added.any():
            return self.frame.points
        return take_rows(self.frame.points, self.added_owner < 0)

    @cached_property
    def sensor(self) -> Sensor:
        """The frame's sensor (``auto``: estimated from its own points; where a frame is too
        sparse or unordered to estimate from, the model's base sensor, noted in
        :attr:`fallback`)."""
        try:
            return self.config.sensor_for(self.own_points)
        except DataError as exc:
            self.fallback = str(exc)
            return self.config.base()

    def record(self) -> dict[str, Any] | None:
        """What :attr:`sensor` was, for the statistics; ``None`` when no step needed it."""
        if "sensor" not in self.__dict__:  # cached_property keeps its value there
            return None
        sensor = self.sensor
        return {
            "model": sensor.name,
            "beams": sensor.num_beams,
            "azimuth_step_deg": round(math.degrees(sensor.azimuth_step), 6),
            "fallback": self.fallback,
        }

    @cached_property
    def ground(self) -> GroundModel:
        """The ground estimated from the frame before earlier stages added objects."""
        frame = self.frame
        if self.added.any():
            frame = frame.replace(points=self.own_points)
        return frame_ground(frame)

    @cached_property
    def cells(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each frame point's ray cell and distance from its beam's origin
        (:func:`~drcpo.occlusion.render.point_cells`), found once for the steps that need them."""
        return point_cells(self.frame.points, self.sensor)

    @cached_property
    def range_image(self) -> RangeImage:
        """The frame's nearest return per ray cell (added objects included: they hide too)."""
        return RangeImage.from_cells(self.sensor, *self.cells)

    @cached_property
    def solid_image(self) -> RangeImage:
        """:attr:`range_image` with the added objects' boxes as solids (the last step makes
        each object solid, holes and all: nothing behind one is seen through it)."""
        return self.range_image.with_boxes(self.frame.boxes[self.added])

    def hidden_added(self, min_points: int, tolerance: float = 0.1) -> np.ndarray:
        """``bool (K,)``: of the ``K`` added boxes, those left with fewer than ``min_points``
        of their points in their box once the frame's returns hide theirs: a point of one is
        hidden when its ray cell (:meth:`~drcpo.sensor.Sensor.cells`) holds a return of the
        frame's own or of another added object nearer than it by more than ``tolerance``
        metres (ranges from the beam's origin). The cell rule of :func:`sensor_occlusion`
        for them (the added objects' surfaces crossing other cells are left to it)."""
        if not self.added.any():
            return np.zeros(0, dtype=bool)
        beam, column, distance = self.cells
        sensor = self.sensor
        cell = np.where(beam >= 0, beam * sensor.num_columns + column, -1)
        cells = sensor.num_beams * sensor.num_columns
        keep = ~_behind_other_owner(cell, distance, self.added_owner, float(tolerance), cells)
        return self.added_counts(keep) < min_points

    def without_hidden_added(self, min_points: int) -> tuple[SensorFrame, np.ndarray]:
        """This frame without the added objects of :meth:`hidden_added` (see
        :meth:`without_added`) and the names of those dropped."""
        return self.without_added(self.hidden_added(min_points))

    def without_added(self, drop: np.ndarray) -> tuple[SensorFrame, np.ndarray]:
        """This frame without the added objects ``drop`` (``bool (K,)`` over the added boxes):
        their boxes, and their points (those :attr:`added_owner` gives them, as
        :func:`sensor_occlusion` takes them out), and the names of those dropped. The frame's
        own points stay as they are, so the sensor and the ground are this one's (shared, not
        estimated again); ``self`` when nothing is dropped."""
        drop = np.asarray(drop, dtype=bool)
        if not drop.any():
            return self, np.zeros(0, dtype=str)
        frame = self.frame
        boxes = np.zeros(len(frame.boxes), dtype=bool)
        boxes[np.flatnonzero(self.added)[drop]] = True
        points = ~np.append(drop, False)[self.added_owner]  # (index -1: the frame's own)
        keep = np.flatnonzero(~boxes)
        pruned = frame.replace(
            points=take_rows(frame.points, points),
            boxes=frame.boxes[keep],
            names=frame.names[keep],
            metadata=update_box_metadata(frame.metadata, len(frame.boxes), keep=keep),
        )
        out = SensorFrame(pruned, self.config)
        out.fallback, out.placing = self.fallback, self.placing
        out.__dict__["sensor"] = self.sensor  # (cached_property keeps its value there)
        out.__dict__["ground"] = self.ground
        # the last kept added box holding each point left is the last of all holding it (the
        # points of the dropped ones went with them): numbered among the kept ones
        number = np.cumsum(~drop) - 1
        owner = self.added_owner[points]
        out.__dict__["added_owner"] = np.where(owner >= 0, number[owner.clip(0)], -1)
        if "cells" in self.__dict__:
            out.__dict__["cells"] = tuple(a[points] for a in self.cells)
        if "_added_members" in self.__dict__:  # the pairs of the points and boxes kept
            point, box = self._added_members
            pair = points[point] & ~drop[box]
            row = np.cumsum(points) - 1
            out.__dict__["_added_members"] = (row[point[pair]], number[box[pair]])
        return out, frame.names[boxes]

    def occlusion(
        self,
        points: np.ndarray,
        owner: np.ndarray,
        count_kept: Callable[[np.ndarray], np.ndarray],
        min_points: int,
        fill_holes: bool,
        boxes: Sequence[np.ndarray],
    ) -> tuple[np.ndarray, np.ndarray]:
        """:func:`sensor_occlusion` of this frame after insertion (``points``: its points
        first, all of them, then DR.CPO's objects', whose ``boxes`` these are), with what
        it knows: its points' cells, the added object holding each, the added objects'
        boxes and counts."""
        return sensor_occlusion(
            points,
            owner,
            self.added_owner,
            self.sensor,
            count_kept,
            self.added_counts,
            min_points,
            fill_holes,
            self.boxes_with(boxes),
            self.cells,
        )

    def hidden(
        self,
        boxes: np.ndarray,
        placed: np.ndarray,
        min_rays: int,
        max_hidden: float = 1.0,
        objects: np.ndarray | None = None,
        conflicts: np.ndarray | None = None,
    ) -> np.ndarray:
        """``bool (B,)``: the round's ``boxes`` to reject, first come first served: a box that
        fewer than ``min_rays`` rays would reach, or only ``1 - max_hidden`` of the rays that
        cross it (in front of the frame's returns and of the boxes accepted before it,
        ``placed`` and this round's), or that would leave one of those so (objects in a row
        along a street would hide each other). A box's share counts: the rays left reaching a
        mostly hidden box pass its corners, where the object leaves the box empty.

        ``objects``: the object of each box (a round may hold several poses of one, tried in
        turn: once one is accepted, its later ones are passed over, ``False``); ``conflicts``:
        see :class:`~drcpo.placement.Round` (a box conflicting with one accepted before is
        passed over; placement rejects it).

        The rounds of a call share one :class:`~drcpo.occlusion.rays.PlacedView` (the boxes
        accepted in earlier rounds are the ``placed`` ones), so each box is counted once."""
        view = self._view
        key = (int(min_rays), float(max_hidden))
        if view is None or view[0] != key or not view[1].holds(placed):
            view = self._view = (key, PlacedView(self.solid_image, *key, placed=placed))
        return view[1].admit(boxes, objects, conflicts)


@dataclass(eq=False)
class Placing:
    """The sensor-true placement of one call: its first pass (:func:`place_along_rays`, then
    :func:`displace_added`) and, once the objects are rendered, new poses for those that the
    frame and the others would hide (:meth:`repose`).

    Args:
        rounds: the first pass's rounds over the objects of sizes ``dims`` ``(K, 3)`` from
            ``source`` ``(K, 7)``, drawn with ``rng`` under ``config``.
        min_rays, max_hidden: the visibility test of :meth:`SensorFrame.hidden`.
    """

    seen: SensorFrame
    rounds: PlacementRounds
    dims: np.ndarray
    source: np.ndarray
    rng: np.random.Generator
    config: PlacementConfig
    min_rays: int
    max_hidden: float
    #: the objects the first pass placed (indices into ``dims``), once it ran
    accepted: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def first_pass(self) -> tuple[PlacementResult, np.ndarray]:
        """The placement and the names of the added objects displaced (see
        :func:`displace_added`; none with ``displace_attempts`` 0)."""
        result = place_along_rays(self.rounds, self.seen, self.min_rays, self.max_hidden)
        gone = np.zeros(0, dtype=str)
        if self.config.displace_attempts:
            result, gone = displace_added(
                self.seen, result, self.dims, self.source, self.rng, self.config,
                self.min_rays, self.max_hidden, self.rounds.cells,
            )  # fmt: skip
        self.accepted = result.accepted
        return result, gone

    def repose(
        self,
        seen: SensorFrame,
        boxes: np.ndarray,
        rendered: Sequence[tuple[np.ndarray, Any]],
        render: Callable[[int, np.ndarray], tuple[np.ndarray, Any]],
        min_points: int,
    ) -> tuple[np.ndarray, list[tuple[np.ndarray, Any]]]:
        """The placed ``boxes`` ``(A, 7)`` and their objects ``rendered`` (returns first) with
        new poses for the objects left with fewer than ``min_points`` returns that the frame
        and the other objects would not hide (:func:`visible_returns`), each
        rendered by ``render(k, box)``: up to ``_REPOSE_PASSES`` passes of
        ``repose_attempts`` poses per such object, placed as the first pass places (on
        ``seen``, the frame placement left), clear of the other objects' boxes and not hiding
        them. An object no new pose fits keeps its own."""
        boxes, rendered = np.array(boxes, dtype=np.float64), list(rendered)
        if not self.config.repose_attempts or len(boxes) == 0:
            return boxes, rendered
        for _ in range(_REPOSE_PASSES):
            counts = visible_returns(seen, rendered)
            hidden = np.flatnonzero(counts < min_points)
            if len(hidden) == 0:
                break
            others = np.delete(boxes, hidden, axis=0)
            result = self._place_again(seen, self.accepted[hidden], others)
            for k, box in zip(hidden[result.accepted], result.boxes, strict=True):
                boxes[k] = box
                rendered[k] = render(int(k), box)
        return boxes, rendered

    def _place_again(
        self, seen: SensorFrame, objects: np.ndarray, others: np.ndarray
    ) -> PlacementResult:
        """A pass of ``repose_attempts`` poses per object (``objects``: indices into
        ``dims``) on ``seen``, clear of ``others`` (see :func:`place_clear_of`)."""
        config = dataclasses.replace(
            self.config, attempts=self.config.repose_attempts, max_attempts_per_frame=None
        )
        dims, source = self.dims[objects], self.source[objects]
        return place_clear_of(seen, others, dims, source, self.rng, config, self.min_rays,
                              self.max_hidden, self.rounds.cells)  # fmt: skip


def visible_returns(
    seen: SensorFrame, rendered: Sequence[tuple[np.ndarray, np.ndarray]], tolerance: float = 0.1
) -> np.ndarray:
    """``int64 (A,)``: per object, its returns (``rendered[k]``: returns ``(n_k, 3+)`` and
    label box ``(7,)``) that neither the frame with the added objects as solids
    (:attr:`SensorFrame.solid_image`: a nearer return or box entry in the return's cell, by
    more than ``tolerance`` metres) nor another object's box in front (the sight line enters
    it, :func:`~drcpo.occlusion.sightlines.sight_lines_cross`) would hide."""
    count = len(rendered)
    sizes = np.array([len(r[0]) for r in rendered], dtype=np.int64)
    if count == 0 or sizes.sum() == 0:
        return np.zeros(count, dtype=np.int64)
    owner = np.repeat(np.arange(count), sizes)
    points = np.concatenate([r[0][:, :3] for r in rendered])
    beam, column, distance = point_cells(points, seen.sensor)
    on = beam >= 0
    free = np.zeros(len(points), dtype=bool)
    free[on] = seen.solid_image.ranges[beam[on], column[on]] >= distance[on] - tolerance
    labels = np.stack([r[1] for r in rendered])
    free[free] = ~sight_lines_cross(points[free], seen.sensor.mount, labels, owner[free])
    return np.bincount(owner[free], minlength=count)


def place_along_rays(
    rounds: PlacementRounds,
    seen: SensorFrame,
    min_rays: int,
    max_hidden: float,
    before: np.ndarray | None = None,
) -> PlacementResult:
    """Run ``rounds`` to the end, each round's boxes judged by :meth:`SensorFrame.hidden` (the
    boxes ``before`` ``(P, 7)``, placed by an earlier pass, count as placed before)."""
    before = np.zeros((0, 7)) if before is None else before
    while (drawn := rounds.next_round()) is not None:
        hidden = None
        if len(drawn.boxes):
            placed = np.concatenate([before, drawn.placed])
            hidden = seen.hidden(
                drawn.boxes, placed, min_rays, max_hidden, drawn.objects, drawn.conflicts
            )
        rounds.settle(hidden)
    return rounds.result()


def place_clear_of(
    seen: SensorFrame,
    placed: np.ndarray,
    dims: np.ndarray,
    source: np.ndarray,
    rng: np.random.Generator,
    config: PlacementConfig,
    min_rays: int,
    max_hidden: float,
    cells: CentreCells | None = None,
) -> PlacementResult:
    """A placement pass on ``seen`` for the objects of sizes ``dims`` ``(K, 3)`` from
    ``source`` ``(K, 7)`` under ``config``, with ``placed`` ``(P, 7)`` (grown by
    ``config.clearance``) as boxes to avoid and as placed before (:func:`place_along_rays`);
    ``cells``: the centre cells of an earlier pass on the same ground and area, when known
    (:attr:`~drcpo.placement.PlacementRounds.cells`)."""
    room = placed.copy()
    room[:, 3:5] += 2.0 * config.clearance
    frame = seen.frame.replace(
        boxes=np.concatenate([seen.frame.boxes, room]),
        names=np.concatenate([seen.frame.names, np.full(len(room), "DontCare")]),
    )
    rounds = PlacementRounds(frame, dims, source, rng, config, seen.ground, cells)
    return place_along_rays(rounds, seen, min_rays, max_hidden, placed)


def displace_added(
    seen: SensorFrame,
    first: PlacementResult,
    dims: np.ndarray,
    source: np.ndarray,
    rng: np.random.Generator,
    config: PlacementConfig,
    min_rays: int,
    max_hidden: float,
    cells: CentreCells | None = None,
) -> tuple[PlacementResult, np.ndarray]:
    """A second placement pass for the objects ``first`` left unplaced, through the objects
    earlier stages added (augmentation too, so they make way when no free spot is left).

    The pass places (``dims``, ``source``: ``(K, 3)``, ``(K, 7)`` of ``first``'s objects, with
    ``config``, ``displace_attempts`` poses per object within the poses of
    ``max_attempts_per_frame`` that ``first`` left) on the frame
    without any added object (their points are no obstacle, their returns hide nothing, their
    boxes no collision), with ``first``'s boxes (grown by ``config.clearance``) as boxes to
    avoid and as placed before. The added objects whose box meets a box placed there (with
    the clearance) are dropped: :attr:`SensorFrame.after_placing` is the frame without them
    (``seen`` when none). Returns the merged result (the second pass's verdicts for its
    objects) and the names of the objects displaced. ``cells``: see :func:`place_clear_of`."""
    seen.after_placing = seen
    failed = np.flatnonzero(first.reasons != "")
    if len(failed) == 0 or not seen.added.any():
        return first, np.zeros(0, dtype=str)
    bare, _ = seen.without_added(np.ones(int(np.count_nonzero(seen.added)), dtype=bool))
    cap = config.max_attempts_per_frame
    if cap is not None and cap <= first.attempts:
        return first, np.zeros(0, dtype=str)
    budget = None if cap is None else cap - first.attempts
    config = dataclasses.replace(
        config, attempts=config.displace_attempts, max_attempts_per_frame=budget
    )
    second = place_clear_of(bare, first.boxes, dims[failed], source[failed], rng, config,
                            min_rays, max_hidden, cells)  # fmt: skip
    grown = second.boxes.copy()
    grown[:, 3:5] += 2.0 * config.clearance
    added = seen.frame.boxes[seen.added]
    displaced = bev_collisions(added, grown).any(axis=1)
    seen.after_placing, names = seen.without_added(displaced)
    accepted = np.concatenate([first.accepted, failed[second.accepted]])
    order = np.argsort(accepted, kind="stable")
    # one dtype wide enough for both passes' names (a copy of first's would cut them short)
    reasons = first.reasons.astype(np.result_type(first.reasons, second.reasons))
    reasons[failed] = second.reasons
    merged = PlacementResult(
        boxes=np.concatenate([first.boxes, second.boxes])[order],
        accepted=accepted[order],
        rejected={k: first.rejected[k] + second.rejected[k] for k in first.rejected},
        reasons=reasons,
        attempts=first.attempts + second.attempts,
    )
    return merged, names


def render(
    points: np.ndarray, sensor: Sensor, seed: int, max_radius: float | None = None
) -> np.ndarray:
    """An object's placed ``points`` as ``sensor`` records them (its own generator from
    ``seed``, so the answer does not depend on when it is rendered); ``max_radius``: the
    upper clip of its surface elements' radii (see :func:`~drcpo.occlusion.render.radius_cap`)."""
    rng = np.random.default_rng(seed)
    returns, _ = render_object(points, sensor, rng, max_radius=max_radius)
    return returns


def sensor_occlusion(
    points: np.ndarray,
    owner: np.ndarray,
    added_owner: np.ndarray,
    sensor: Sensor,
    count_kept: Callable[[np.ndarray], np.ndarray],
    count_added: Callable[[np.ndarray], np.ndarray],
    min_points: int,
    fill_holes: bool = False,
    boxes: np.ndarray | None = None,
    frame_cells: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """e-HPR along the sensor's rays: points kept ``bool (N,)`` and DR.CPO's objects dropped
    ``bool (A,)``.

    Args:
        points: the frame's points then the inserted objects' (``owner`` >= 0: object number).
        owner: ``int64 (N,)``; -1 for the frame's points.
        added_owner: ``int64 (F,)`` for the frame's ``F`` points, the earlier-added object
            holding each (-1: none); those objects occlude and are occluded like DR.CPO's.
        sensor: the frame's sensor.
        count_kept: given ``keep`` of the inserted points (``bool (N - F,)``), how many each
            DR.CPO object keeps that count for its label; objects below the minimum return
            ``True``.
        count_added: given ``keep`` of the frame's points (``bool (F,)``), how many each
            earlier-added object keeps in its box.
        min_points: an earlier-added object left with fewer points there goes too, all of
            its points (its label then goes with the frame's sparse boxes).
        fill_holes: the holes in each inserted object's rows and columns of returns hide
            what lies behind them too (``external_occlusion.fill_holes``;
            :func:`with_silhouette_gaps`).
        boxes: ``(K, 7)`` the objects' boxes by number, DR.CPO's then the earlier-added ones
            (:meth:`SensorFrame.boxes_with`): a frame point whose sight line enters none of
            the kept ones (its own aside) is never hidden, though a surface element beside
            a box reaches it (:func:`~drcpo.occlusion.sightlines.sight_lines_cross`).
        frame_cells: the frame points' ray cells and distances, when known
            (:attr:`SensorFrame.cells`; found here otherwise).

    Two passes: the first decides which objects keep too few returns (dropped); the second,
    without them, decides every point, so a dropped object hides nothing (the work of the
    first kept: :meth:`~drcpo.occlusion.rays.RayOcclusion.without`).
    """
    first = len(added_owner)
    num_drcpo = int(owner.max()) + 1 if len(owner) > first else 0
    combined = owner.copy()
    combined[:first] = np.where(added_owner >= 0, added_owner + num_drcpo, -1)
    count, radii = len(points), None
    cells = cache(partial(_point_cell_arrays, points, first, sensor, frame_cells))
    if fill_holes:
        points, combined, radii = with_silhouette_gaps(points, combined, sensor, cells())
    rays = RayOcclusion(
        points, combined, sensor, radii, cells=_with_cells_of(cells(), points, sensor)
    )
    objects = int(combined.max(initial=-1)) + 1  # (those with points)
    if boxes is not None and len(boxes) < objects:
        raise DataError(f"boxes must hold one box per object, {objects}, got {len(boxes)}")
    gone = np.zeros(objects if boxes is None else len(boxes), dtype=bool)  # per object
    sight = partial(_in_sight, owner=combined[:count], points=points, boxes=boxes, cells=cells,
                    sensor=sensor)  # fmt: skip
    removed = sight(rays.removed[:count], gone=gone)
    dropped = count_kept(~removed[first:])
    gone[:num_drcpo] = dropped
    if added_owner.max(initial=-1) >= 0:
        sparse = count_added(~removed[:first]) < min_points
        gone[num_drcpo:] = sparse[: len(gone) - num_drcpo]
    if gone.any():
        removed = rays.without(np.flatnonzero(gone[:objects]))[:count]
        removed = sight(removed, gone=gone)
    return ~removed, dropped


def _point_cell_arrays(
    points: np.ndarray,
    first: int,
    sensor: Sensor,
    frame_cells: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`~drcpo.occlusion.render.point_cells` of ``points``; of the first ``first`` (the
    frame's) from ``frame_cells`` when given."""
    if frame_cells is None:
        return point_cells(points, sensor)
    if len(frame_cells[0]) != first:
        raise DataError(f"frame_cells must hold {first} points, got {len(frame_cells[0])}")
    return _with_cells_of(frame_cells, points, sensor)


def _with_cells_of(
    cells: tuple[np.ndarray, np.ndarray, np.ndarray], points: np.ndarray, sensor: Sensor
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``cells`` of the first points, then those of the rest of ``points`` (found here)."""
    count = len(cells[0])
    if count == len(points):
        return cells
    beam, column, distance = (
        np.concatenate(pair)
        for pair in zip(cells, point_cells(points[count:], sensor), strict=True)
    )
    return beam, column, distance


def _in_sight(
    removed: np.ndarray,
    owner: np.ndarray,
    points: np.ndarray,
    gone: np.ndarray,
    boxes: np.ndarray | None,
    cells: Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray]],
    sensor: Sensor,
    tolerance: float = 0.1,
) -> np.ndarray:
    """``removed`` (``bool (N,)``, points of object ``owner``, -1: the frame's own) with the
    points restored whose sight line from the mount enters no box of an object not ``gone``
    but their own, unless (an object's point) its ray cell (``cells()``: beam, column and
    distance of each) holds a return of another owner (the frame's included) nearer by
    more than ``tolerance`` metres; ``removed`` itself without ``boxes``."""
    if boxes is None:
        return removed
    alive = (owner < 0) | ~gone[owner.clip(0)]
    rows = np.flatnonzero(removed & alive)
    kept = np.flatnonzero(~gone)
    number = np.full(len(gone) + 1, -1, dtype=np.int64)  # (index -1: none)
    number[kept] = np.arange(len(kept))
    crossed = sight_lines_cross(points[rows], sensor.mount, boxes[kept], number[owner[rows]])
    free = rows[~crossed]
    if (owner[free] >= 0).any():
        beam, column, distance = cells()
        cell = np.where(alive & (beam >= 0), beam * sensor.num_columns + column, -1)
        count = sensor.num_beams * sensor.num_columns
        behind = _behind_other_owner(cell, distance, owner, tolerance, count)
        free = free[~behind[free]]
    removed = removed.copy()
    removed[free] = False
    return removed


def with_silhouette_gaps(
    points: np.ndarray,
    owner: np.ndarray,
    sensor: Sensor,
    cells: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``points`` ``(N, F)`` and ``owner`` ``(N,)`` with the holes of each inserted object's
    returns (:func:`~drcpo.occlusion.silhouettes.silhouette_gaps`) appended as points of that
    object (features 0), and the surface-element radii of every inserted point in order: the
    default ones (:func:`~drcpo.occlusion.rays.element_radii`) for the points given, half an
    azimuth step across at its distance for a gap, so that a gap hides the rays of its own
    cell and not its neighbours'. The rows after the first ``N`` are never returns. ``cells``:
    the points' ray cells, when known (see :func:`silhouette_gaps`)."""
    gaps, gap_owner = silhouette_gaps(points, owner, sensor, cells)
    given = element_radii(points, owner)
    extra = np.zeros((len(gaps), points.shape[1]), dtype=points.dtype)
    extra[:, :3] = gaps
    reach = np.linalg.norm(gaps - np.asarray(sensor.mount, dtype=np.float64), axis=1)
    radii = np.concatenate([given, reach * (sensor.azimuth_step / 2.0)])
    return np.concatenate([points, extra]), np.concatenate([owner, gap_owner]), radii


@numba.njit(cache=True, nogil=True)
def _behind_other_owner(cell, distance, owner, tolerance, cells):  # pragma: no cover - numba
    # bool (N,): the points of an added object (owner >= 0) whose cell (in [0, cells); -1:
    # none) holds a point of another owner (the frame's own: -1) nearer than it by more than
    # tolerance. Per cell: the nearest point's distance and owner, and the nearest of another
    # owner than that one.
    best = np.full(cells, np.inf)
    best_owner = np.full(cells, -2, np.int64)
    second = np.full(cells, np.inf)
    for i in range(cell.shape[0]):
        k = cell[i]
        if k < 0:
            continue
        if distance[i] < best[k]:
            if best_owner[k] != owner[i]:
                second[k] = best[k]
            best[k], best_owner[k] = distance[i], owner[i]
        elif owner[i] != best_owner[k] and distance[i] < second[k]:
            second[k] = distance[i]
    hidden = np.zeros(cell.shape[0], np.bool_)
    for i in range(cell.shape[0]):
        k = cell[i]
        if k < 0 or owner[i] < 0:
            continue
        rival = second[k] if best_owner[k] == owner[i] else best[k]
        hidden[i] = rival < distance[i] - tolerance
    return hidden
