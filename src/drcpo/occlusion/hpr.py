"""Katz et al.'s hidden point removal (HPR): :func:`hidden_point_removal`, methods, fallbacks.

Hidden point removal ("Direct Visibility of Point Sets", Katz, Tal and Basri, SIGGRAPH 2007)
---------------------------------------------------------------------------------------------
With the viewpoint ``C`` as origin, every point ``p`` is flipped to ``p + 2 (R - |p|) p / |p|``
(a point at range ``r`` lands on its own ray at range ``2R - r``); ``p`` is *visible* iff its
flipped image is a vertex of the convex hull of the flipped set together with ``C``. A larger
``R`` keeps more points. Open3D's ``PointCloud.hidden_point_removal(camera_location, radius)``
does exactly this (``radius`` is ``R`` itself, the origin is appended, Qhull runs with ``"Qt"``),
and DR.CPO's reference code calls it; :func:`hidden_point_removal` gives the same set.

Methods (``method=``):

* ``"reference"``: the plain algorithm, one Qhull hull (``scipy.spatial.ConvexHull``) of the
  whole flipped set. Open3D's answer, point for point, on inputs in general position. Clouds
  of at most :data:`HULL_KERNEL_MAX` points (``"auto"``: :data:`AUTO_REFERENCE_MAX`) within
  84 degrees of their mean direction, asked about every point (one object, for s-HPR), first
  try :mod:`drcpo.occlusion.hull`'s certified hull, which is cheaper: it answers only when
  every test it takes holds with a margin a thousand times Qhull's roundoff, and then its
  vertex set is Qhull's (exact copies share a verdict, as here); on a close call (coplanar
  points on the hull, near-copies, flat inputs, points at the viewpoint, ``R`` below half a
  range) Qhull decides, as before.
* ``"local"``: exact and fast. A flipped point is a hull vertex iff some plane through it has
  every other flipped point and ``C`` on one side. A plane tilted by ``alpha`` from the ray of
  ``p`` can only be crossed by points within a known angle of its normal (all flipped points
  lie within ``2R - r_min`` of ``C``), so each point is decided from its angular neighbours:
  first the plane normal to the ray (a cheap pre-filter that settles most points), then the
  least tilted plane that keeps every neighbour below (a two-variable problem solved by
  Seidel's randomised incremental method); no such plane means hidden. A point whose plane
  is tilted too far for its neighbourhood is retried with a wider one, at worst against every
  point (more than a few hundred such points go to one reference hull instead). Written with
  ranges and unit vectors, it never subtracts flipped coordinates, so it stays exact for huge
  ``R`` where those (and hence Qhull and Open3D) lose precision. Its cost grows with the
  number of points per neighbourhood: it is at its best on LiDAR sweeps and loses its lead
  over one hull on dense volumetric blobs (thousands of points per degree).
* ``"auto"`` (default): ``"reference"`` for small inputs (at most :data:`AUTO_REFERENCE_MAX`
  points, such as one object for s-HPR), when ``R`` is not far above the ranges (every
  neighbourhood is then a wide cone and one hull is cheaper) and when the points crowd the
  per-point test's neighbourhoods (on average more than :data:`AUTO_CROWDED` points share a
  point's grid cell, about a first neighbourhood wide: a dense object much smaller than its
  neighbourhoods, or many copies of a point, which make that test quadratic; LiDAR frames
  stay far below it), unless ``R`` is too large for the flipped coordinates (a crowded set is then
  tested once per distinct point); else ``"local"`` (e-HPR on whole frames). The answer is
  the same either way (see the methods' agreement above); only the time differs.

Defined behaviour on awkward input (every method):

* ``NaN``/``inf`` coordinates, a bad shape or viewpoint: :class:`~drcpo.errors.DataError`; a
  radius that is not a positive finite number (or above :data:`MAX_RADIUS`), an unknown method:
  :class:`~drcpo.errors.ConfigError`.
* No points: an empty mask. Points at the viewpoint (closer than ``1e-9 * (1 + max range)``)
  cannot be flipped: they are reported visible and take no part in the hull.
* Exact duplicates share one verdict (all copies visible or all hidden); Open3D keeps one copy.
* Fewer than four hull points, or a flat configuration (all points and the viewpoint on one
  plane, collinear, ...): Qhull cannot build a 3-D hull; the answer is the ``"local"`` one, which
  is the same construction within that plane or line.
* ``R`` below half the largest range (Katz's method needs ``R`` above every range): the
  flip is applied literally as Open3D does (points beyond ``2R`` land behind the viewpoint),
  always through the reference hull; the result is Open3D's, not a meaningful visibility.
* A Qhull failure never escapes: a degenerate hull falls back to ``"local"`` (or, when ``R``
  is below half the largest range, to Qhull's joggled mode ``"QJ"`` and finally to "all
  visible" with a :class:`RuntimeWarning`).

The paper's uses of it are in :mod:`drcpo.occlusion.scopes` (s-HPR) and
:mod:`drcpo.occlusion.external` (e-HPR). This module
imports the checks, flip, local and hull modules of :mod:`drcpo.occlusion`.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from drcpo.errors import ConfigError, DataError
from drcpo.occlusion.checks import (
    _check_points,
    _check_query,
    _check_radius,
    _check_viewpoint,
)
from drcpo.occlusion.flip import _AT_VIEWPOINT, _hull_vertices, _Setup
from drcpo.occlusion.hull import hpr_hull_visible
from drcpo.occlusion.local import _local, _LocalState

__all__ = [
    "AUTO_CROWDED",
    "AUTO_REFERENCE_MAX",
    "HPR_METHODS",
    "HULL_KERNEL_MAX",
    "hidden_point_removal",
]

HPR_METHODS: tuple[str, ...] = ("auto", "local", "reference")
AUTO_REFERENCE_MAX = 2000  # "auto" runs one Qhull hull up to this many points
# "auto" runs one hull when more points than this, on average, share a point's cell of the
# per-point test's grid (cells about a first neighbourhood wide): that test's time grows with
# the points per neighbourhood, a hull's does not. LiDAR frames stay far below it, the crowded
# inputs of benchmarks/bench_hpr_crowded.py far above (docs/measurements.md).
AUTO_CROWDED = 128
HULL_KERNEL_MAX = 20000  # "reference" tries occlusion.hull's certified hull up to this many points
_KERNEL_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))
# Above this R / (max range), the flipped coordinates keep too few bits of the ranges for Qhull.
_QHULL_RATIO_MAX = 1e7
# "auto" prefers one hull when the median point's first neighbourhood is wider than this (rad).
_LOCAL_MAX_CONE = 0.1


def hidden_point_removal(
    points: np.ndarray,
    viewpoint: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    radius: float = 100000.0,
    *,
    method: str = "auto",
    query: np.ndarray | None = None,
) -> np.ndarray:
    """Katz et al.'s hidden point removal: which points are visible from ``viewpoint``.

    Args:
        points: ``(N, 3 + C)`` x, y, z (metres) then any features (ignored); any float dtype,
            computed in float64.
        viewpoint: ``(3,)`` viewpoint (metres), the origin of the spherical flip.
        radius: ``R`` of the spherical flip (metres), Open3D's ``radius`` argument.
        method: ``"auto"``, ``"local"`` or ``"reference"`` (module docstring).
        query: optional ``bool (N,)`` mask or integer indices of the points whose visibility is
            wanted; the others are still potential occluders but are reported ``True`` without
            being decided. ``None``: all points.

    Returns:
        ``bool (N,)``: ``True`` for visible points (and for points outside ``query``).
    """
    if query is None and method in ("reference", "auto"):
        certified = _certified_reference(points, viewpoint, radius, method)
        if certified is not None:
            return certified
    xyz = _check_points(points)
    center = _check_viewpoint(viewpoint)
    radius = _check_radius(radius)
    if method not in HPR_METHODS:
        raise ConfigError(f"method must be one of {', '.join(HPR_METHODS)}, got {method!r}")
    wanted = _check_query(query, len(xyz))
    visible = np.ones(len(xyz), dtype=bool)
    if len(xyz) == 0 or not wanted.any():
        return visible
    setup = _Setup.build(xyz, center, radius)
    if setup.size == 0:
        return visible
    wanted_hull = wanted[setup.index]
    chosen = _resolve_method(method, setup)
    if chosen == "reference":
        decided = _reference(setup, wanted_hull)
    elif method == "auto":
        decided = _auto_local(setup, wanted_hull)
    else:
        decided = _local(setup, wanted_hull)
    visible[setup.index] = decided | ~wanted_hull
    return visible


def _resolve_method(method: str, setup: _Setup) -> str:
    if not setup.local_ok:
        return "reference"
    if method != "auto":
        return method
    precise = _precise(setup)
    if setup.size <= AUTO_REFERENCE_MAX and precise:
        return "reference"
    # With R not far above the ranges every point's neighbourhood is a wide cone and the
    # per-point test degrades towards quadratic time; one hull is then cheaper.
    spread = float(np.median(setup.ranges)) - float(setup.ranges.min())
    if spread > _LOCAL_MAX_CONE**2 * setup.radius and precise:
        return "reference"
    return "local"


def _precise(setup: _Setup) -> bool:
    """Whether ``R`` leaves the flipped coordinates enough bits of the ranges for Qhull."""
    return setup.radius <= _QHULL_RATIO_MAX * float(setup.ranges.max())


def _crowded(starts: np.ndarray, setup: _Setup) -> bool:
    """Whether the set-up's points crowd the cells of its per-point test's grid (``starts``:
    each cell's first sorted position): on average more than :data:`AUTO_CROWDED` points
    share a point's cell."""
    sizes = np.diff(starts).astype(np.float64)
    return float(sizes @ sizes) > AUTO_CROWDED * max(setup.size, 1)


def _auto_local(setup: _Setup, wanted: np.ndarray) -> np.ndarray:
    """``"auto"``'s verdicts where :func:`_resolve_method` chose ``"local"``: the per-point test,
    unless the points crowd its neighbourhoods; then one hull, or (``R`` too large for one)
    the per-point test on the distinct points (copies share a verdict and do not constrain
    each other's planes, so the answer is the same)."""
    state = _LocalState.build(setup)
    if not _crowded(state.starts, setup):
        return state.visible(wanted)
    if _precise(setup):
        return _reference(setup, wanted)
    return _distinct_local(setup, wanted)


def _distinct_local(setup: _Setup, wanted: np.ndarray) -> np.ndarray:
    """:func:`_local`'s verdicts, computed once per distinct point."""
    distinct, inverse = setup.distinct()
    if distinct is setup:
        return _local(setup, wanted)
    wanted_distinct = np.zeros(distinct.size, dtype=bool)
    wanted_distinct[inverse[wanted]] = True
    return _local(distinct, wanted_distinct)[inverse] & wanted


# ----------------------------------------------------------------------------------------------
# Reference: one Qhull hull, as Open3D
# ----------------------------------------------------------------------------------------------
def _reference(setup: _Setup, wanted: np.ndarray) -> np.ndarray:
    """Visible flags ``(M,)`` of the set-up's points from one hull of the whole flipped set."""
    distinct, inverse = setup.distinct()
    vertex = _hull_vertices(distinct.flipped())
    if vertex is None:
        return _degenerate_fallback(setup, wanted)
    return vertex if distinct is setup else vertex[inverse]


def _certified_reference(
    points: np.ndarray, viewpoint: Sequence[float] | np.ndarray, radius: float, method: str
) -> np.ndarray | None:
    """The reference answer from :mod:`drcpo.occlusion.hull`'s certified hull, straight from
    float32 or float64 ``(N, 3 + C)`` points, or ``None`` where it gives up or the input is one
    it leaves to the general path (which also validates it): non-finite values, points at the
    viewpoint, ``R`` below half a range, and, for ``"auto"``, the inputs it does not send to one
    hull."""
    limit = HULL_KERNEL_MAX if method == "reference" else AUTO_REFERENCE_MAX
    if not (
        isinstance(points, np.ndarray)
        and points.dtype in _KERNEL_DTYPES
        and points.ndim == 2
        and points.shape[1] >= 3
        and 4 <= len(points) <= limit
    ):
        return None
    try:
        center = _check_viewpoint(viewpoint)
        radius = _check_radius(radius)
    except (ConfigError, DataError):
        return None  # raised again, in the usual order, by the general path
    ratio = math.inf if method == "reference" else _QHULL_RATIO_MAX
    return hpr_hull_visible(
        np.ascontiguousarray(points), center, radius, max_ratio=ratio, at_viewpoint=_AT_VIEWPOINT
    )


def _degenerate_fallback(setup: _Setup, wanted: np.ndarray) -> np.ndarray:
    """Verdicts when Qhull cannot build the hull: "local" (once per distinct point: many
    copies of one point would make it quadratic), else joggled Qhull, else all."""
    if setup.local_ok:
        return _distinct_local(setup, wanted)
    distinct, inverse = setup.distinct()
    cloud = np.vstack([distinct.flipped(), np.zeros((1, 3))])
    try:
        hull = ConvexHull(cloud, qhull_options="QJ")
    except (QhullError, ValueError):
        warnings.warn(
            "hidden_point_removal: Qhull cannot build a hull of these points even joggled "
            f"({distinct.size} distinct points, R below half the largest range); all are kept",
            RuntimeWarning,
            stacklevel=4,
        )
        return np.ones(setup.size, dtype=bool)
    vertex = np.zeros(len(cloud), dtype=bool)
    vertex[hull.vertices] = True
    return vertex[:-1][inverse]
