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
    (cells by :meth:`Sensor.cells`), the columns of the shortest arc of the turn that holds
    all of them (every empty arc between two of its columns but the widest, which is the
    outside) that hold none: one point per such cell, on the cell's ray (from
    ``sensor.ray_origins(b)`` along ``sensor.ray_directions(b, c)``) at the mean distance from
    that origin of the object's returns of beam ``b``.

    Args:
        points: ``(N, 3+)`` the frame after insertion, metres, LiDAR frame.
        owner: ``int (N,)``: -1 for the frame's own points, ``k`` for inserted object ``k``.
        sensor: the LiDAR whose cells these are.

    Returns:
        ``gaps float64 (G, 3)`` and ``gap_owner int64 (G,)``: the points and their objects,
        by object, then beam, then column.
    """
    owner = np.asarray(owner)
    inserted = np.flatnonzero(owner >= 0)
    beam, column, distance = point_cells(np.asarray(points)[inserted], sensor)
    seen = (beam >= 0) & (column >= 0)
    if not seen.any():
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    columns = sensor.num_columns
    code = (owner[inserted[seen]] * sensor.num_beams + beam[seen]) * columns + column[seen]
    order = np.argsort(code, kind="stable")
    code, distance = code[order], distance[seen][order]
    row_code = code // columns
    row = np.cumsum(np.r_[True, row_code[1:] != row_code[:-1]]) - 1
    mean = np.bincount(row, distance) / np.bincount(row)
    # the cells holding returns, by row then column; the empty arc before each
    new_cell = np.r_[True, code[1:] != code[:-1]]
    held_row, held_column = row[new_cell], code[new_cell] % columns
    row_first = np.flatnonzero(np.r_[True, held_row[1:] != held_row[:-1]])
    row_last = np.r_[row_first[1:] - 1, len(held_row) - 1]
    empty_before = np.empty(len(held_row), dtype=np.int64)
    empty_before[1:] = held_column[1:] - held_column[:-1] - 1
    empty_before[row_first] = held_column[row_first] + columns - held_column[row_last] - 1
    # the widest empty arc of each row (its first, on a tie) lies outside the object
    widest = np.maximum.reduceat(empty_before, row_first)
    candidates = np.flatnonzero(empty_before == widest[held_row])
    outside = candidates[np.r_[True, held_row[candidates][1:] != held_row[candidates][:-1]]]
    empty_before[outside] = 0
    cell_of = np.repeat(np.arange(len(held_row)), empty_before)
    step = np.arange(len(cell_of)) - np.repeat(np.cumsum(empty_before) - empty_before, empty_before)
    gap_column = (held_column[cell_of] - empty_before[cell_of] + step) % columns
    gap_row = held_row[cell_of]
    gap_row_code = row_code[new_cell][cell_of]
    gap_beam = gap_row_code % sensor.num_beams
    gaps = sensor.ray_origins(gap_beam) + mean[gap_row, None] * sensor.ray_directions(
        gap_beam, gap_column
    )
    return gaps, (gap_row_code // sensor.num_beams).astype(np.int64)
