""":class:`~drcpo.occlusion.frame_grid.FrameGrid`'s kernels (numba): e-HPR's inserted scope per
point (:func:`_insertion_verdicts`), groups of samples hidden by the frame
(:func:`_hidden_groups`) and points inside direction windows (:func:`_window_members`).
Imports :mod:`drcpo.occlusion.kernels` only.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from drcpo.occlusion.kernels import (
    _BOTH,
    _CERTIFY,
    _INSERTED,
    _ORIGINALS,
    _STATE_HIDDEN,
    _STATE_VISIBLE,
    _decide,
    _new_work,
    _radial_clear,
    _row_runs,
)

__all__: list[str] = []  # internal to drcpo.occlusion, whose __init__ has the API

_VERDICT_KEEP, _VERDICT_REMOVE, _VERDICT_UNDECIDED_WITHOUT, _VERDICT_UNDECIDED_WITH = 0, 1, 2, 3
# A frame point among the frame's points alone (see _without_state).
_WITHOUT_CLEAR, _WITHOUT_HIDDEN, _WITHOUT_VISIBLE, _WITHOUT_UNRESOLVED = range(1, 5)


@nb.njit(cache=True, nogil=True)
def _without_state(i, cone, scene, work, brutes, brute_budget):
    """State of sorted frame point ``i`` among the frame's points (first cone ``cone``):
    clear (the plane normal to its ray), hidden, visible (a tilted plane) or unresolved; with
    the full scans made so far and the buffers, as :func:`_decide`."""
    if _radial_clear(i, cone, _ORIGINALS, scene):
        return _WITHOUT_CLEAR, brutes, work
    state, brutes, work = _decide(i, cone, _ORIGINALS | _CERTIFY, scene, work, brutes, brute_budget)
    if state == _STATE_HIDDEN:
        return _WITHOUT_HIDDEN, brutes, work
    if state == _STATE_VISIBLE:
        return _WITHOUT_VISIBLE, brutes, work
    return _WITHOUT_UNRESOLVED, brutes, work


@nb.njit(cache=True, nogil=True)
def _insertion_verdicts(queries, cones, n_original, scene, brute_budget):
    """e-HPR's inserted scope for the sorted points ``queries`` (first cones ``cones``) of
    ``scene``, whose cells are sorted by range: the frame's points (positions below
    ``n_original``) go when visible without the inserted ones and hidden with them, inserted
    points when hidden. Per query: keep 0, remove 1, or which verdict it could not settle
    within ``brute_budget`` full scans: without the inserted points 2, with them 3.

    A frame point's plane normal to its ray is checked against the frame's points and the
    inserted ones separately, so that one scan of each decides both sets when it fits;
    otherwise each set is decided as :func:`_classify` does.
    """
    verdicts = np.empty(queries.shape[0], dtype=np.int8)
    work = _new_work(256)
    brutes = 0
    for slot in range(queries.shape[0]):
        i = queries[slot]
        cone = cones[slot]
        if i < n_original:
            state, brutes, work = _without_state(i, cone, scene, work, brutes, brute_budget)
            if state == _WITHOUT_HIDDEN:
                verdicts[slot] = _VERDICT_KEEP
                continue
            if state == _WITHOUT_UNRESOLVED:
                verdicts[slot] = _VERDICT_UNDECIDED_WITHOUT
                continue
            # visible without the inserted points: by the radial plane unless they block it
            if state == _WITHOUT_CLEAR and _radial_clear(i, cone, _INSERTED, scene):
                verdicts[slot] = _VERDICT_KEEP
                continue
        elif _radial_clear(i, cone, _BOTH, scene):
            verdicts[slot] = _VERDICT_KEEP
            continue
        state, brutes, work = _decide(i, cone, _BOTH | _CERTIFY, scene, work, brutes, brute_budget)
        if state == _STATE_HIDDEN:
            verdicts[slot] = _VERDICT_REMOVE
        elif state == _STATE_VISIBLE:
            verdicts[slot] = _VERDICT_KEEP
        else:
            verdicts[slot] = _VERDICT_UNDECIDED_WITH
    return verdicts


@nb.njit(cache=True, nogil=True)
def _hidden_groups(
    position, cones, offsets, allowed, scene, brute_budget, hidden
):  # pragma: no cover - numba
    # FrameGrid.hidden_groups: per group, the samples' radial planes first (cheap, and one
    # visible sample more than ``allowed`` settles the group), then the full test.
    work = _new_work(256)
    for m in range(offsets.shape[0] - 1):
        lo, hi = offsets[m], offsets[m + 1]
        if hi == lo:
            continue
        brutes = 0  # a budget per group: the verdicts do not depend on how groups are split
        visible = 0
        blocked = np.empty(hi - lo, dtype=np.int64)
        n_blocked = 0
        for k in range(lo, hi):
            if _radial_clear(position[k], cones[k], _ORIGINALS, scene):
                visible += 1
                if visible > allowed[m]:
                    break
            else:
                blocked[n_blocked] = k
                n_blocked += 1
        if visible > allowed[m]:
            continue
        for b in range(n_blocked):
            k = blocked[b]
            state, brutes, work = _decide(
                position[k], cones[k], _ORIGINALS | _CERTIFY, scene, work, brutes, brute_budget
            )
            if state != _STATE_HIDDEN:
                visible += 1
                if visible > allowed[m]:
                    break
        hidden[m] = visible <= allowed[m]


@nb.njit(cache=True, nogil=True)
def _window_members(windows, scene, out):
    """Mark in ``out`` the sorted points of member set 0 of ``scene`` inside any of ``windows``
    (see :meth:`FrameGrid.in_windows`; distance: ``ranges``), visiting only the cells each
    window overlaps, and one more on every side so that rounding in the cell numbers cannot
    miss a point."""
    azimuth, elevation, ranges, starts = scene.azimuth, scene.elevation, scene.ranges, scene.starts
    origin, height, rows, columns = scene.origin, scene.size, scene.rows, scene.columns
    step = 2.0 * math.pi / columns
    for w in range(windows.shape[0]):
        az0, az1, el0, el1, near = windows[w]
        row_lo = max(0, math.floor((el0 - origin) / height) - 1)
        row_hi = min(rows - 1, math.floor((el1 - origin) / height) + 1)
        col_lo = math.floor((az0 + math.pi) / step) - 1
        col_n = min(columns, math.floor((az1 + math.pi) / step) + 2 - col_lo)
        if az1 < az0:
            continue
        for row in range(row_lo, row_hi + 1):
            lo0, hi0, lo1, hi1 = _row_runs(starts, 0, row, col_lo, col_n, columns)
            for run in range(2):
                lo, hi = (lo0, hi0) if run == 0 else (lo1, hi1)
                for j in range(lo, hi):
                    if (
                        azimuth[j] >= az0
                        and azimuth[j] <= az1
                        and elevation[j] >= el0
                        and elevation[j] <= el1
                        and ranges[j] >= near
                    ):
                        out[j] = True
