"""The gaps in an inserted object's rows of returns (``external_occlusion.fill_rows``).

An object's returns, rendered from a union of candidates' points or recorded in another frame,
leave holes: rays that pass between its surface elements, or that the recording lost. A solid
object blocks those rays all the same, so a point the frame recorded behind such a hole could
not have been seen. :func:`row_gaps` gives, per object and beam, the ray cells between its
outermost returns of that beam that hold none of its returns, as points on those rays at the
mean distance of the row's returns; occlusion along the rays (:mod:`~drcpo.occlusion.rays`)
takes them as surfaces that hide and are never returned. The outline is unchanged: nothing
is added beyond a row's first and last return. Imports :mod:`drcpo.sensor` and
:mod:`drcpo.occlusion.render` only.
"""

from __future__ import annotations

import numpy as np

from drcpo.occlusion.render import point_cells
from drcpo.sensor import Sensor

__all__ = ["row_gaps"]


def row_gaps(
    points: np.ndarray, owner: np.ndarray, sensor: Sensor
) -> tuple[np.ndarray, np.ndarray]:
    """The empty ray cells inside each inserted object's rows of returns.

    For each object ``k`` (``owner == k >= 0``) and beam ``b`` holding some of its returns
    (cells by :meth:`Sensor.cells`), the columns from its first to its last return of that
    beam (the shorter way round the turn) that hold none: one point per such cell, on the
    cell's ray (from ``sensor.ray_origins(b)`` along ``sensor.ray_directions(b, c)``) at the
    mean distance from that origin of the object's returns of beam ``b``.

    Args:
        points: ``(N, 3+)`` the frame after insertion, metres, LiDAR frame.
        owner: ``int (N,)``: -1 for the frame's own points, ``k`` for inserted object ``k``.
        sensor: the LiDAR whose cells these are.

    Returns:
        ``gaps float64 (G, 3)`` and ``gap_owner int64 (G,)``: the points and their objects,
        by object, then beam, then column from the row's first return.
    """
    owner = np.asarray(owner)
    inserted = np.flatnonzero(owner >= 0)
    beam, column, distance = point_cells(np.asarray(points)[inserted], sensor)
    seen = (beam >= 0) & (column >= 0)
    inserted, beam, column, distance = inserted[seen], beam[seen], column[seen], distance[seen]
    if len(inserted) == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    columns = sensor.num_columns
    rows, row = np.unique(owner[inserted] * sensor.num_beams + beam, return_inverse=True)
    # A row across the turn's seam spans less once the columns are turned half a turn.
    half = columns // 2
    first, last = _spans(row, column, len(rows))
    turned_first, turned_last = _spans(row, (column + half) % columns, len(rows))
    seam = turned_last - turned_first < last - first
    first = np.where(seam, turned_first, first)
    shift = np.where(seam, half, 0)
    mean = np.bincount(row, distance, len(rows)) / np.bincount(row, minlength=len(rows))
    widths = np.where(seam, turned_last, last) - first + 1
    cell_row = np.repeat(np.arange(len(rows)), widths)
    step = np.arange(len(cell_row)) - np.repeat(np.cumsum(widths) - widths, widths)
    cell_column = (first[cell_row] + step - shift[cell_row]) % columns
    held = np.unique(rows[row] * columns + column)
    empty = ~np.isin(rows[cell_row] * columns + cell_column, held, assume_unique=False)
    cell_row, cell_column = cell_row[empty], cell_column[empty]
    cell_beam = rows[cell_row] % sensor.num_beams
    gaps = sensor.ray_origins(cell_beam) + mean[cell_row, None] * sensor.ray_directions(
        cell_beam, cell_column
    )
    return gaps, (rows[cell_row] // sensor.num_beams).astype(np.int64)


def _spans(row: np.ndarray, column: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Per row ``0..count-1``, the least and greatest column of its cells."""
    first = np.full(count, np.iinfo(np.int64).max, dtype=np.int64)
    last = np.full(count, -1, dtype=np.int64)
    np.minimum.at(first, row, column)
    np.maximum.at(last, row, column)
    return first, last
