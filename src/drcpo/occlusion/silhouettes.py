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

import numba
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
    of a line but the widest (its first, on a tie: that one lies outside the object).
    Returns each gap's line, position and the mean ``distance`` of its line's cells, by
    line, then by the held position the gap comes before."""
    code = np.asarray(line, dtype=np.int64) * period + np.asarray(position, dtype=np.int64)
    order = np.argsort(code, kind="stable")  # (numpy's sort is faster than numba's)
    return _gaps_of_lines(code, order, int(period), np.asarray(distance, dtype=np.float64))


@numba.njit(cache=True, nogil=True)
def _gaps_of_lines(code, order, period, distance):  # pragma: no cover - numba
    # One pass over the cells in `order` (by code, stable, so each line's distances are
    # summed in the order given): per line its held positions, the empty run before each
    # (the first's wraps around from the last) and, but for the widest, its gaps.
    n = code.shape[0]
    held = np.empty(n, np.int64)  # per held cell: its position, its line's number
    held_line = np.empty(n, np.int64)
    empty = np.empty(n, np.int64)  # empty positions before it
    lines = np.empty(n, np.int64)  # per line: its code // period and mean distance
    mean = np.empty(n)
    cells, count, begin = 0, 0, 0
    while begin < n:
        current = code[order[begin]] // period
        total, end = 0.0, begin
        start = cells
        while end < n and code[order[end]] // period == current:
            total += distance[order[end]]
            p = code[order[end]] % period
            if cells == start or held[cells - 1] != p:
                held[cells], held_line[cells] = p, count
                cells += 1
            end += 1
        lines[count], mean[count] = current, total / (end - begin)
        for c in range(start + 1, cells):
            empty[c] = held[c] - held[c - 1] - 1
        empty[start] = held[start] + period - held[cells - 1] - 1
        widest = start
        for c in range(start + 1, cells):
            if empty[c] > empty[widest]:
                widest = c
        empty[widest] = 0
        count += 1
        begin = end
    gaps = 0
    for c in range(cells):
        gaps += empty[c]
    gap_line = np.empty(gaps, np.int64)
    gap_position = np.empty(gaps, np.int64)
    gap_mean = np.empty(gaps)
    g = 0
    for c in range(cells):
        for step in range(empty[c]):
            k = held_line[c]
            gap_line[g], gap_mean[g] = lines[k], mean[k]
            gap_position[g] = (held[c] - empty[c] + step) % period
            g += 1
    return gap_line, gap_position, gap_mean
