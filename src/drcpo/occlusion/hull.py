"""Certified hidden point removal for small clouds: the hull of flipped points and the viewpoint.

Katz et al.'s HPR keeps a point when its spherical flip is a vertex of the convex hull of the
flipped points together with the viewpoint. :func:`flip_hull_visible` computes that vertex set
with its own hull (numba) and answers only when the answer is certain, so that the caller can
fall back on Qhull otherwise; whenever it answers, Qhull (hence Open3D) gives the same set.

The hull. With the viewpoint ``O`` as origin and every point within 84 degrees of one axis, ``O`` is
a vertex and every other facet ("far" facets) is met by the rays from ``O`` through the points
behind it. The points are inserted one at a time: first the nearest point of each cell of a coarse
grid across the mean direction, then the others along a Hilbert curve over a fine grid, so that the
visible surface is built early, most later points fall inside and each point is found near the last
one (:mod:`~drcpo.occlusion.hull_order`). A walk across far facets finds the facet that a point's
ray crosses (edge by edge, from the last facet found); a point below it is dropped, a point above it
is a new vertex: the facets it sees are replaced by a cone from it over their horizon. An exact copy
of a vertex is left out and takes the vertex's verdict (Open3D keeps one copy; drcpo gives all
copies its verdict).

Certainty is defined against a perturbation: every point may move by up to ``rho = rel_tol x
(largest |coordinate|)``. Every orientation test (is point ``q`` above the plane of ``(a, b,
c)``?) is accepted only when its sign holds for every such perturbation of the four points: a
quick margin first, then, for close calls, a tight one (the determinant's gradient with respect
to each corner is twice the area of the opposite face), both far above float64's own error. A
close call in the walk is settled by testing every facet instead; any other close call gives
up. The incremental hull is correct in exact arithmetic, so a run that took no close call
returns the same, hence the exact, vertex set for every input in that ball:

* a dropped point lies, clearly, in the cone from ``O`` over a far facet and below its plane,
  hence on the segment from ``O`` to that facet (or below every facet's plane), inside the hull;
* the final hull is then checked edge by edge: the far corner of each facet's neighbour lies
  clearly below the facet's plane, so no two facets are coplanar, every facet is a 2-face of
  the polytope and all its corners are vertices, with a margin.

Qhull's roundoff and merge thresholds (a few ``1e-15`` of the coordinates, times small factors)
lie far inside that ball. Coplanar quadruples on the hull, near-copies, flat sets, points around
or at the viewpoint and other awkward inputs make it give up instead (about one real s-HPR
object in a thousand; checked against Qhull on real, synthetic, mirrored and lattice clouds in
``tests/test_hull.py``).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from drcpo.occlusion.hull_order import _insertion_order

__all__ = ["REL_TOL", "flip_hull_visible", "hpr_hull_visible"]

# Radius of the perturbation ball, relative to the largest |coordinate|: hundreds of times
# Qhull's roundoff and a thousand times our own float64 error.
REL_TOL = 1e-12
# Facet slots of a first attempt; a run that needs more starts again with room for any hull.
_FIRST_CAPACITY = 512
CERTIFIED, UNSURE, _FULL = 0, 1, 2


def hpr_hull_visible(
    xyz: np.ndarray,
    center: np.ndarray,
    radius: float,
    *,
    max_ratio: float = math.inf,
    at_viewpoint: float = 1e-9,
) -> np.ndarray | None:
    """``bool (N,)`` Katz et al.'s visible points, or ``None`` when not certain (module docstring).

    Args:
        xyz: ``(N, 3 + C)`` float32 or float64 points, metres (extra columns ignored).
        center: ``(3,)`` float64 viewpoint, metres.
        radius: the flip's ``R`` (metres).
        max_ratio: give up when ``R`` exceeds this many times the largest range.
        at_viewpoint: give up when a point is closer to the viewpoint than this times
            ``1 + largest range`` (the caller treats those points apart).

    Returns:
        ``bool (N,)``, or ``None`` for fewer than four points, ``2 R`` not above every range, and
        whatever :func:`flip_hull_visible` gives up on.
    """
    visible = np.empty(len(xyz), dtype=np.bool_)
    if flip_hull_visible(xyz, center, float(radius), float(max_ratio), at_viewpoint, visible):
        return visible
    return None


@nb.njit(cache=True, nogil=True)
def flip_hull_visible(xyz, center, radius, max_ratio, at_viewpoint, visible):  # pragma: no cover
    """Numba kernel of :func:`hpr_hull_visible`: fills ``visible`` and returns ``True``, or
    returns ``False`` (``visible`` undefined). Releases the GIL.

    The flip of ``p`` (relative to ``center``) is ``p + p * (2 (R - |p|) / |p|)``, as Open3D
    and :mod:`drcpo.occlusion` compute it.
    """
    n = xyz.shape[0]
    if n < 4:
        return False
    cloud = np.empty((n + 1, 3), dtype=np.float64)
    ranges = np.empty(n, dtype=np.float64)
    largest = 0.0
    axis = np.zeros(3, dtype=np.float64)  # the mean direction of the flipped points, scaled
    for i in range(n):
        x = xyz[i, 0] - center[0]
        y = xyz[i, 1] - center[1]
        z = xyz[i, 2] - center[2]
        r = np.sqrt(x * x + y * y + z * z)
        if not r < np.inf:  # NaN or inf: the caller's validation reports it
            return False
        ranges[i] = r
        largest = max(largest, r)
        if not r > 0.0:  # at the viewpoint: turned away below
            return False
        scale = 2.0 * (radius - r) / r
        cloud[i, 0] = x + x * scale
        cloud[i, 1] = y + y * scale
        cloud[i, 2] = z + z * scale
        axis[0] += cloud[i, 0]
        axis[1] += cloud[i, 1]
        axis[2] += cloud[i, 2]
    cloud[n, :] = 0.0
    if not (2.0 * radius > largest * (1.0 + 1e-12) and radius <= max_ratio * largest):
        return False
    near = at_viewpoint * (1.0 + largest)
    for i in range(n):
        if not ranges[i] > near:
            return False
    order = _insertion_order(cloud, ranges, radius, axis)
    if len(order) == 0:
        return False
    vertex = np.zeros(n + 1, dtype=np.bool_)
    copies = np.full(n + 1, -1, dtype=np.int64)
    cap = min(_FIRST_CAPACITY, 3 * n + 16)
    status = _apex_hull(cloud, order, REL_TOL, vertex, copies, cap)
    if status == _FULL:
        vertex[:] = False
        copies[:] = -1
        status = _apex_hull(cloud, order, REL_TOL, vertex, copies, 3 * n + 16)  # live <= 2n
    if status != CERTIFIED:
        return False
    for i in range(n):  # copies must be copies of the input too, as the general path sees them
        j = copies[i]
        if j >= 0 and not (
            xyz[i, 0] == xyz[j, 0] and xyz[i, 1] == xyz[j, 1] and xyz[i, 2] == xyz[j, 2]
        ):
            return False
    visible[:] = vertex[:n]
    return True


@nb.njit(cache=True, nogil=True, inline="always")
def _set_plane(points, f, corners, facets, rho, diam):  # pragma: no cover - numba
    """Facet ``f`` with ``corners`` ``(a, b, c)`` (counter-clockwise seen from outside): its
    plane in ``facets`` and the quick margin ``facets.taus[f]`` that a height must exceed to
    keep its sign under the perturbation."""
    a, b, c = corners
    verts, normals, offsets, taus = facets
    verts[f, 0] = a
    verts[f, 1] = b
    verts[f, 2] = c
    x0 = points[b, 0] - points[a, 0]
    x1 = points[b, 1] - points[a, 1]
    x2 = points[b, 2] - points[a, 2]
    y0 = points[c, 0] - points[a, 0]
    y1 = points[c, 1] - points[a, 1]
    y2 = points[c, 2] - points[a, 2]
    n0 = x1 * y2 - x2 * y1
    n1 = x2 * y0 - x0 * y2
    n2 = x0 * y1 - x1 * y0
    normals[f, 0] = n0
    normals[f, 1] = n1
    normals[f, 2] = n2
    offsets[f] = n0 * points[a, 0] + n1 * points[a, 1] + n2 * points[a, 2]
    # Lengths bounded by 1-norms (no square root: this runs for every facet).
    lx = abs(x0) + abs(x1) + abs(x2)
    ly = abs(y0) + abs(y1) + abs(y2)
    # det(b - a, c - a, q - a) moves by at most 2 rho (|x||y| + |x||z| + |y||z|) + O(rho^2)
    # when each point moves by rho, with |z| = |q - a| <= diam; twice that, to be safe.
    taus[f] = 4.0 * rho * (lx * ly + diam * (lx + ly) + 2.0 * rho * (lx + ly + diam) + 4.0 * rho**2)


@nb.njit(cache=True, nogil=True, inline="always")
def _height(points, f, q, normals, offsets):  # pragma: no cover - numba
    """``det(b - a, c - a, q - a)`` of facet ``f = (a, b, c)``: positive above (outside)."""
    return (
        normals[f, 0] * points[q, 0]
        + normals[f, 1] * points[q, 1]
        + normals[f, 2] * points[q, 2]
        - offsets[f]
    )


@nb.njit(cache=True, nogil=True)
def _close_call(points, f, q, h, verts, rho, maxabs):  # pragma: no cover - numba
    """Sign (+1, -1, or 0: not sure) of ``q``'s height ``h`` over facet ``f`` when the quick
    margin was not enough; only reached on close calls, so it may be slower."""
    a = verts[f, 0]
    b = verts[f, 1]
    c = verts[f, 2]
    return _tight_sign(
        (points[a, 0], points[a, 1], points[a, 2]),
        (points[b, 0], points[b, 1], points[b, 2]),
        (points[c, 0], points[c, 1], points[c, 2]),
        (points[q, 0], points[q, 1], points[q, 2]),
        h,
        rho,
        maxabs,
    )


@nb.njit(cache=True, nogil=True)
def _tight_sign(a, b, c, q, h, rho, maxabs):  # pragma: no cover - numba
    """Sign of ``h = det(b - a, c - a, q - a)`` when it holds under the perturbation, else 0.
    The points are tuples of three floats (values, not arrays: a call from the hot loops then
    costs nothing until it is taken)."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    c0, c1, c2 = c
    q0, q1, q2 = q
    x0 = b0 - a0
    x1 = b1 - a1
    x2 = b2 - a2
    y0 = c0 - a0
    y1 = c1 - a1
    y2 = c2 - a2
    z0 = q0 - a0
    z1 = q1 - a1
    z2 = q2 - a2
    area_abc = _norm_cross(x0, x1, x2, y0, y1, y2)
    area_abq = _norm_cross(x0, x1, x2, z0, z1, z2)
    area_acq = _norm_cross(y0, y1, y2, z0, z1, z2)
    area_bcq = _norm_cross(c0 - b0, c1 - b1, c2 - b2, q0 - b0, q1 - b1, q2 - b2)
    lx = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    ly = np.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
    lz = np.sqrt(z0 * z0 + z1 * z1 + z2 * z2)
    bound = (
        2.0 * rho * (area_abc + area_abq + area_acq + area_bcq)
        + 8.0 * rho * rho * (lx + ly + lz + rho)
        + 1e-15 * lx * ly * lz  # float64 roundoff of h itself
        + 1e-14 * area_abc * maxabs
    )
    if h > bound:
        return 1
    if h < -bound:
        return -1
    return 0


