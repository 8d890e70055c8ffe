"""The holes in an inserted object's returns (``external_occlusion.fill_holes``).

An object's returns, rendered from a union of candidates' points or recorded in another frame,
leave holes: rays that pass between its surface elements, or that the recording lost. A solid
object blocks those rays all the same, so a point the frame recorded behind such a hole could
not have been seen. :func:`silhouette_gaps` gives, per object, the ray cells between its
returns of one beam, or of one column, that hold none of its returns, as points on those rays
at the mean distance of that beam's (column's) returns; occlusion along the rays
(:mod:`~drcpo.occlusion.rays`) takes them as surfaces that hide and are never returned. The
outline is unchanged: nothing is added beyond a row's or a column's outermost returns.
Imports :mod:`drcpo.errors`, :mod:`drcpo.sensor` and :mod:`drcpo.occlusion.render` only.
"""

from __future__ import annotations

import numpy as np

from drcpo.errors import DataError
from drcpo.occlusion.render import point_cells
from drcpo.sensor import Sensor

__all__ = ["silhouette_gaps"]


def silhouette_gaps(
    points: np.ndarray,
    owner: np.ndarray,
    sensor: Sensor,
    cells: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The empty ray cells inside each inserted object's rows and columns of returns.

    For each object ``k`` (``owner == k >= 0``; cells by :meth:`Sensor.cells`): in each beam
    ``b`` holding some of its returns, the columns of the shortest arc of the turn that holds
    all of them (every empty arc between two of its columns but the widest, which is the
    outside) that hold none; in each column holding some, the beams between its highest and
    lowest that hold none. One point per such cell (once, when it is both), on the cell's ray
    (from ``sensor.ray_origins(b)`` along ``sensor.ray_directions(b, c)``) at the mean
    distance from the beam's origin of the object's returns of that beam (row gaps) or column
    (column gaps).

    Args:
        points: ``(N, 3+)`` the frame after insertion, metres, LiDAR frame.
        owner: ``int (N,)``: -1 for the frame's own points, ``k`` for inserted object ``k``.
        sensor: the LiDAR whose cells these are.
        cells: each point's beam, column and distance from its beam's origin
            (:func:`~drcpo.occlusion.render.point_cells` of ``points``), when known.

    Returns:
        ``gaps float64 (G, 3)`` and ``gap_owner int64 (G,)``: the points and their objects,
        by object, then beam, then column.
    """
    owner = np.asarray(owner)
    inserted = np.flatnonzero(owner >= 0)
    if cells is None:
        beam, column, distance = point_cells(np.asarray(points)[inserted], sensor)
    else:
        if any(len(a) != len(owner) for a in cells):
            raise DataError(f"cells must hold {len(owner)} points each")
        beam, column, distance = (a[inserted] for a in cells)
    seen = (beam >= 0) & (column >= 0)
    if not seen.any():
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    beams, columns = sensor.num_beams, sensor.num_columns
    mine, beam, column, distance = owner[inserted[seen]], beam[seen], column[seen], distance[seen]
    row, row_column, row_mean = _line_gaps(mine * beams + beam, column, columns, distance)
    # columns are straight lines: a period of twice the beams makes the outside the widest
    line, line_beam, line_mean = _line_gaps(mine * columns + column, beam, 2 * beams, distance)
    gap_owner = np.concatenate([row // beams, line // columns])
    gap_beam = np.concatenate([row % beams, line_beam])
    gap_column = np.concatenate([row_column, line % columns])
    _, first = np.unique((gap_owner * beams + gap_beam) * columns + gap_column, return_index=True)
    gap_owner, gap_beam, gap_column = gap_owner[first], gap_beam[first], gap_column[first]
    mean = np.concatenate([row_mean, line_mean])[first]
    gaps = sensor.ray_origins(gap_beam) + mean[:, None] * sensor.ray_directions(
        gap_beam, gap_column
    )
    return gaps, gap_owner.astype(np.int64)


def _line_gaps(
    line: np.ndarray, position: np.ndarray, period: int, distance: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The empty positions of each line of cells between its held ones: of the cells
    ``(line, position)`` (positions on a circle of ``period``; a period over twice the
    positions' range makes the lines straight), every empty arc between two held positions
    of a line but the widest. Returns each gap's line, position and the mean ``distance``
    of its line's cells."""
    code = line * period + position
    order = np.argsort(code, kind="stable")
    code, distance = code[order], distance[order]
    line = code // period
    index = np.cumsum(np.r_[True, line[1:] != line[:-1]]) - 1
    mean = np.bincount(index, distance) / np.bincount(index)
    new_cell = np.r_[True, code[1:] != code[:-1]]
    held_line, held = index[new_cell], code[new_cell] % period
    first = np.flatnonzero(np.r_[True, held_line[1:] != held_line[:-1]])
    last = np.r_[first[1:] - 1, len(held_line) - 1]
    empty_before = np.empty(len(held_line), dtype=np.int64)
    empty_before[1:] = held[1:] - held[:-1] - 1
    empty_before[first] = held[first] + period - held[last] - 1
    # the widest empty arc of each line (its first, on a tie) lies outside the object
    widest = np.maximum.reduceat(empty_before, first)
    candidates = np.flatnonzero(empty_before == widest[held_line])
    outside = candidates[np.r_[True, held_line[candidates][1:] != held_line[candidates][:-1]]]
    empty_before[outside] = 0
    cell_of = np.repeat(np.arange(len(held_line)), empty_before)
    step = np.arange(len(cell_of)) - np.repeat(np.cumsum(empty_before) - empty_before, empty_before)
    gap_position = (held[cell_of] - empty_before[cell_of] + step) % period
    gap_line = held_line[cell_of]
    return line[new_cell][cell_of], gap_position, mean[gap_line]
