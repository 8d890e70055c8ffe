"""The per-point supporting-plane test (numba): a point's angular neighbours as constraints on
the tilt of a plane through it (:func:`_gather`), the least tilted plane (:func:`_min_tilt`,
Seidel's method), and the verdicts built on them (:func:`_radial_pass`, :func:`_decide`,
:func:`_classify`, :func:`_radial_clear`). See :mod:`drcpo.occlusion.hpr` for the method.
Imports nothing from drcpo.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

__all__ = ["Scene"]

# Kernel constants. The tilt box bounds the plane search to 90 deg - 1e-7 rad from the ray;
# the slack is how far (in units of the flipped range) a point must lie below a plane to count
# as below it, about Qhull's own roundoff, so points on a common plane are not vertices.
_TILT_BOX = 1e7
_SLACK = 1e-15
_BOX_A = np.array([1.0, -1.0, 0.0, 0.0])
_BOX_B = np.array([0.0, 0.0, 1.0, -1.0])
_FIRST_WIDENING = 1.3  # first neighbourhood of a point the plane normal to its ray fails
_PROBE_NARROWING = 0.5  # the probe for hidden points looks this far, relative to the first
_BRUTE_ANGLE = 0.6  # radians: wider neighbourhoods scan every point
_BRUTE_BUDGET = 64  # full scans per call before the leftovers go to the reference hull
_GROUP_BRUTE_BUDGET = 4  # full scans per group of FrameGrid.hidden_groups
_STATE_HIDDEN, _STATE_VISIBLE, _STATE_UNRESOLVED = 0, 1, 2


_ORIGINALS, _INSERTED, _BOTH = 1, 2, 3  # member sets a gather looks at (bit per starts row)
# With this bit, a gather stops as soon as its points show that no plane fits (returns _NO_PLANE).
_CERTIFY = 4
_NO_PLANE = -2


class Scene(NamedTuple):
    """The kernels' view of a point set sorted into a grid of (elevation, azimuth) cells, by cell
    and, within a cell, by range (one structure instead of a long argument list; numba takes it
    as a tuple, so its field types must not change between callers).

    Attributes:
        rays: ``(M, 3)`` unit vectors from the viewpoint, sorted.
        rel: ``(M, 3)`` coordinates relative to the viewpoint, metres.
        ranges: ``(M,)`` distances from the viewpoint, metres.
        rho: ``(M,)`` flipped ranges ``2R - r``, metres.
        elevation: ``(M,)`` radians.
        azimuth: ``(M,)`` radians.
        starts: ``int64 (S, cells + 1)`` first sorted position of each cell, one row per member
            set (the set itself, or the frame's points then the inserted ones).
        absent: ``bool (M,)`` points to skip, or empty: none.
        origin: elevation of the first row's lower edge, radians.
        size: row height, radians.
        rows: number of grid rows.
        columns: number of grid columns (cells ``2 pi / columns`` wide in azimuth).
        radius: ``R``, metres.
        r_min: a lower bound of the ranges that may take part, metres.
        rho_max: ``2R - r_min``, the largest flipped range, metres.
    """

    rays: np.ndarray
    rel: np.ndarray
    ranges: np.ndarray
    rho: np.ndarray
    elevation: np.ndarray
    azimuth: np.ndarray
    starts: np.ndarray
    absent: np.ndarray
    origin: float
    size: float
    rows: int
    columns: int
    radius: float
    r_min: float
    rho_max: float


@nb.njit(cache=True, nogil=True)
def _tangent_basis(ux: float, uy: float, uz: float) -> tuple:
    """Two unit vectors completing the ray ``u`` to an orthonormal basis."""
    if abs(uz) < 0.9:
        ax, ay, az = -uy, ux, 0.0
    else:
        ax, ay, az = 0.0, -uz, uy
    norm = math.sqrt(ax * ax + ay * ay + az * az)
    ax, ay, az = ax / norm, ay / norm, az / norm
    return ax, ay, az, uy * az - uz * ay, uz * ax - ux * az, ux * ay - uy * ax


@nb.njit(cache=True, nogil=True)
def _cell_range(el, az, reach, origin, size, rows, columns):
    """Grid rows ``row_lo..row_hi`` and ``col_n`` columns from ``col_lo`` (cyclic) holding
    every ray within ``reach`` radians of the ray at elevation ``el``, azimuth ``az`` (a
    scene's grid: ``origin``, ``size``, ``rows``, ``columns``; scalars, not the scene, as its
    arrays would be reference-counted on every call). Rows are clamped both ways, as points
    beyond the grid's rows are stored in its edge rows."""
    if reach >= _BRUTE_ANGLE:
        return 0, rows - 1, 0, columns
    row_lo = min(rows - 1, max(0, math.floor((el - reach - origin) / size)))
    row_hi = max(0, min(rows - 1, math.floor((el + reach - origin) / size)))
    if math.sin(reach) >= math.cos(el):  # the cone holds a pole: every azimuth
        return row_lo, row_hi, 0, columns
    spread = math.asin(min(1.0, math.sin(reach) / math.cos(el))) * (1.0 + 1e-9) + 1e-12
    step = 2.0 * math.pi / columns
    col_lo = math.floor((az - spread + math.pi) / step)
    col_hi = math.floor((az + spread + math.pi) / step)
    return row_lo, row_hi, col_lo, min(columns, col_hi - col_lo + 1)


@nb.njit(cache=True, nogil=True)
def _row_runs(starts, member, row, col_lo, col_n, columns):
    """Sorted positions of one grid row's cells ``col_lo .. col_lo + col_n - 1`` (cyclic) in
    member set ``member``: two runs ``[lo0, hi0)`` then ``[lo1, hi1)``, in the cells' order."""
    base = row * columns
    first = (col_lo % columns + columns) % columns
    end = first + col_n
    if end <= columns:
        return starts[member, base + first], starts[member, base + end], 0, 0
    return (
        starts[member, base + first],
        starts[member, base + columns],
        starts[member, base],
        starts[member, base + end - columns],
    )


@nb.njit(cache=True, nogil=True)
def _radial_pass(todo, first_cone, scene):
    """``bool`` per point of ``todo``: visible by the plane normal to its ray (the pre-filter);
    ``False`` means undecided."""
    empty = np.empty(0)
    settled = np.empty(todo.shape[0], dtype=np.bool_)
    for slot in range(todo.shape[0]):
        i = todo[slot]
        found = _gather(i, first_cone[i], True, _ORIGINALS, scene, empty, empty, empty)
        settled[slot] = found >= 0
    return settled


@nb.njit(cache=True, nogil=True)
def _gather(i, cone, radial_only, members, scene, out_s1, out_s2, out_t):
    """Constraints from the points within ``cone`` radians of point ``i``'s ray.

    A plane through flipped point ``i`` with normal ``u_i + a e1 + b e2`` has flipped point
    ``j`` strictly below it iff ``a s1_j + b s2_j < t_j`` with ``s_j = (u_j - u_i) . e`` and
    ``t_j = |u_j - u_i|^2 / 2 - (r_i - r_j) / (2R - r_j)``. Returns the number of constraints
    (which may exceed the buffers: the caller grows them and asks again), or ``-1`` when
    ``radial_only`` and some point blocks the plane normal to the ray (``t_j`` not positive).
    Only the member sets in the bits of ``members`` (rows of ``starts``) take part; exact
    duplicates of point ``i`` and ``absent`` points are skipped. With the :data:`_CERTIFY`
    bit, it returns ``_NO_PLANE`` as soon as points with ``t_j`` below the slack lie in all
    four quadrants around ``(0, 0)`` (``(s1_j, s2_j)`` clear of the axes): three of them then
    sum to zero with positive weights while their ``t_j - slack`` do not, so no ``(a, b)``
    meets all constraints (Farkas) and the point is hidden.
    """
    ux, uy, uz = scene.rays[i, 0], scene.rays[i, 1], scene.rays[i, 2]
    e1x, e1y, e1z, e2x, e2y, e2z = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    if not radial_only:
        e1x, e1y, e1z, e2x, e2y, e2z = _tangent_basis(ux, uy, uz)
    ri = scene.ranges[i]
    reach = min(cone * (1.0 + 1e-9) + 1e-12, math.pi)
    half = math.sin(reach / 2.0)
    chord2 = 4.0 * half * half * (1.0 + 1e-12) + 1e-300
    if reach >= math.pi:
        chord2 = 5.0
    masked = scene.absent.shape[0] > 0
    near = np.empty(64, dtype=np.int64)
    certify = members & _CERTIFY != 0
    quadrants = 0
    capacity = out_t.shape[0]
    count = 0
    row_lo, row_hi, col_lo, col_n = _cell_range(
        scene.elevation[i],
        scene.azimuth[i],
        reach,
        scene.origin,
        scene.size,
        scene.rows,
        scene.columns,
    )
    for member in range(scene.starts.shape[0]):
        if not members & (1 << member):
            continue
        for row in range(row_lo, row_hi + 1):
            lo0, hi0, lo1, hi1 = _row_runs(scene.starts, member, row, col_lo, col_n, scene.columns)
            for run in range(2):
                lo, hi = (lo0, hi0) if run == 0 else (lo1, hi1)
                if hi - lo > near.shape[0]:
                    near = np.empty(2 * (hi - lo), dtype=np.int64)
                # The points within the chord first, without branches (the cheaper scan), then
                # only those.
                found = 0
                for j in range(lo, hi):
                    dx = scene.rays[j, 0] - ux
                    dy = scene.rays[j, 1] - uy
                    dz = scene.rays[j, 2] - uz
                    near[found] = j
                    found += dx * dx + dy * dy + dz * dz <= chord2
                for f in range(found):
                    j = near[f]
                    if j == i or (masked and scene.absent[j]):
                        continue
                    dx = scene.rays[j, 0] - ux
                    dy = scene.rays[j, 1] - uy
                    dz = scene.rays[j, 2] - uz
                    d2 = dx * dx + dy * dy + dz * dz
                    if (
                        d2 == 0.0
                        and scene.rel[j, 0] == scene.rel[i, 0]
                        and scene.rel[j, 1] == scene.rel[i, 1]
                        and scene.rel[j, 2] == scene.rel[i, 2]
                    ):
                        continue  # an exact duplicate (equal points have equal rays)
                    t = 0.5 * d2 - (ri - scene.ranges[j]) / scene.rho[j]
                    if radial_only:
                        if t <= _SLACK:
                            return -1
                        continue
                    s1 = dx * e1x + dy * e1y + dz * e1z
                    s2 = dx * e2x + dy * e2y + dz * e2z
                    if certify and t < _SLACK:
                        quadrants |= _quadrant(s1, s2)
                        if quadrants == 15:
                            return _NO_PLANE
                    if count < capacity:
                        out_s1[count] = s1
                        out_s2[count] = s2
                        out_t[count] = t
                    count += 1
    return count


@nb.njit(cache=True, nogil=True)
def _quadrant(s1, s2):
    """Bit of the open quadrant holding ``(s1, s2)`` with a margin of 1e-9 of its size (far
    above rounding), 0 when near an axis."""
    margin = 1e-9 * (abs(s1) + abs(s2))
    if s1 > margin:
        return 1 if s2 > margin else (8 if s2 < -margin else 0)
    if s1 < -margin:
        return 2 if s2 > margin else (4 if s2 < -margin else 0)
    return 0


class _Work(NamedTuple):
    """Scratch buffers for a point's plane constraints ``a s1_j + b s2_j <= t_j``
    (:func:`_gather`), replaced by larger ones when they overflow."""

    s1: np.ndarray
    s2: np.ndarray
    t: np.ndarray


@nb.njit(cache=True, nogil=True)
def _new_work(size):
    return _Work(np.empty(size), np.empty(size), np.empty(size))


@nb.njit(cache=True, nogil=True)
def _gather_grown(i, cone, members, scene, work):
    """:func:`_gather` into the :class:`_Work` buffers, replaced by larger ones until every
    constraint fits; returns the count and the (possibly new) buffers."""
    while True:
        count = _gather(i, cone, False, members, scene, work.s1, work.s2, work.t)
        if count <= work.t.shape[0]:
            return count, work
        work = _new_work(2 * count)


@nb.njit(cache=True, nogil=True)
def _line_interval(constraint, f, d, lo, hi):
    """Clip the parameter interval ``[lo, hi]`` of the line ``f + lam d`` (``f = (fa, fb)``,
    ``d = (da, db)``) by the ``constraint`` ``(a, b, c)``: ``a x + b y <= c``. Returns
    ``(lo, hi, ok)``; ``ok`` is False when the constraint excludes the whole line (a parallel
    constraint that coincides with the line up to rounding counts as satisfied)."""
    a, b, c = constraint
    fa, fb = f
    da, db = d
    along = a * da + b * db
    room = c - (a * fa + b * fb)
    scale = abs(a) + abs(b)
    if abs(along) <= 1e-14 * scale:
        return lo, hi, room >= -1e-13 * (abs(c) + scale * (abs(fa) + abs(fb)))
    bound = room / along
    if along > 0.0:
        hi = min(hi, bound)
    else:
        lo = max(lo, bound)
    return lo, hi, True


@nb.njit(cache=True, nogil=True)
def _min_tilt(s1, s2, t, count):
    """The point nearest ``(0, 0)`` of the region ``a s1_j + b s2_j <= t_j - slack`` (all j),
    within the tilt box ``|a|, |b| <= _TILT_BOX``.

    Seidel's randomised incremental method for this LP-type problem: the optimum so far is kept
    while constraints hold, and recomputed on the violated constraint's line (a 1-D problem
    over the constraints seen before) when one does not. Seidel visits them in random order for
    expected linear work; a fixed stride through them (coprime with their number) scrambles
    the spatial order of the neighbour scan just as well in practice and stays deterministic.
    Returns ``(status, a, b)``: status 1
    feasible with ``(a, b)`` the nearest point, 0 infeasible.
    """
    box = _TILT_BOX
    xa, xb = 0.0, 0.0
    # 2**31 - 1 is prime, so its residue is coprime with count: k -> k * stride is a permutation
    stride = 2147483647 % count if count > 0 else 1
    for k in range(count):
        j = (k * stride) % count
        a, b, c = s1[j], s2[j], t[j] - _SLACK
        if a * xa + b * xb <= c:
            continue
        norm2 = a * a + b * b
        if norm2 == 0.0:
            return 0, 0.0, 0.0  # 0 <= c fails: a point straight in front on the same ray
        # nearest point of the line to the origin, and the line's direction
        fa, fb = c * a / norm2, c * b / norm2
        da, db = -b, a
        lo, hi, inside = -math.inf, math.inf, True
        for side in range(4):
            side_constraint = (_BOX_A[side], _BOX_B[side], box)
            lo, hi, ok = _line_interval(side_constraint, (fa, fb), (da, db), lo, hi)
            inside = inside and ok
        if not inside:
            return 0, 0.0, 0.0
        for previous in range(k):
            i = (previous * stride) % count
            lo, hi, ok = _line_interval((s1[i], s2[i], t[i] - _SLACK), (fa, fb), (da, db), lo, hi)
            if not ok:
                return 0, 0.0, 0.0
        if lo > hi:
            return 0, 0.0, 0.0
        lam = min(max(0.0, lo), hi)
        xa, xb = fa + lam * da, fb + lam * db
    return 1, xa, xb


@nb.njit(cache=True, nogil=True)
def _danger_cone(alpha_tan, ri, r_min, rho_max):
    """Tilt ``alpha`` and the angle around the plane normal beyond which no flipped point can
    cross a plane through flipped point ``i`` (range ``ri``) tilted by ``alpha``."""
    cos_alpha = 1.0 / math.sqrt(1.0 + alpha_tan * alpha_tan)
    alpha = math.atan(alpha_tan)
    one_minus = 2.0 * math.sin(alpha / 2.0) ** 2 + cos_alpha * (ri - r_min) / rho_max
    gamma = 2.0 * math.asin(min(1.0, math.sqrt(max(0.0, one_minus) / 2.0)))
    return alpha, gamma


@nb.njit(cache=True, nogil=True)
def _decide(i, first_cone, members, scene, work, brutes, brute_budget):
    """State (hidden 0, visible 1, unresolved 2) of sorted point ``i`` among the member sets
    ``members``, which the plane normal to its ray leaves undecided (see :func:`_radial_pass`).
    Returns it with the full scans made so far and the (possibly grown) buffers.

    Hidden is proven by a neighbourhood where no plane fits (hidden in a subset implies
    hidden); visible by the least tilted plane whose danger cone the neighbourhood covers.
    ``members`` may hold the :data:`_CERTIFY` bit (see :func:`_gather`).
    """
    ri = scene.ranges[i]
    cone = max(_FIRST_WIDENING * first_cone, 1e-6)
    # A narrow neighbourhood first: the points hiding a hidden point are usually its
    # nearest, and the full one can hold many times more.
    probe = _PROBE_NARROWING * first_cone
    if probe > 1e-6:
        count, work = _gather_grown(i, probe, members, scene, work)
        if count == _NO_PLANE or _min_tilt(work.s1, work.s2, work.t, count)[0] == 0:
            return _STATE_HIDDEN, brutes, work
    while True:
        everything = cone >= _BRUTE_ANGLE
        if everything:
            if brutes >= brute_budget:
                return _STATE_UNRESOLVED, brutes, work
            brutes += 1
            cone = math.pi
        count, work = _gather_grown(i, cone, members, scene, work)
        if count == _NO_PLANE:
            return _STATE_HIDDEN, brutes, work
        status, a, b = _min_tilt(work.s1, work.s2, work.t, count)
        if status == 0:
            return _STATE_HIDDEN, brutes, work
        if everything:
            return _STATE_VISIBLE, brutes, work
        alpha, gamma = _danger_cone(math.sqrt(a * a + b * b), ri, scene.r_min, scene.rho_max)
        if alpha + gamma <= cone * (1.0 - 1e-9):
            return _STATE_VISIBLE, brutes, work
        cone = max(2.0 * cone, 1.05 * (alpha + gamma))


@nb.njit(cache=True, nogil=True)
def _classify(todo, first_cone, scene, brute_budget):
    """States (hidden 0, visible 1, unresolved 2) of the sorted points ``todo``, which the
    plane normal to their ray leaves undecided (see :func:`_radial_pass`); at most
    ``brute_budget`` full scans, the points that need more are left unresolved."""
    state = np.empty(todo.shape[0], dtype=np.int64)
    work = _new_work(256)
    brutes = 0
    for slot in range(todo.shape[0]):
        i = todo[slot]
        state[slot], brutes, work = _decide(
            i, first_cone[i], _ORIGINALS, scene, work, brutes, brute_budget
        )
    return state


@nb.njit(cache=True, nogil=True)
def _radial_clear(i, cone, members, scene):
    """Whether no point of the member sets blocks the plane through sorted point ``i`` normal
    to its ray, within its first cone ``cone`` (:func:`_gather`'s radial test), on cells
    sorted by range.

    A point ``j`` blocks it when ``2 sin^2(theta / 2) <= (r_i - r_j) / (2R - r_j) + slack``
    (``theta``: the angle between the rays), so none farther than ``r_i + 4 slack R`` does:
    each cell is read only up to the first such point.
    """
    ux, uy, uz = scene.rays[i, 0], scene.rays[i, 1], scene.rays[i, 2]
    ri = scene.ranges[i]
    limit = ri + 4.0 * _SLACK * scene.radius
    reach = min(cone * (1.0 + 1e-9) + 1e-12, math.pi)
    half = math.sin(reach / 2.0)
    chord2 = 4.0 * half * half * (1.0 + 1e-12) + 1e-300
    if reach >= math.pi:
        chord2 = 5.0
    row_lo, row_hi, col_lo, col_n = _cell_range(
        scene.elevation[i],
        scene.azimuth[i],
        reach,
        scene.origin,
        scene.size,
        scene.rows,
        scene.columns,
    )
    first = (col_lo % scene.columns + scene.columns) % scene.columns
    masked = scene.absent.shape[0] > 0
    # Cells from the query's own outwards: a blocker, when there is one, usually lies right
    # next to the query's ray, and the answer does not depend on the order.
    n_rows = row_hi - row_lo + 1
    own_row = math.floor((scene.elevation[i] - scene.origin) / scene.size)
    own_row = min(max(own_row, row_lo), row_hi) - row_lo
    own_k = math.floor((scene.azimuth[i] + math.pi) / (2.0 * math.pi / scene.columns)) - col_lo
    own_k = min(max(own_k, 0), col_n - 1)
    for member in range(scene.starts.shape[0]):
        if not members & (1 << member):
            continue
        for a in range(2 * n_rows):
            row = own_row + ((a + 1) // 2 if a % 2 else -(a // 2))
            if row < 0 or row >= n_rows:
                continue
            row += row_lo
            for b in range(2 * col_n):
                k = own_k + ((b + 1) // 2 if b % 2 else -(b // 2))
                if k < 0 or k >= col_n:
                    continue
                column = first + k
                if column >= scene.columns:
                    column -= scene.columns
                cell = row * scene.columns + column
                for j in range(scene.starts[member, cell], scene.starts[member, cell + 1]):
                    if scene.ranges[j] > limit:
                        break
                    if j == i:
                        continue
                    dx = scene.rays[j, 0] - ux
                    dy = scene.rays[j, 1] - uy
                    dz = scene.rays[j, 2] - uz
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 > chord2 or (masked and scene.absent[j]):
                        continue
                    if (
                        d2 == 0.0
                        and scene.rel[j, 0] == scene.rel[i, 0]
                        and scene.rel[j, 1] == scene.rel[i, 1]
                        and scene.rel[j, 2] == scene.rel[i, 2]
                    ):
                        continue  # an exact duplicate
                    if 0.5 * d2 - (ri - scene.ranges[j]) / scene.rho[j] <= _SLACK:
                        return False
    return True
