"""DR.CPO's last three steps (:class:`~drcpo.transforms.drcpo.DRCPO` runs them in order), each a
function of data: **insert** the built objects into the frame, **e-HPR** scoped to them with the
label rule (which inserted objects keep enough points), and the **labels** (the output frame:
dropped objects leave no trace, original boxes left too sparse go)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from drcpo import occlusion
from drcpo.frame import Frame
from drcpo.occlusion.view_windows import grown_boxes, window_spans
from drcpo.transforms.insertion import (
    BoxQuery,
    key_sweep,
    take_rows,
    update_box_metadata,
    with_box_sources,
)

__all__ = ["Inserted", "Insertion", "insert", "scoped_e_hpr", "settle"]


@dataclass(frozen=True, eq=False)
class Insertion:
    """One object on its way into the frame: source row, class, placed box, its label (the
    placed box grown to hold the points, see DRCPO's s-HPR step), placed points."""

    row: int
    name: str
    placed: np.ndarray
    box: np.ndarray
    points: np.ndarray


class Inserted(NamedTuple):
    """The frame after :func:`insert`: its points (the frame's outside the objects' room, then
    the objects'), each point's owner (-1: an original point, else the insertion's number) and,
    per frame point, the insertion it made room for (-1: none)."""

    points: np.ndarray
    owner: np.ndarray
    cleared_by: np.ndarray


def insert(frame: Frame, insertions: Sequence[Insertion], room: float) -> Inserted:
    """The ``insertions``' points into ``frame``: the frame's points within ``room`` metres of an
    object's placed box make way for it."""
    cleared_by = np.full(len(frame), -1, dtype=np.int64)
    if not insertions:
        return Inserted(frame.points, cleared_by.copy(), cleared_by)
    rooms = grown_boxes(np.array([i.placed for i in insertions]), room)
    cleared_by = BoxQuery(frame.points).owners(rooms)
    original = cleared_by < 0
    points = np.concatenate([take_rows(frame.points, original), *(i.points for i in insertions)])
    key_sweep(points, frame, int(np.count_nonzero(original)))
    owner = np.concatenate(
        [np.full(int(original.sum()), -1)]
        + [np.full(len(i.points), j) for j, i in enumerate(insertions)]
    ).astype(np.int64)
    return Inserted(points, owner, cleared_by)


def scoped_e_hpr(
    inserted: Inserted,
    insertions: Sequence[Insertion],
    setting: tuple[float, np.ndarray] | None,
    min_points_after: int,
    grid: occlusion.FrameGrid | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Points kept by e-HPR, ``bool (N,)``, and the insertions left with fewer than
    ``min_points_after`` points in their box, ``bool (len(insertions),)``.

    e-HPR itself is :func:`drcpo.occlusion.inserted_scope` (``setting``: its radius and
    viewpoint; ``None``: e-HPR off); this applies the label rule: the inserted points are decided
    first, each exactly against the whole frame, and hidden ones go; then, for the original
    points behind the boxes of the objects that keep enough points, in their view windows (the
    directions they cover), those hidden with the objects but visible without them go. With
    ``grid`` (the frame's :class:`~drcpo.occlusion.FrameGrid`), the frame's points are not
    sorted again."""
    points, owner, cleared_by = inserted
    keep = np.ones(len(points), dtype=bool)
    if setting is None or len(points) == 0 or not insertions:
        return keep, _dropped(points, owner, insertions, keep, min_points_after)
    radius, viewpoint = setting
    first = int(np.count_nonzero(owner < 0))  # the original points come first
    scope = occlusion.inserted_scope(
        points, owner >= 0, viewpoint, radius, grid=grid, cleared=cleared_by >= 0
    )
    # The label rule on the inserted points left; the view windows of the objects kept.
    kept_inserted = ~scope.removed_inserted
    dropped = _dropped(points[first:], owner[first:], insertions, kept_inserted, min_points_after)
    kept = np.flatnonzero(~dropped)
    windows = window_spans(grown_boxes([insertions[k].placed for k in kept]), viewpoint, True)
    removed = np.concatenate([scope.removed_behind(windows), scope.removed_inserted])
    return ~removed, dropped


def _dropped(
    points: np.ndarray,
    owner: np.ndarray,
    insertions: Sequence[Insertion],
    keep: np.ndarray,
    minimum: int,
) -> np.ndarray:
    """``bool (len(insertions),)``: objects with fewer than ``minimum`` of their points that
    ``keep`` (``bool (N,)``) holds in their own box (some may lie outside)."""
    if not insertions:
        return np.zeros(0, dtype=bool)
    survivors = BoxQuery(points).own_counts(owner, [i.box for i in insertions], keep)
    return survivors < minimum


def settle(
    frame: Frame,
    inserted: Inserted,
    keep: np.ndarray,
    dropped: np.ndarray,
    insertions: Sequence[Insertion],
    min_points_after: int,
    added_values: Mapping[str, Any],
) -> tuple[Frame, np.ndarray]:
    """The output frame, and the original boxes dropped (``bool (M,)``).

    An inserted object of ``dropped`` goes with all its points, and the frame points it
    displaced come back (e-HPR removed frame points only behind the objects kept), so it leaves
    no trace. An original box is dropped when it lost points and is left with fewer than
    ``min_points_after``, unless it had fewer already. ``added_values``: per-box metadata of the
    objects kept (:func:`~drcpo.transforms.insertion.update_box_metadata`).
    """
    points, owner, cleared_by = inserted
    original_rows = np.flatnonzero(cleared_by < 0)  # frame row of each original point
    removed = cleared_by >= 0
    if dropped.any():
        removed &= ~np.append(dropped, False)[cleared_by]  # (index -1: the frame's own)
    removed[original_rows[~keep[: len(original_rows)]]] = True
    kept = [i for i, gone in zip(insertions, dropped, strict=True) if not gone]
    drop_original = _sparse_originals(frame, removed, min_points_after)
    inserted_keep = keep & ~np.append(dropped, True)[owner]  # (index -1: not inserted)
    kept_boxes = np.flatnonzero(~drop_original)
    out = frame.replace(
        points=np.concatenate(
            [take_rows(frame.points, ~removed), take_rows(points, inserted_keep)]
        ),
        boxes=np.concatenate([frame.boxes[kept_boxes], grown_boxes([i.box for i in kept], 0.0)]),
        names=np.concatenate([frame.names[kept_boxes], [i.name for i in kept]]),
        metadata=update_box_metadata(
            with_box_sources(frame.metadata, len(frame.boxes)) if kept else frame.metadata,
            len(frame.boxes),
            keep=kept_boxes if drop_original.any() else None,
            added=len(kept),
            added_values=dict(added_values),
        ),
    )
    return out, drop_original


def _sparse_originals(frame: Frame, removed: np.ndarray, minimum: int) -> np.ndarray:
    """``bool (M,)``: frame boxes that lost points and now hold fewer than ``minimum``, having
    held at least ``minimum`` before. Only boxes holding removed points can have lost any, so
    only those are counted."""
    drop = np.zeros(len(frame.boxes), dtype=bool)
    if not removed.any() or len(frame.boxes) == 0:
        return drop
    lost = BoxQuery(take_rows(frame.points, removed)).counts(frame.boxes)
    touched = np.flatnonzero(lost)
    if len(touched):
        had = BoxQuery(frame.points).counts(frame.boxes[touched])
        drop[touched] = (had >= minimum) & (had - lost[touched] < minimum)
    return drop