@nb.njit(cache=True, nogil=True, inline="always")
def _norm_cross(x0, x1, x2, y0, y1, y2):  # pragma: no cover - numba
    c0 = x1 * y2 - x2 * y1
    c1 = x2 * y0 - x0 * y2
    c2 = x0 * y1 - x1 * y0
    return np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)


@nb.njit(cache=True, nogil=True, inline="always")
def _set_edges(points, f, verts, edges):  # pragma: no cover - numba
    """The planes through the apex and each edge of far facet ``f``: ``edges[f, i]`` is
    ``v_i x v_(i+1)``, positive on the facet's side."""
    for i in range(3):
        a = verts[f, i]
        b = verts[f, (i + 1) % 3]
        edges[f, i, 0] = points[a, 1] * points[b, 2] - points[a, 2] * points[b, 1]
        edges[f, i, 1] = points[a, 2] * points[b, 0] - points[a, 0] * points[b, 2]
        edges[f, i, 2] = points[a, 0] * points[b, 1] - points[a, 1] * points[b, 0]


@nb.njit(cache=True, nogil=True)
def _apex_hull(points, order, rel_tol, vertex, copies, cap):  # pragma: no cover - numba
    """Vertices of the hull of ``points`` (``(N + 1, 3)``, the last row the apex ``(0, 0, 0)``),
    inserting ``order`` (its first three with the apex form the first tetrahedron), with
    ``cap`` facet slots: :data:`CERTIFIED` (``vertex`` filled), :data:`UNSURE`, or ``_FULL``.
    A point equal to a vertex is left out and takes its verdict: ``copies`` (``(N + 1,)``, -1
    on entry) holds that vertex."""
    m = points.shape[0]
    apex = m - 1
    maxabs = 0.0
    reach = 0.0  # the largest squared distance from the apex
    for i in range(m):
        reach = max(reach, points[i, 0] ** 2 + points[i, 1] ** 2 + points[i, 2] ** 2)
        for k in range(3):
            maxabs = max(maxabs, abs(points[i, k]))
    if not maxabs > 0.0:
        return UNSURE
    rho = rel_tol * maxabs
    diam = 2.0 * np.sqrt(3.0) * maxabs  # bounds |q - a| for any two points
    # One quick margin for all the walk's tests det(u, v, q) (apex, u, v and q): twice the
    # areas of their faces add up to at most 7 reach (every point within sqrt(reach) of the
    # apex); twice that, plus the higher orders.
    reach = np.sqrt(reach)
    etau = 2.0 * rho * (14.0 * reach * reach + 16.0 * rho * reach + 16.0 * rho**2)

    verts = np.empty((cap, 3), dtype=np.int32)
    nbrs = np.empty((cap, 3), dtype=np.int32)  # nbrs[f, i]: across edge (verts[f, i], next)
    normals = np.empty((cap, 3), dtype=np.float64)
    offsets = np.empty(cap, dtype=np.float64)
    taus = np.empty(cap, dtype=np.float64)
    edges = np.empty((cap, 3, 3), dtype=np.float64)
    alive = np.zeros(cap, dtype=np.bool_)
    is_far = np.zeros(cap, dtype=np.bool_)
    vis_mark = np.zeros(cap, dtype=np.int32)
    nov_mark = np.zeros(cap, dtype=np.int32)
    free = np.empty(cap, dtype=np.int32)
    visible = np.empty(cap, dtype=np.int32)
    hor_f = np.empty(cap, dtype=np.int32)
    hor_i = np.empty(cap, dtype=np.int32)
    hor_u = np.empty(cap, dtype=np.int32)
    hor_v = np.empty(cap, dtype=np.int32)
    hor_g = np.empty(cap, dtype=np.int32)
    new = np.empty(cap, dtype=np.int32)
    start_of = np.empty(m, dtype=np.int32)
    end_of = np.empty(m, dtype=np.int32)

    # The first tetrahedron, its far facet first.
    a = order[0]
    b = order[1]
    c = order[2]
    facets = (verts, normals, offsets, taus)
    _set_plane(points, 0, (a, b, c), facets, rho, diam)
    h = -offsets[0]  # the apex's height
    if not abs(h) > taus[0] and _close_call(points, 0, apex, h, verts, rho, maxabs) == 0:
        return UNSURE
    if h > 0.0:
        b, c = c, b
    corners = (a, b, c, apex)
    faces = ((0, 1, 2), (0, 3, 1), (1, 3, 2), (2, 3, 0))
    for f in range(4):
        face = faces[f]
        _set_plane(
            points, f, (corners[face[0]], corners[face[1]], corners[face[2]]), facets, rho, diam
        )
        opposite = corners[6 - faces[f][0] - faces[f][1] - faces[f][2]]
        h = _height(points, f, opposite, normals, offsets)
        if not h < -taus[f] and _close_call(points, f, opposite, h, verts, rho, maxabs) != -1:
            return UNSURE
        alive[f] = True
    is_far[0] = True
    _set_edges(points, 0, verts, edges)
    for f in range(4):
        for i in range(3):
            u = verts[f, i]
            v = verts[f, (i + 1) % 3]
            for g in range(4):
                for j in range(3):
                    if verts[g, j] == v and verts[g, (j + 1) % 3] == u:
                        nbrs[f, i] = g
    top = 4
    n_free = 0
    last = 0  # where the next walk starts: the last far facet found
    it = 0
    for t in range(3, len(order)):
        q = order[t]
        q0 = points[q, 0]
        q1 = points[q, 1]
        q2 = points[q, 2]
        # Walk to the far facet that q's ray crosses; eye: the facet to insert q from, -1 to
        # drop q, -2 to decide by testing every facet (a close call on the way).
        f = last
        eye = -2
        steps = 0
        while steps <= top + 16:
            if not is_far[f]:  # the ray left the cone over the far facets, through f's plane
                h = _height(points, f, q, normals, offsets)
                if h > taus[f] or (
                    h >= -taus[f] and _close_call(points, f, q, h, verts, rho, maxabs) == 1
                ):
                    eye = f
                break
            e0 = edges[f, 0, 0] * q0 + edges[f, 0, 1] * q1 + edges[f, 0, 2] * q2
            e1 = edges[f, 1, 0] * q0 + edges[f, 1, 1] * q1 + edges[f, 1, 2] * q2
            e2 = edges[f, 2, 0] * q0 + edges[f, 2, 1] * q1 + edges[f, 2, 2] * q2
            close = False
            if not (e0 > etau and e1 > etau and e2 > etau):
                # Across the edge q is farthest beyond (any edge it is beyond would do), or
                # a close call settled with the tight bound.
                i = 0 if e0 <= e1 and e0 <= e2 else (1 if e1 <= e2 else 2)
                e = min(e0, e1, e2)
                if e < -etau:
                    f = nbrs[f, i]
                    steps += 1
                    continue
                moved = False
                for i in range(3):
                    e = e0 if i == 0 else (e1 if i == 1 else e2)
                    if e > etau:
                        continue
                    u = verts[f, i]
                    v = verts[f, i + 1 if i < 2 else 0]
                    sign = _tight_sign(
                        (0.0, 0.0, 0.0),
                        (points[u, 0], points[u, 1], points[u, 2]),
                        (points[v, 0], points[v, 1], points[v, 2]),
                        (q0, q1, q2),
                        e,
                        rho,
                        maxabs,
                    )
                    if sign == -1:
                        f = nbrs[f, i]
                        moved = True
                        break
                    if sign == 0:
                        close = True
                if moved:
                    steps += 1
                    continue
            if not close:
                last = f
                h = _height(points, f, q, normals, offsets)
                if h < -taus[f]:
                    eye = -1
                elif h > taus[f]:
                    eye = f
                else:
                    sign = _close_call(points, f, q, h, verts, rho, maxabs)
                    if sign != 0:
                        eye = f if sign == 1 else -1
            break
        if eye == -2:
            unsure = False
            for g in range(top):
                if not alive[g]:
                    continue
                h = _height(points, g, q, normals, offsets)
                if h < -taus[g]:
                    continue
                sign = 1 if h > taus[g] else _close_call(points, g, q, h, verts, rho, maxabs)
                if sign == 1:
                    eye = g
                    break
                if sign == 0:
                    unsure = True
                    for j in range(3):  # an exact copy of a vertex takes that vertex's verdict
                        w = verts[g, j]
                        if points[w, 0] == q0 and points[w, 1] == q1 and points[w, 2] == q2:
                            copies[q] = w
                    if copies[q] >= 0:
                        eye = -1
                        break
            if eye == -2:
                if unsure:
                    return UNSURE
                eye = -1
        if eye == -1:
            continue
        # q is a new vertex: the facets it sees (a patch around eye) and their horizon.
        it += 1
        vis_mark[eye] = it
        visible[0] = eye
        n_vis = 1
        n_hor = 0
        k = 0
        while k < n_vis:
            vf = visible[k]
            k += 1
            for i in range(3):
                g = nbrs[vf, i]
                if vis_mark[g] == it:
                    continue
                if nov_mark[g] != it:
                    h = _height(points, g, q, normals, offsets)
                    if h > taus[g]:
                        sign = 1
                    elif h < -taus[g]:
                        sign = -1
                    else:
                        sign = _close_call(points, g, q, h, verts, rho, maxabs)
                    if sign == 1:
                        vis_mark[g] = it
                        visible[n_vis] = g
                        n_vis += 1
                        continue
                    if sign == 0:
                        return UNSURE
                    nov_mark[g] = it
                hor_f[n_hor] = vf
                hor_i[n_hor] = i
                n_hor += 1
        # The cone from q over the horizon, in the slots of the replaced facets first.
        for e in range(n_hor):
            vf = hor_f[e]
            i = hor_i[e]
            hor_u[e] = verts[vf, i]
            hor_v[e] = verts[vf, i + 1 if i < 2 else 0]
            hor_g[e] = nbrs[vf, i]
        for k in range(n_vis):
            alive[visible[k]] = False
            free[n_free] = visible[k]
            n_free += 1
        for e in range(n_hor):
            u = hor_u[e]
            v = hor_v[e]
            g = hor_g[e]
            if n_free > 0:
                n_free -= 1
                nf = free[n_free]
            elif top < cap:
                nf = top
                top += 1
            else:
                return _FULL
            _set_plane(points, nf, (u, v, q), facets, rho, diam)
            alive[nf] = True
            is_far[nf] = u != apex and v != apex
            if is_far[nf]:
                h = -offsets[nf]  # the apex's height: it must lie clearly below
                if not h < -taus[nf] and _close_call(points, nf, apex, h, verts, rho, maxabs) != -1:
                    return UNSURE
                _set_edges(points, nf, verts, edges)
                last = nf
            nbrs[nf, 0] = g
            # g holds the edge as (v, u); matched by vertices, as slots are being reused
            nbrs[g, 0 if verts[g, 1] == u else (1 if verts[g, 2] == u else 2)] = nf
            start_of[u] = nf
            end_of[v] = nf
            new[e] = nf
        for e in range(n_hor):
            nf = new[e]
            nbrs[nf, 1] = start_of[verts[nf, 1]]
            nbrs[nf, 2] = end_of[verts[nf, 0]]

    # Certificate: every edge clearly convex, so that every facet is a 2-face.
    n_facets = 0
    for f in range(top):
        if not alive[f]:
            continue
        n_facets += 1
        for i in range(3):
            g = nbrs[f, i]
            u = verts[f, i]
            v = verts[f, i + 1 if i < 2 else 0]
            w = verts[g, 0]
            if w == u or w == v:
                w = verts[g, 1]
                if w == u or w == v:
                    w = verts[g, 2]
            h = _height(points, f, w, normals, offsets)
            if not h < -taus[f] and _close_call(points, f, w, h, verts, rho, maxabs) != -1:
                return UNSURE
            vertex[u] = True
    n_vertices = 0
    for i in range(m):
        if vertex[i]:
            n_vertices += 1
    if n_facets != 2 * n_vertices - 4:  # not a triangulated sphere: a bug, let Qhull decide
        return UNSURE
    for i in range(m):
        if copies[i] >= 0:
            vertex[i] = vertex[copies[i]]
    return CERTIFIED
