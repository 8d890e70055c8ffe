"""Occlusion: Katz et al.'s hidden point removal (HPR), the paper's s-HPR / e-HPR, a range image.

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
  try :mod:`drcpo.hull`'s certified hull, 6-7 times cheaper: it answers only when every test it
  takes holds with a margin a thousand times Qhull's roundoff, and then its vertex set is
  Qhull's (exact copies share a verdict, as here); on a close call (coplanar points on the
  hull, near-copies, flat inputs, points at the viewpoint, ``R`` below half a range) Qhull
  decides, as before.
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
  number of points per neighbourhood: LiDAR sweeps take tens of milliseconds, while dense
  volumetric blobs (thousands of points per degree) bring it down to about Qhull's speed.
* ``"sectors"``: the reference hull split into overlapping azimuth sectors, the hulls spread
  over threads; a sector's verdict on one of its core points is used only when it is provably the
  whole set's (hidden in a subset implies hidden; visible needs a hull facet whose danger cone
  lies inside the sector), the rest go to ``"local"``.
* ``"auto"`` (default): ``"reference"`` for small inputs (at most :data:`AUTO_REFERENCE_MAX`
  points, such as one object for s-HPR), when ``R`` is not far above the ranges (every
  neighbourhood is then a wide cone and one hull is cheaper) and when the points crowd the
  per-point test's neighbourhoods (on average more than :data:`AUTO_CROWDED` points share a
  point's grid cell, about a first neighbourhood wide: a dense object much smaller than its
  neighbourhoods, or many copies of a point, which make that test quadratic; LiDAR frames
  give 2-6), unless ``R`` is too large for the flipped coordinates (a crowded set is then
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

The paper's two uses are :func:`self_occlusion` (s-HPR, per placed object, ``R`` = box
diagonal x 200) and :func:`external_occlusion` (e-HPR, the whole frame after insertion, ``R`` and
the viewpoint height from :data:`HPR_PRESETS`). :func:`range_image_occlusion` is a z-buffer
alternative that is *not* the paper's method.

Everything here is safe in forked worker processes (PyTorch DataLoader workers): no thread or
pool outlives a call, and numba kernels are compiled without a threading layer.
"""

from __future__ import annotations

import math
import os
import threading
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from typing import Any

import numba as nb
import numpy as np
from scipy.spatial import ConvexHull, QhullError

from drcpo.errors import ConfigError, DataError
from drcpo.hull import hpr_hull_visible

__all__ = [
    "AUTO_CROWDED",
    "AUTO_REFERENCE_MAX",
    "HPR_METHODS",
    "HPR_PRESETS",
    "HULL_KERNEL_MAX",
    "MAX_RADIUS",
    "FrameGrid",
    "HPRPreset",
    "azimuth_focus",
    "external_occlusion",
    "hidden_by_insertion",
    "hidden_point_removal",
    "range_image_occlusion",
    "self_occlusion",
    "self_occlusion_many",
]


@dataclass(frozen=True)
class HPRPreset:
    """e-HPR setting of one detector in the paper: radius ``R`` and viewpoint ``(0, 0, z)``.

    Attributes:
        radius: HPR radius ``R``, metres.
        viewpoint_z: height of the viewpoint above the sensor origin, metres.
    """

    radius: float
    viewpoint_z: float


HPR_PRESETS: dict[str, HPRPreset] = {
    "second": HPRPreset(radius=300000.0, viewpoint_z=2.0),
    "pointrcnn": HPRPreset(radius=300000.0, viewpoint_z=1.0),
    "pv_rcnn": HPRPreset(radius=100000.0, viewpoint_z=0.0),
    "pv_rcnn_plusplus": HPRPreset(radius=100000.0, viewpoint_z=0.0),
}

HPR_METHODS: tuple[str, ...] = ("auto", "local", "sectors", "reference")
AUTO_REFERENCE_MAX = 2000  # "auto" runs one Qhull hull up to this many points
# "auto" runs one hull when more points than this, on average, share a point's cell of the
# per-point test's grid (cells about a first neighbourhood wide): that test's time grows with
# the points per neighbourhood, a hull's does not. LiDAR frames (KITTI sample, e-HPR presets)
# give 2-6; 30,000 points on a 0.1 m sphere 10 m away with R = 100 give 30,000.
AUTO_CROWDED = 128
HULL_KERNEL_MAX = 20000  # "reference" tries drcpo.hull's certified hull up to this many points
_KERNEL_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))
MAX_RADIUS = 1e150  # keeps 2R (and R squared terms) finite in float64
# Above this R / (max range), the flipped coordinates keep too few bits of the ranges for Qhull.
_QHULL_RATIO_MAX = 1e7
# "auto" prefers one hull when the median point's first neighbourhood is wider than this (rad).
_LOCAL_MAX_CONE = 0.1
# Points this close to the viewpoint, relative to (1 + max range), count as "at the viewpoint".
_AT_VIEWPOINT = 1e-9
# Parallel work only pays above this many points (measured on 2 cores: e-HPR of a KITTI
# frame with a few thousand queried points runs about 10% faster on two threads).
_PARALLEL_MIN = 2000

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


# ----------------------------------------------------------------------------------------------
# Public API
# ----------------------------------------------------------------------------------------------
def hidden_point_removal(
    points: np.ndarray,
    viewpoint: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    radius: float = 100000.0,
    *,
    method: str = "auto",
    query: np.ndarray | None = None,
    workers: int | None = None,
) -> np.ndarray:
    """Katz et al.'s hidden point removal: which points are visible from ``viewpoint``.

    Args:
        points: ``(N, 3 + C)`` x, y, z (metres) then any features (ignored); any float dtype,
            computed in float64.
        viewpoint: ``(3,)`` viewpoint (metres), the origin of the spherical flip.
        radius: ``R`` of the spherical flip (metres), Open3D's ``radius`` argument.
        method: ``"auto"``, ``"local"``, ``"sectors"`` or ``"reference"`` (module docstring).
        query: optional ``bool (N,)`` mask or integer indices of the points whose visibility is
            wanted; the others are still potential occluders but are reported ``True`` without
            being decided. ``None``: all points.
        workers: threads to use (``None``: up to two of the CPUs this process may use; ``1``
            inside data-loader workers that already share the cores).

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
    workers = _check_workers(workers)
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
    elif chosen == "sectors":
        decided = _sectors(setup, wanted_hull, workers)
    elif method == "auto":
        decided = _auto_local(setup, wanted_hull, workers)
    else:
        decided = _local(setup, wanted_hull, workers)
    visible[setup.index] = decided | ~wanted_hull
    return visible


def hidden_by_insertion(
    points: np.ndarray,
    inserted: np.ndarray,
    behind: np.ndarray | Callable[[np.ndarray], np.ndarray],
    viewpoint: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    radius: float = 100000.0,
    *,
    method: str = "auto",
    workers: int | None = None,
) -> np.ndarray:
    """Points that inserted objects remove from a frame (e-HPR's ``inserted`` scope).

    An inserted point goes when it is hidden; a point of ``behind`` (original points that the
    inserted objects may occlude) goes when it is hidden in the whole set but visible once the
    inserted points are taken out, so HPR's own verdicts on the original frame never delete a
    point. The same as :func:`hidden_point_removal` with ``query=inserted | behind``, then on
    ``points[~inserted]`` for the hidden points of ``behind``. With the ``"local"`` method this is
    :meth:`FrameGrid.hidden_by_insertion`: both sets share one sorted grid, and each point
    of ``behind`` is decided in one go, without the inserted points first.

    Args:
        points: ``(N, 3 + C)`` the frame after insertion (metres).
        inserted: ``bool (N,)`` the inserted points.
        behind: ``bool (N,)`` original points whose removal is to be decided (points of
            ``inserted`` are ignored here), or a function that returns them given the
            inserted points to remove (``bool (N,)``), which are decided first.
        viewpoint, radius, method, workers: as in :func:`hidden_point_removal`.

    Returns:
        ``bool (N,)``: points to remove.
    """
    xyz = _check_points(points)
    center = _check_viewpoint(viewpoint)
    radius = _check_radius(radius)
    if method not in HPR_METHODS:
        raise ConfigError(f"method must be one of {', '.join(HPR_METHODS)}, got {method!r}")
    n = len(xyz)
    inserted = _check_query(inserted, n)
    workers = _check_workers(workers)
    removed = np.zeros(n, dtype=bool)
    if not callable(behind):
        behind = _check_query(behind, n) & ~inserted
        if not (inserted | behind).any():
            return removed
    setup = _Setup.build(xyz, center, radius)
    if setup.size == 0:
        return removed
    chosen = _resolve_method(method, setup)
    if chosen == "local" and not (method == "auto" and _crowded(_local_grid(setup).starts, setup)):
        original = np.flatnonzero(~inserted)

        def behind_frame(removed_inserted: np.ndarray) -> np.ndarray:
            if not callable(behind):
                return _check_query(behind, n)[original]
            found = np.zeros(n, dtype=bool)
            found[inserted] = removed_inserted
            return _check_query(behind(found), n)[original]

        grid = FrameGrid.build(xyz[original], center, radius, spare=n - len(original))
        found = grid.hidden_by_insertion(
            np.zeros(len(original), dtype=bool),
            xyz[inserted],
            behind_frame,
            method="local",
            workers=workers,
        )
        if found is not None:
            removed[original], removed[inserted] = found
            return removed

    def hidden(query: np.ndarray) -> np.ndarray:
        if not query.any():
            return np.zeros(n, dtype=bool)
        return query & ~hidden_point_removal(
            xyz, center, radius, method=method, query=query, workers=workers
        )

    if callable(behind):
        removed = hidden(inserted)
        behind = _check_query(behind(removed.copy()), n) & ~inserted
        removed |= hidden(behind)
    else:
        removed = hidden(inserted | behind)
    suspects = behind & removed
    if suspects.any():
        original = np.flatnonzero(~inserted)
        before = np.ones(n, dtype=bool)
        before[original] = hidden_point_removal(
            xyz[original], center, radius, method=method, query=suspects[original], workers=workers
        )
        # Original points hidden even without the inserted objects stay.
        removed[suspects & ~before] = False
    return removed


def self_occlusion(
    points: np.ndarray,
    box: np.ndarray,
    radius_factor: float = 200.0,
    *,
    viewpoint: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    method: str = "auto",
    workers: int | None = 1,
) -> np.ndarray:
    """s-HPR: the paper's self-occlusion of one placed object, seen from the sensor.

    Args:
        points: ``(N, 3 + C)`` the object's points in the LiDAR frame (metres).
        box: ``(7,)`` (or ``(1, 7)``) the object's box; ``R = diagonal * radius_factor``.
        radius_factor: the paper uses 200.
        viewpoint: ``(3,)`` the sensor position, metres (the origin in the paper).
        method, workers: as in :func:`hidden_point_removal` (one thread by default: objects
            are small).

    Returns:
        ``bool (N,)``: points kept (visible).
    """
    box = np.asarray(box, dtype=np.float64)
    if box.size != 7:
        raise DataError(f"self_occlusion: box must have 7 values, got shape {box.shape}")
    # geometry.box_diagonal's sum, in the same order, without its array overhead (per object)
    dx, dy, dz = box.reshape(7)[3:6].tolist()
    diagonal = math.sqrt(dx * dx + dy * dy + dz * dz)
    factor = _check_radius(radius_factor, "radius_factor")
    if not diagonal > 0.0:
        raise DataError(f"self_occlusion: the box has no extent (diagonal {diagonal})")
    return hidden_point_removal(
        points, viewpoint, diagonal * factor, method=method, workers=workers
    )


def self_occlusion_many(
    objects: Sequence[tuple[np.ndarray, np.ndarray]],
    radius_factor: float = 200.0,
    *,
    viewpoint: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    method: str = "auto",
    workers: int | None = None,
    pool: ThreadPoolExecutor | None = None,
) -> list[np.ndarray]:
    """:func:`self_occlusion` of several objects, spread over ``workers`` threads.

    The hulls (:mod:`drcpo.hull`'s numba kernel, or Qhull) release the GIL while they are
    built, so two objects' hulls can run at once. Each object's answer is exactly
    :func:`self_occlusion`'s, whichever thread computes it; the calling thread does part of the
    work.

    Args:
        objects: ``(points (N_i, 3 + C), box (7,))`` pairs, as :func:`self_occlusion` takes.
        radius_factor, viewpoint, method: as in :func:`self_occlusion`.
        workers: threads (``None``: up to two of the CPUs this process may use).
        pool: a running pool whose thread takes part when it is free (else, with
            ``workers > 1``, one is started for the call and shut down after it).

    Returns:
        ``bool (N_i,)`` visible masks, in the order of ``objects``.
    """
    workers = _check_workers(workers)
    # Largest first, so that the threads finish together; the order does not change answers.
    order = sorted(range(len(objects)), key=lambda k: -len(objects[k][0]))
    masks = _shared_chunks(
        lambda k: self_occlusion(
            *objects[k], radius_factor, viewpoint=viewpoint, method=method, workers=1
        ),
        order,
        pool if workers > 1 else None,
        start=workers > 1,
    )
    results: list[np.ndarray | None] = [None] * len(objects)
    for k, mask in zip(order, masks, strict=True):
        results[k] = mask
    return results  # type: ignore[return-value]


def external_occlusion(
    points: np.ndarray,
    preset: str = "pv_rcnn_plusplus",
    *,
    mode: str = "hpr",
    radius: float | None = None,
    viewpoint_z: float | None = None,
    focus: np.ndarray | None = None,
    focus_margin: float = float(np.deg2rad(2.0)),
    method: str = "auto",
    workers: int | None = None,
    range_image: dict | None = None,
) -> np.ndarray:
    """e-HPR: the paper's external occlusion of a whole frame (after insertion).

    Args:
        points: ``(N, 3 + C)`` the frame's points (metres).
        preset: detector whose ``(R, z)`` is used, a key of :data:`HPR_PRESETS`.
        mode: ``"hpr"`` (the paper) or ``"range_image"`` (:func:`range_image_occlusion`, not the
            paper's method); both look from the preset's viewpoint (or ``viewpoint_z``), as
            the DR.CPO pipeline does.
        radius, viewpoint_z: override the preset's ``R`` (metres) and viewpoint height (metres).
        focus: optional ``bool (N,)`` mask (or indices) of the points that matter, e.g. inserted
            ones. Only points in the azimuth directions of the focus points (see
            :func:`azimuth_focus`, ``focus_margin`` radians) are decided, exactly, against the
            whole frame; all others are reported visible.
        focus_margin: radians added on both sides of the focus points' azimuths.
        method, workers: as in :func:`hidden_point_removal`.
        range_image: keyword arguments for :func:`range_image_occlusion` in that mode.

    Returns:
        ``bool (N,)``: points kept (visible).
    """
    if preset not in HPR_PRESETS:
        raise ConfigError(f"unknown HPR preset {preset!r}; choose one of {', '.join(HPR_PRESETS)}")
    setting = HPR_PRESETS[preset]
    xyz = _check_points(points)
    query = None if focus is None else azimuth_focus(xyz, focus, focus_margin)
    height = setting.viewpoint_z if viewpoint_z is None else float(viewpoint_z)
    if mode == "range_image":
        visible = range_image_occlusion(xyz, (0.0, 0.0, height), **(range_image or {}))
        return visible if query is None else visible | ~query
    if mode != "hpr":
        raise ConfigError(f"external occlusion mode must be 'hpr' or 'range_image', got {mode!r}")
    r = setting.radius if radius is None else radius
    return hidden_point_removal(
        xyz, (0.0, 0.0, height), r, method=method, query=query, workers=workers
    )


def azimuth_focus(
    points: np.ndarray,
    focus: np.ndarray,
    margin: float = float(np.deg2rad(2.0)),
    *,
    bin_width: float = float(np.deg2rad(0.5)),
) -> np.ndarray:
    """``bool (N,)``: points in the azimuth directions (about the z axis) of the focus points.

    Azimuth is cut into bins of ``bin_width`` radians; a point is selected when its bin lies
    within ``margin`` radians (rounded up to whole bins) of a bin holding a focus point. Focus
    points themselves are always selected.

    Args:
        points: ``(N, 3 + C)`` points, metres.
        focus: ``bool (N,)`` mask or integer indices of the focus points.
        margin: radians of context on both sides.
        bin_width: radians per azimuth bin.
    """
    xyz = _check_points(points)
    chosen = _check_query(focus, len(xyz))
    if not chosen.any():
        return chosen
    if not (math.isfinite(margin) and margin >= 0 and math.isfinite(bin_width) and bin_width > 0):
        raise ConfigError(f"margin must be >= 0 and bin_width > 0, got {margin}, {bin_width}")
    bins = max(1, math.ceil(2 * math.pi / bin_width))
    azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
    index = np.floor((azimuth + np.pi) * (bins / (2 * np.pi))).astype(np.int64) % bins
    hit = np.zeros(bins, dtype=bool)
    hit[index[chosen]] = True
    reach = math.ceil(margin * bins / (2 * math.pi))
    if 2 * reach + 1 >= bins:
        return np.ones(len(xyz), dtype=bool)
    grown = hit.copy()
    for shift in range(1, reach + 1):
        grown |= np.roll(hit, shift) | np.roll(hit, -shift)
    return grown[index] | chosen


def range_image_occlusion(
    points: np.ndarray,
    viewpoint: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    *,
    azimuth_resolution: float = float(np.deg2rad(0.2)),
    elevation_resolution: float = float(np.deg2rad(0.4)),
    beam_elevations: np.ndarray | None = None,
    depth_tolerance: float = 0.2,
) -> np.ndarray:
    """Z-buffer occlusion: keep the nearest surface in each (azimuth, elevation) cell.

    This is *not* the paper's method (HPR); it is a lighter alternative that mimics a spinning
    LiDAR: points are binned by azimuth (``azimuth_resolution`` radians) and elevation (either
    regular cells of ``elevation_resolution`` radians or the nearest of the sensor's
    ``beam_elevations``), and a point is kept when its range is within ``depth_tolerance``
    metres of the nearest range in its cell.

    Args:
        points: ``(N, 3 + C)`` points, metres.
        viewpoint: ``(3,)`` sensor position, metres.
        azimuth_resolution: radians per azimuth cell.
        elevation_resolution: radians per elevation cell (ignored with ``beam_elevations``).
        beam_elevations: optional ``(B,)`` beam elevation angles in radians (any order).
        depth_tolerance: metres behind the nearest return that still count as the same surface.

    Returns:
        ``bool (N,)``: visible points. Points at the viewpoint are visible.
    """
    xyz = _check_points(points)
    center = _check_viewpoint(viewpoint)
    for name, value in (
        ("azimuth_resolution", azimuth_resolution),
        ("elevation_resolution", elevation_resolution),
    ):
        if not (math.isfinite(value) and 0 < value <= math.pi):
            raise ConfigError(f"{name} must be in (0, pi] radians, got {value}")
    if not (math.isfinite(depth_tolerance) and depth_tolerance >= 0):
        raise ConfigError(f"depth_tolerance must be >= 0 metres, got {depth_tolerance}")
    visible = np.ones(len(xyz), dtype=bool)
    if len(xyz) == 0:
        return visible
    rel = xyz - center
    rng = np.sqrt(np.einsum("ij,ij->i", rel, rel))
    valid = rng > 0
    if not valid.any():
        return visible
    rel, rng = rel[valid], rng[valid]
    azimuth = np.arctan2(rel[:, 1], rel[:, 0])
    elevation = np.arcsin(np.clip(rel[:, 2] / rng, -1.0, 1.0))
    n_azimuth = max(1, math.ceil(2 * math.pi / azimuth_resolution))
    column = np.floor((azimuth + np.pi) / azimuth_resolution).astype(np.int64) % n_azimuth
    row = _elevation_rows(elevation, elevation_resolution, beam_elevations)
    cell = row * n_azimuth + column
    _, inverse = np.unique(cell, return_inverse=True)
    nearest = np.full(int(inverse.max()) + 1, np.inf)
    np.minimum.at(nearest, inverse, rng)
    visible[valid] = rng <= nearest[inverse] + depth_tolerance
    return visible


def _elevation_rows(
    elevation: np.ndarray, resolution: float, beams: np.ndarray | None
) -> np.ndarray:
    if beams is None:
        return np.floor((elevation + np.pi / 2) / resolution).astype(np.int64)
    beams = np.sort(np.asarray(beams, dtype=np.float64).ravel())
    if beams.size == 0 or not np.isfinite(beams).all():
        raise ConfigError("beam_elevations must be a non-empty list of finite angles (radians)")
    middles = (beams[1:] + beams[:-1]) / 2
    return np.searchsorted(middles, elevation).astype(np.int64)


# ----------------------------------------------------------------------------------------------
# Validation
# ----------------------------------------------------------------------------------------------
def _check_points(points: np.ndarray) -> np.ndarray:
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] < 3:
        raise DataError(f"points must have shape (N, 3 + C), got {array.shape}")
    if not np.issubdtype(array.dtype, np.number) or np.issubdtype(array.dtype, np.complexfloating):
        raise DataError(f"points must be real numbers, got dtype {array.dtype}")
    xyz = np.ascontiguousarray(array[:, :3], dtype=np.float64)
    if not np.isfinite(xyz).all():
        bad = np.flatnonzero(~np.isfinite(xyz).all(axis=1))
        raise DataError(
            f"points hold NaN/inf coordinates in {len(bad)} rows (first: row {int(bad[0])})"
        )
    return xyz


def _check_viewpoint(viewpoint: Sequence[float] | np.ndarray) -> np.ndarray:
    try:
        center = np.asarray(viewpoint, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as error:
        raise DataError(f"viewpoint must be 3 numbers, got {viewpoint!r}") from error
    # math.isfinite on three floats: a tenth of np.isfinite's call overhead (once per object)
    if center.shape != (3,) or not all(map(math.isfinite, center.tolist())):
        raise DataError(f"viewpoint must be 3 finite numbers, got {viewpoint!r}")
    return center


def _check_radius(radius: float, name: str = "radius") -> float:
    try:
        value = float(radius)
    except (TypeError, ValueError) as error:
        raise ConfigError(f"{name} must be a number, got {radius!r}") from error
    if not (math.isfinite(value) and 0.0 < value <= MAX_RADIUS):
        raise ConfigError(f"{name} must be a finite number in (0, {MAX_RADIUS:g}], got {radius}")
    return value


def _check_query(query: np.ndarray | None, count: int) -> np.ndarray:
    if query is None:
        return np.ones(count, dtype=bool)
    array = np.asarray(query)
    if array.dtype == bool:
        if array.shape != (count,):
            raise DataError(f"query mask must have shape ({count},), got {array.shape}")
        return array
    if array.size and not np.issubdtype(array.dtype, np.integer):
        raise DataError(f"query must be a bool mask or integer indices, got dtype {array.dtype}")
    index = array.astype(np.int64).ravel()
    if index.size and (index.min() < -count or index.max() >= count):
        raise DataError(f"query indices out of range for {count} points")
    mask = np.zeros(count, dtype=bool)
    mask[index] = True
    return mask


def _check_workers(workers: int | None) -> int:
    if workers is None:
        try:
            available = len(os.sched_getaffinity(0))
        except AttributeError:  # not on Linux
            available = os.cpu_count() or 1
        return max(1, min(2, available))
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ConfigError(f"workers must be a positive integer or None, got {workers!r}")
    return int(workers)


# ----------------------------------------------------------------------------------------------
# Shared set-up: the points that take part in the hull, as rays and ranges
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Setup:
    """The flip's inputs for the points that are not at the viewpoint.

    Attributes:
        index: ``(M,)`` rows of the caller's points that take part.
        rel: ``(M, 3)`` coordinates relative to the viewpoint, metres.
        ranges: ``(M,)`` ``|rel|``, metres.
        rays: ``(M, 3)`` unit vectors ``rel / ranges``.
        radius: ``R``, metres.
    """

    index: np.ndarray
    rel: np.ndarray
    ranges: np.ndarray
    rays: np.ndarray
    radius: float

    @classmethod
    def build(cls, xyz: np.ndarray, center: np.ndarray, radius: float) -> _Setup:
        rel = xyz - center
        ranges = _norms(rel)
        if not np.isfinite(ranges).all():
            row = int(np.flatnonzero(~np.isfinite(ranges))[0])
            raise DataError(f"points: row {row} is too far from the viewpoint for float64")
        # A hypot-free norm underflows for coordinates near 1e-160; those points sit at the
        # viewpoint for any practical purpose and fall under the same rule.
        away = ranges > _AT_VIEWPOINT * (1.0 + float(ranges.max(initial=0.0)))
        if not away.all():
            rel, ranges = rel[away], ranges[away]
        return cls(np.flatnonzero(away), rel, ranges, rel / ranges[:, None], radius)

    @property
    def size(self) -> int:
        return len(self.ranges)

    @property
    def local_ok(self) -> bool:
        """The ray-and-range formulation needs every flipped range ``2R - r`` positive."""
        return 2.0 * self.radius > float(self.ranges.max()) * (1.0 + 1e-12)

    def distinct(self) -> tuple[_Setup, np.ndarray]:
        """The set-up of the distinct points, and ``(M,)`` the position of each point's copy in
        it (Qhull keeps one of several equal points; drcpo gives every copy its verdict)."""
        rel = self.rel
        # Equal points have equal x: when no two x are equal (the usual case) there is no
        # duplicate, and one single-key sort is much cheaper than the three-key one.
        by_x = np.argsort(rel[:, 0])
        sorted_x = rel[by_x, 0]
        tie = sorted_x[1:] == sorted_x[:-1]
        if not tie.any():
            return self, np.arange(self.size)
        # Equal x is common (float32 inputs), a copy rare: look for one among the ties only.
        tied = by_x[np.flatnonzero(np.concatenate([tie, [False]]) | np.concatenate([[False], tie]))]
        candidates = rel.take(tied, axis=0)
        candidates = candidates[np.lexsort((candidates[:, 2], candidates[:, 1], candidates[:, 0]))]
        if not (candidates[1:] == candidates[:-1]).all(axis=1).any():
            return self, np.arange(self.size)
        order = np.lexsort((rel[:, 2], rel[:, 1], rel[:, 0]))
        ordered = rel[order]
        repeat = (ordered[1:] == ordered[:-1]).all(axis=1)
        if not repeat.any():
            return self, np.arange(self.size)
        group = np.concatenate([[0], np.cumsum(~repeat)])
        first = order[np.concatenate([[True], ~repeat])]
        inverse = np.empty(self.size, dtype=np.int64)
        inverse[order] = group
        subset = _Setup(
            self.index[first], self.rel[first], self.ranges[first], self.rays[first], self.radius
        )
        return subset, inverse

    def flipped(self) -> np.ndarray:
        """``(M, 3)`` Open3D's spherical flip ``p + 2 (R - |p|) p / |p|``."""
        scale = 2.0 * (self.radius - self.ranges) / self.ranges
        return self.rel + self.rel * scale[:, None]


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


def _local_grid(setup: _Setup) -> _Grid:
    """The grid the per-point test sorts the set-up's points into (as :class:`_LocalState`)."""
    r_min = float(setup.ranges.min())
    return _build_grid(setup.rays, _first_cones(setup.ranges, r_min, 2.0 * setup.radius - r_min))


def _auto_local(setup: _Setup, wanted: np.ndarray, workers: int) -> np.ndarray:
    """``"auto"``'s verdicts where :func:`_resolve_method` chose ``"local"``: the per-point test,
    unless the points crowd its neighbourhoods; then one hull, or (``R`` too large for one)
    the per-point test on the distinct points (copies share a verdict and do not constrain
    each other's planes, so the answer is the same)."""
    state = _LocalState.build(setup)
    if not _crowded(state.starts, setup):
        return state.visible(wanted, workers)
    if _precise(setup):
        return _reference(setup, wanted)
    return _distinct_local(setup, wanted, workers)


def _distinct_local(setup: _Setup, wanted: np.ndarray, workers: int) -> np.ndarray:
    """:func:`_local`'s verdicts, computed once per distinct point."""
    distinct, inverse = setup.distinct()
    if distinct is setup:
        return _local(setup, wanted, workers)
    wanted_distinct = np.zeros(distinct.size, dtype=bool)
    wanted_distinct[inverse[wanted]] = True
    return _local(distinct, wanted_distinct, workers)[inverse] & wanted


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
    """The reference answer from :mod:`drcpo.hull`'s certified hull, straight from float32 or
    float64 ``(N, 3 + C)`` points, or ``None`` where it gives up or the input is one it leaves
    to the general path (which also validates it): non-finite values, points at the viewpoint,
    ``R`` below half a range, and, for ``"auto"``, the inputs it does not send to one hull."""
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


def _hull_vertices(flipped: np.ndarray) -> np.ndarray | None:
    """``bool (K,)``: flipped points that are vertices of hull(flipped + origin); ``None`` when
    Qhull cannot build a 3-D hull (too few points, flat or precision failure)."""
    if len(flipped) < 3:
        return None
    cloud = np.vstack([flipped, np.zeros((1, 3))])
    try:
        hull = ConvexHull(cloud)
    except (QhullError, ValueError):
        return None
    vertex = np.zeros(len(cloud), dtype=bool)
    vertex[hull.vertices] = True
    return vertex[:-1]


def _degenerate_fallback(setup: _Setup, wanted: np.ndarray) -> np.ndarray:
    """Verdicts when Qhull cannot build the hull: "local" (once per distinct point: many
    copies of one point would make it quadratic), else joggled Qhull, else all."""
    if setup.local_ok:
        return _distinct_local(setup, wanted, 1)
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


# ----------------------------------------------------------------------------------------------
# Local: per-point supporting-plane test against angular neighbours (numba)
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Grid:
    """Points sorted into (elevation, azimuth) cells of ``size`` radians, for cone queries."""

    order: np.ndarray  # (M,) set-up index of the k-th sorted point
    starts: np.ndarray  # (cells + 1,) first sorted position of each cell
    elevation: np.ndarray  # (M,) sorted, radians
    azimuth: np.ndarray  # (M,) sorted, radians
    origin: float  # elevation of the first row's lower edge
    size: float  # row height, radians
    rows: int
    columns: int


def _build_grid(rays: np.ndarray, cone: np.ndarray) -> _Grid:
    elevation = np.arcsin(np.clip(rays[:, 2], -1.0, 1.0))
    azimuth = np.arctan2(rays[:, 1], rays[:, 0])
    low, high = float(elevation.min()), float(elevation.max())
    # Cells about as wide as a typical first neighbourhood, but never many more cells than
    # points (sparse sets) nor so wide that a query scans most of the set.
    area = max(high - low, 1e-3) * 2 * math.pi
    size = float(np.clip(np.median(cone), math.sqrt(area / max(len(rays), 1)), 0.25))
    rows = int((high - low) / size) + 1
    columns = max(1, int(2 * math.pi / size))
    row = np.minimum(((elevation - low) / size).astype(np.int64), rows - 1)
    column = ((azimuth + np.pi) * (columns / (2 * math.pi))).astype(np.int64) % columns
    cell = row * columns + column
    counts = np.bincount(cell, minlength=rows * columns)
    starts = np.zeros(rows * columns + 1, dtype=np.int64)
    np.cumsum(counts, out=starts[1:])
    order = _counting_sort(cell, starts)
    return _Grid(order, starts, elevation[order], azimuth[order], low, size, rows, columns)


@nb.njit(cache=True, nogil=True)
def _counting_sort(cell, starts):  # pragma: no cover - numba
    # The stable argsort of the cell numbers in linear time (cells are few and known).
    order = np.empty(len(cell), dtype=np.int64)
    position = starts[:-1].copy()
    for i in range(len(cell)):
        order[position[cell[i]]] = i
        position[cell[i]] += 1
    return order


@nb.njit(cache=True, nogil=True)
def _counting_sort_into(cell, starts, offset):  # pragma: no cover - numba
    # _counting_sort that also counts the cells, writing their first sorted positions plus
    # ``offset`` into ``starts`` (in place: no scratch array as large as the grid).
    order = np.empty(len(cell), dtype=np.int64)
    _counting_sort_to(cell, starts, offset, order)
    return order


@nb.njit(cache=True, nogil=True)
def _counting_sort_to(cell, starts, offset, order):  # pragma: no cover - numba
    # _counting_sort_into, writing the order into ``order``.
    cells = starts.shape[0] - 1
    starts[:] = 0
    for c in cell:
        starts[c + 1] += 1
    starts[0] = offset
    for c in range(cells):
        starts[c + 1] += starts[c]
    for i in range(len(cell) - 1, -1, -1):  # backwards from each cell's end: stable
        c = cell[i]
        starts[c + 1] -= 1
        order[starts[c + 1] - offset] = i
    for c in range(cells):  # starts[c + 1] now holds cell c's first position
        starts[c] = starts[c + 1]
    starts[cells] = offset + len(cell)


@nb.njit(cache=True, nogil=True)
def _directions(points, center, rel, azimuth, elevation):  # pragma: no cover - numba
    # Per point (x, y, z in float64) relative to ``center``, into the given arrays: its
    # offset, ``arctan2(y, x)`` and ``arctan2(z, sqrt(x x + y y))`` (libm's atan2; numpy's
    # vectorised arctan2 may differ in the last bit on some CPUs). Returns the first row
    # holding a NaN or infinite coordinate (-1: none).
    bad = -1
    for i in range(points.shape[0]):
        x = np.float64(points[i, 0]) - center[0]
        y = np.float64(points[i, 1]) - center[1]
        z = np.float64(points[i, 2]) - center[2]
        if bad < 0 and not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            bad = i
        rel[i, 0], rel[i, 1], rel[i, 2] = x, y, z
        azimuth[i] = math.atan2(y, x)
        elevation[i] = math.atan2(z, math.sqrt(x * x + y * y))
    return bad


@nb.njit(cache=True, nogil=True)
def _norms(rel):  # pragma: no cover - numba
    out = np.empty(rel.shape[0])
    _norms_to(rel, out)
    return out


@nb.njit(cache=True, nogil=True)
def _norms_to(rel, out):  # pragma: no cover - numba
    # |rel| per row as (x x + y y) + z z: the ranges of _Setup.build and FrameGrid alike.
    for i in range(rel.shape[0]):
        x, y, z = rel[i, 0], rel[i, 1], rel[i, 2]
        out[i] = math.sqrt(x * x + y * y + z * z)


class GridMemory:
    """Memory a :class:`FrameGrid` is built in, kept for the next grid: fresh memory costs a
    page fault per 4 KiB on first use, which made a frame's grid built on a second thread
    about twice as slow. A grid built in it is valid until the next one is."""

    def __init__(self) -> None:
        self.floats = np.empty(0)
        self.ints = np.empty(0, dtype=np.int64)

    def reserve(self, count: int, spare: int) -> tuple[np.ndarray, np.ndarray]:
        """Buffers for a grid of ``count`` points with ``spare`` rows (the int64 one may
        still be too short for the cells; the build then replaces it)."""
        floats = 6 * count + 10 * (count + spare)
        ints = 7 * count + 2
        if len(self.floats) < floats:
            self.floats = np.empty(floats + floats // 4)
        if len(self.ints) < ints:
            self.ints = np.empty(ints + ints // 4, dtype=np.int64)
        return self.floats, self.ints


_THREAD_MEMORY = threading.local()


def thread_grid_memory() -> GridMemory:
    """The calling thread's :class:`GridMemory` (one grid at a time per thread)."""
    memory = getattr(_THREAD_MEMORY, "grid", None)
    if memory is None:
        memory = _THREAD_MEMORY.grid = GridMemory()
    return memory


@nb.njit(cache=True, nogil=True)
def _build_frame_grid(
    points, center, radius, spare, row_height, column_width, floats, ints
):  # pragma: no cover
    # FrameGrid's arrays in one pass over its steps: directions and ranges, the cell geometry
    # (cells about a typical first neighbourhood wide, never smaller than an even share of the
    # covered directions, at most 0.25 rad), the points sorted by cell and by range within a
    # cell, and the sorted copies with ``spare`` zeroed rows after them, all in ``floats`` and
    # ``ints`` (GridMemory.reserve's; ``ints`` is replaced when too short for the cells).
    # Returns the first non-finite row and the first row too far for float64 (-1: none), the
    # smallest and largest range, the geometry (origin, row height, rows, columns), then the
    # arrays and the int64 buffer used.
    n = points.shape[0]
    total = n + spare
    rel = floats[: 3 * n].reshape((n, 3))
    azimuth = floats[3 * n : 4 * n]
    elevation = floats[4 * n : 5 * n]
    ranges = floats[5 * n : 6 * n]
    base = 6 * n
    out_rel = floats[base : base + 3 * total].reshape((total, 3))
    out_rays = floats[base + 3 * total : base + 6 * total].reshape((total, 3))
    out_ranges = floats[base + 6 * total : base + 7 * total]
    out_rho = floats[base + 7 * total : base + 8 * total]
    out_elevation = floats[base + 8 * total : base + 9 * total]
    out_azimuth = floats[base + 9 * total : base + 10 * total]
    bad = _directions(points, center, rel, azimuth, elevation)
    _norms_to(rel, ranges)
    far = -1
    r_min, r_max = np.inf, 0.0
    for i in range(n):
        r = ranges[i]
        if not math.isfinite(r):
            if far < 0 and bad < 0:
                far = i
            continue
        r_min, r_max = min(r_min, r), max(r_max, r)
    origin, height, rows, columns = 0.0, 1.0, 1, 1
    if n and bad < 0 and far < 0:
        low, high = elevation.min(), elevation.max()
        size = math.sqrt(max(high - low, 1e-3) * 2 * math.pi / n)
        if 2.0 * radius > r_max * (1.0 + 1e-12):
            rho_max = 2.0 * radius - r_min
            typical = np.median(ranges[:: max(1, n // 4096)])  # a sample is enough here
            cone = min(max((typical - r_min) / rho_max, 0.0), 2.0) / 2.0
            size = max(size, 2.0 * math.asin(math.sqrt(cone)))
        size = min(size, 0.25)
        origin, height = low, size * row_height
        rows = int((high - low) / height) + 1
        columns = max(1, int(2 * math.pi / (size * column_width)))
    cells_count = rows * columns + 1
    if ints.shape[0] < 3 * n + 2 * cells_count:
        ints = np.empty(3 * n + 2 * cells_count + n, dtype=np.int64)
    cells = ints[:n]
    position = ints[n : 2 * n]
    order = ints[2 * n : 3 * n]
    starts = ints[3 * n : 3 * n + 2 * cells_count].reshape((2, cells_count))
    starts[:] = 0
    if bad < 0 and far < 0:
        _cell_numbers(elevation, azimuth, origin, height, rows, columns, cells)
        _counting_sort_to(cells, starts[0], 0, order)
        _sort_cells(order, ranges, starts[0], 0)
        _scatter_sorted(
            order,
            rel,
            ranges,
            elevation,
            azimuth,
            2.0 * radius,
            out_rel,
            out_ranges,
            out_rho,
            out_rays,
            out_elevation,
            out_azimuth,
            position,
        )
    else:
        order = order[:0]
    return (
        bad,
        far,
        r_min,
        r_max,
        origin,
        height,
        rows,
        columns,
        starts,
        order,
        out_rel,
        out_ranges,
        out_rho,
        out_rays,
        out_elevation,
        out_azimuth,
        position,
        ints,
    )


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _scatter_sorted(
    order,
    rel,
    ranges,
    elevation,
    azimuth,
    diameter,
    out_rel,
    out_ranges,
    out_rho,
    out_rays,
    out_elevation,
    out_azimuth,
    position,
):  # pragma: no cover - numba
    # FrameGrid's sorted copies in one pass (rays rel / range: NaN at the viewpoint, as numpy
    # would give), and each point's sorted position; the rows after the frame's are zeroed.
    for k in range(order.shape[0]):
        i = order[k]
        r = ranges[i]
        for c in range(3):
            out_rel[k, c] = rel[i, c]
            out_rays[k, c] = rel[i, c] / r
        out_ranges[k] = r
        out_rho[k] = diameter - r
        out_elevation[k] = elevation[i]
        out_azimuth[k] = azimuth[i]
        position[i] = k
    for k in range(order.shape[0], out_ranges.shape[0]):
        for c in range(3):
            out_rel[k, c] = 0.0
            out_rays[k, c] = 0.0
        out_ranges[k] = out_rho[k] = out_elevation[k] = out_azimuth[k] = 0.0


@nb.njit(cache=True, nogil=True)
def _cell_numbers(elevation, azimuth, origin, height, rows, columns, out):  # pragma: no cover
    # FrameGrid's cell of each direction: row floor((elevation - origin) / height) clamped to
    # the rows, column floor((azimuth + pi) * columns / 2 pi) modulo the columns.
    per_radian = columns / (2 * math.pi)
    for i in range(elevation.shape[0]):
        row = min(max(math.floor((elevation[i] - origin) / height), 0), rows - 1)
        out[i] = row * columns + int((azimuth[i] + math.pi) * per_radian) % columns


@nb.njit(cache=True, nogil=True)
def _sort_cells(order, keys, starts, offset):  # pragma: no cover - numba
    # Each cell's run of ``order`` (positions ``starts`` minus ``offset``) sorted by ``keys``;
    # cells are small, so an insertion sort, except for the odd crowded one.
    for c in range(starts.shape[0] - 1):
        lo, hi = starts[c] - offset, starts[c + 1] - offset
        if hi - lo > 64:
            run = order[lo:hi].copy()
            order[lo:hi] = run[np.argsort(keys[run], kind="mergesort")]
            continue
        for a in range(lo + 1, hi):
            item = order[a]
            key = keys[item]
            b = a - 1
            while b >= lo and keys[order[b]] > key:
                order[b + 1] = order[b]
                b -= 1
            order[b + 1] = item


def _local(setup: _Setup, wanted: np.ndarray, workers: int) -> np.ndarray:
    """Visible flags ``(M,)`` (``False`` where not wanted) by the per-point plane test."""
    return _LocalState.build(setup).visible(wanted, workers)


def _first_cones(ranges: np.ndarray, r_min: float, rho_max: float) -> np.ndarray:
    """Radius (radians) of the neighbourhood that can cross the plane normal to the ray of a
    point at each of ``ranges`` (module doc), for any set whose ranges are at least ``r_min``
    (a lower ``r_min`` only widens the cones). In place: no temporary per step."""
    cone = np.subtract(ranges, r_min)
    cone /= rho_max
    np.clip(cone, 0, 2, out=cone)
    cone /= 2.0
    np.sqrt(cone, out=cone)
    np.arcsin(cone, out=cone)
    cone *= 2.0
    return cone


# The kernels' view of a point set, ``scene``: sorted rays, rel, ranges, flipped ranges,
# elevation, azimuth, ``starts`` (one row of cell starts per member set: the set itself, or the
# frame's points then inserted ones) and ``absent`` (points to skip; empty: none), then the
# grid geometry (origin, row height, rows, columns).
_NONE_ABSENT = np.zeros(0, dtype=bool)
_ORIGINALS, _INSERTED, _BOTH = 1, 2, 3  # member sets a gather looks at (bit per starts row)
# With this bit, a gather stops as soon as its points show that no plane fits (returns _NO_PLANE).
_CERTIFY = 4
_NO_PLANE = -2


class _LocalState:
    """The per-point test's inputs: the points sorted into the grid, as the kernels take them.

    Attributes:
        setup: the set-up.
        order: ``(M,)`` set-up index of each sorted position.
        first_cone: ``(M,)`` sorted first cones, radians.
        scene: the kernels' view of the sorted points (see ``_NONE_ABSENT``).
        bounds: ``(r_min, rho_max)``.
    """

    def __init__(
        self, setup: _Setup, order: np.ndarray, first_cone: np.ndarray, scene: tuple, bounds
    ) -> None:
        self.setup = setup
        self.order = order
        self.first_cone = first_cone
        self.scene = scene
        self.bounds = bounds

    @property
    def size(self) -> int:
        return len(self.order)

    @property
    def starts(self) -> np.ndarray:
        """``(cells + 1,)`` first sorted position of each grid cell."""
        return self.scene[6][0]

    @classmethod
    def build(cls, setup: _Setup) -> _LocalState:
        ranges, radius = setup.ranges, setup.radius
        r_min = float(ranges.min())
        rho_max = 2.0 * radius - r_min
        first_cone = _first_cones(ranges, r_min, rho_max)
        grid = _build_grid(setup.rays, first_cone)
        order = grid.order
        sorted_ranges = np.ascontiguousarray(ranges[order])
        scene = (
            setup.rays.take(order, axis=0),  # take: much faster than fancy indexing of rows
            setup.rel.take(order, axis=0),
            sorted_ranges,
            2.0 * radius - sorted_ranges,
            grid.elevation,
            grid.azimuth,
            grid.starts[None],
            _NONE_ABSENT,
            grid.origin,
            grid.size,
            grid.rows,
            grid.columns,
        )
        return cls(setup, order, first_cone[order], scene, (r_min, rho_max))

    def visible(self, wanted: np.ndarray, workers: int) -> np.ndarray:
        """Visible flags ``(M,)`` of the set-up's points (``False`` where not wanted)."""
        order, scene, cones = self.order, self.scene, self.first_cone
        todo = np.flatnonzero(wanted[order])
        parts = workers if len(todo) >= _PARALLEL_MIN else 1
        settled = np.concatenate(_in_threads(lambda c: _radial_pass(c, cones, *scene), todo, parts))
        pending = todo[~settled]
        visible_sorted = np.zeros(self.size, dtype=bool)
        visible_sorted[todo[settled]] = True
        if len(pending):
            parts = workers if len(pending) >= _PARALLEL_MIN // 8 else 1
            state = np.concatenate(
                _in_threads(
                    lambda c: _classify(c, cones, *scene, *self.bounds, _BRUTE_BUDGET),
                    pending,
                    parts,
                )
            )
            unresolved = state == _STATE_UNRESOLVED
            if unresolved.any():
                state[unresolved] = _resolve_unresolved(pending[unresolved], self)
            visible_sorted[pending] = state == _STATE_VISIBLE
        visible = np.zeros(self.size, dtype=bool)
        visible[order] = visible_sorted
        return visible


def _in_threads(kernel, items: np.ndarray, parts: int) -> list[np.ndarray]:
    """``kernel`` over ``parts`` contiguous chunks of ``items``, on that many threads (the
    kernels release the GIL); the pool lives only for this call, so nothing leaks into a fork."""
    chunks = np.array_split(items, max(1, parts))
    if len(chunks) == 1:
        return [kernel(chunks[0])]
    # The calling thread takes the first chunk: one thread fewer to start (starting one costs
    # milliseconds when the other core is busy).
    with ThreadPoolExecutor(max_workers=len(chunks) - 1) as pool:
        others = [pool.submit(kernel, chunk) for chunk in chunks[1:]]
        return [kernel(chunks[0])] + [future.result() for future in others]


def _shared_chunks(
    kernel, parts: Sequence[Any], helper: ThreadPoolExecutor | None, *, start: bool = False
) -> list[Any]:
    """``kernel`` over each of ``parts``, results in order; with ``helper`` (a running pool)
    one of its threads and the calling thread claim parts until none is left, so the work
    splits evenly whatever each part costs and however busy the other core is. A helper still
    busy with earlier work when the calling thread runs out is not waited for. ``start``:
    without ``helper``, start a one-thread pool for the call."""
    results: list[Any] = [None] * len(parts)
    claim = iter(range(len(parts)))  # next() on a range iterator is atomic under the GIL

    def drain() -> None:
        for k in claim:
            results[k] = kernel(parts[k])

    if len(parts) < 2 or (helper is None and not start):
        drain()
        return results
    own = helper is None
    pool = ThreadPoolExecutor(max_workers=1) if own else helper
    try:
        other = pool.submit(drain)
        drain()
        if not other.cancel():  # started: it holds at most the parts it claimed
            other.result()
    finally:
        if own:
            pool.shutdown()
    return results


def _resolve_unresolved(unresolved: np.ndarray, state: _LocalState) -> np.ndarray:
    """States of the (sorted) points the neighbourhood search gave up on: a full scan each when
    they are few, else (and for any the scan cannot settle) one reference hull."""
    verdicts = np.full(len(unresolved), _STATE_UNRESOLVED, dtype=np.int64)
    if len(unresolved) <= 4 * _BRUTE_BUDGET:
        verdicts = _classify(
            unresolved, state.first_cone, *state.scene, *state.bounds, len(unresolved) + 1
        )
    left = verdicts == _STATE_UNRESOLVED
    if left.any():
        distinct, inverse = state.setup.distinct()
        vertex = _hull_vertices(distinct.flipped())
        if vertex is None:  # cannot happen for a set the scan failed on; keep the points
            verdicts[left] = _STATE_VISIBLE
        else:
            hull_says = vertex[inverse][state.order[unresolved[left]]]
            verdicts[left] = np.where(hull_says, _STATE_VISIBLE, _STATE_HIDDEN)
    return verdicts


# Grid cells of a FrameGrid, relative to the typical first neighbourhood (half as wide as the
# generic grid's: its scans read whole runs of cells; finer ones gain nothing on KITTI frames).
_FRAME_ROW_HEIGHT = 1.0
_FRAME_COLUMN_WIDTH = 0.5
# Work items per call, claimed by the threads as they go: small enough that a thread the
# system stalls for a while holds up little work.
_FRAME_CHUNKS = 32
_FRAME_PARALLEL_MIN = 256  # queries worth a second thread (one already running: cheap)


class FrameGrid:
    """A frame's points seen from the e-HPR viewpoint, sorted once into the per-point test's
    grid, for e-HPR's ``inserted`` scope on that frame with any inserted objects.

    It depends only on the frame, so the DR.CPO pipeline builds it (on a second thread) while
    objects are placed and constructed. :meth:`hidden_by_insertion` then adds the inserted
    points to its cells (no re-sorting of the frame) and skips the frame points they displace;
    :meth:`in_windows` selects points by direction cell by cell.

    Directions are ``arctan2(y, x)`` (azimuth) and ``arctan2(z, sqrt(x x + y y))`` (elevation)
    of a point relative to the viewpoint, by libm (as :func:`drcpo.pipeline.view_windows`
    computes them).

    Attributes:
        center: ``(3,)`` the viewpoint, metres.
        radius: ``R``, metres.
        size: number of frame points.
    """

    def __init__(
        self,
        points: np.ndarray,
        center: np.ndarray,
        radius: float,
        spare: int,
        memory: GridMemory | None = None,
    ) -> None:
        self._points = points
        self.center = center
        self.radius = radius
        memory = memory if memory is not None else GridMemory()
        # One compiled call: the GIL is taken twice, however busy the other threads are.
        built = _build_frame_grid(
            points,
            center,
            radius,
            spare,
            _FRAME_ROW_HEIGHT,
            _FRAME_COLUMN_WIDTH,
            *memory.reserve(len(points), spare),
        )
        memory.ints = built[-1]
        built = built[:-1]
        bad, far, self._r_min, self._r_max, *geometry = built[:8]
        if bad >= 0:
            _check_points(points)  # raises, naming the rows
        if far >= 0:
            raise DataError(f"points: row {far} is too far from the viewpoint for float64")
        self._geometry = (geometry[0], geometry[1], int(geometry[2]), int(geometry[3]))
        # Sorted copies, with room for the inserted points after the frame's.
        (
            self._starts,
            self._order,
            self._rel,
            self._ranges,
            self._rho,
            self._rays,
            self._elevation,
            self._azimuth,
            self._position,
        ) = built[8:]

    @classmethod
    def build(
        cls,
        points: np.ndarray,
        viewpoint: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
        radius: float = 100000.0,
        *,
        spare: int = 4096,
        memory: GridMemory | None = None,
    ) -> FrameGrid:
        """The grid of ``points`` ``(N, 3 + C)`` (metres; not copied: leave them unchanged)
        seen from ``viewpoint`` ``(3,)`` with e-HPR radius ``radius``; ``spare``: inserted
        points it takes without reallocating; ``memory``: where to build it (see
        :class:`GridMemory`; fresh memory when ``None``)."""
        array = np.asarray(points)
        if array.dtype not in (np.float32, np.float64) or array.ndim != 2 or array.shape[1] < 3:
            array = _check_points(points)  # validated (or refused) and converted
        return cls(array, _check_viewpoint(viewpoint), _check_radius(radius), spare, memory)

    @property
    def size(self) -> int:
        return len(self._points)

    def _cells(self, elevation: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
        origin, height, rows, columns = self._geometry
        # Rows are clamped: inserted points beyond the frame's elevations join its edge rows,
        # which the kernels' cell ranges clamp the same way.
        cells = np.empty(len(elevation), dtype=np.int64)
        _cell_numbers(elevation, azimuth, origin, height, rows, columns, cells)
        return cells

    def _sort(
        self,
        elevation: np.ndarray,
        azimuth: np.ndarray,
        ranges: np.ndarray,
        member: int,
        offset: int,
    ) -> np.ndarray:
        """Points in cell order, by range within a cell; row ``member`` of the cell starts
        receives their sorted positions, plus ``offset``."""
        starts = self._starts[member]
        order = _counting_sort_into(self._cells(elevation, azimuth), starts, offset)
        _sort_cells(order, ranges, starts, offset)
        return order

    def directions(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Azimuth, elevation (radians) and distance (metres) of the frame points ``rows``
        (indices) relative to the viewpoint, as :meth:`in_windows` uses them."""
        positions = self._position[rows]
        return self._azimuth[positions], self._elevation[positions], self._ranges[positions]

    def in_windows(self, windows: np.ndarray) -> np.ndarray:
        """``bool (N,)``: points with ``az0 <= azimuth <= az1``, ``el0 <= elevation <= el1`` and
        ``distance >= d`` for some row ``(az0, az1, el0, el1, d)`` of ``windows`` ``(K, 5)``
        (radians, radians, metres; ``-pi <= az0``, ``az1 <= pi``)."""
        windows = np.ascontiguousarray(windows, dtype=np.float64).reshape(-1, 5)
        inside = np.zeros(self.size, dtype=bool)
        if self.size and len(windows):
            found = np.zeros(self.size, dtype=bool)
            _window_members(
                windows,
                self._azimuth,
                self._elevation,
                self._ranges,
                self._starts,
                *self._geometry,
                found,
            )
            inside[self._order] = found
        return inside

    def hidden_by_insertion(
        self,
        cleared: np.ndarray,
        inserted: np.ndarray,
        behind: np.ndarray | Callable[[np.ndarray], np.ndarray] | None,
        *,
        method: str = "auto",
        workers: int | None = None,
        pool: ThreadPoolExecutor | None = None,
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """:func:`hidden_by_insertion` of the frame without its ``cleared`` points plus the
        ``inserted`` ones, with the per-point test; ``None`` when ``method`` would not use it
        on that set (too few points, ``R`` not far above the ranges, points at the viewpoint):
        the caller then asks :func:`hidden_by_insertion`. The inserted points are decided
        first; ``behind`` may be a function of their verdicts.

        Args:
            cleared: ``bool (N,)`` frame points taken out (room made for the objects).
            inserted: ``(K, 3 + C)`` inserted points, metres.
            behind: ``bool (N,)`` frame points whose removal is to be decided, or a function
                that, given the inserted points to remove (``bool (K,)``), returns them.
            method: as in :func:`hidden_by_insertion`.
            workers: threads (``None``: up to two of the CPUs this process may use).
            pool: a running pool whose thread may take part (else one is started for the call
                when ``workers > 1`` and the work is large enough).

        Returns:
            ``bool (N,)`` frame points and ``bool (K,)`` inserted points to remove.
        """
        n = self.size
        cleared = _check_query(cleared, n)
        xyz = _check_points(inserted)
        workers = _check_workers(workers)
        k = len(xyz)
        removed, removed_inserted = np.zeros(n, dtype=bool), np.zeros(k, dtype=bool)
        rel = xyz - self.center
        ranges = _norms(rel)
        if not np.isfinite(ranges).all():
            row = int(np.flatnonzero(~np.isfinite(ranges))[0])
            raise DataError(f"inserted points: row {row} is too far from the viewpoint for float64")
        r_min = min(self._r_min, float(ranges.min(initial=np.inf)))
        r_max = max(self._r_max, float(ranges.max(initial=0.0)))
        if k and not self._local_applies(n - int(cleared.sum()) + k, r_min, r_max, method):
            return None
        positions = self._add(rel, ranges)
        absent = np.zeros(n + k, dtype=bool)
        absent[:n] = cleared[self._order]
        decide = partial(
            self._verdicts,
            self._scene(n + k, absent),
            r_min,
            2.0 * self.radius - r_min,
            workers,
            pool,
        )
        verdicts = decide(n + np.arange(k))
        removed_inserted[positions] = verdicts == _VERDICT_REMOVE
        undecided = positions[verdicts == _VERDICT_UNDECIDED_WITH]
        if len(undecided):
            nothing = np.zeros(0, dtype=np.int64)
            removed_inserted[undecided] = self._undecided(
                nothing, nothing, undecided, cleared, xyz
            )[1]
        if callable(behind):
            behind = behind(removed_inserted)
        behind = _check_query(behind, n) & ~cleared
        if not behind.any():
            return removed, removed_inserted
        if not k and not self._local_applies(n - int(cleared.sum()), r_min, r_max, method):
            return None
        queries = np.flatnonzero(behind[self._order])
        verdicts = decide(queries)
        frame_rows = self._order[queries]
        removed[frame_rows] = verdicts == _VERDICT_REMOVE
        pending = verdicts >= _VERDICT_UNDECIDED_WITHOUT
        if pending.any():
            removed[frame_rows[pending]] = self._undecided(
                verdicts[pending], frame_rows[pending], np.zeros(0, np.int64), cleared, xyz
            )[0]
        return removed, removed_inserted

    def hidden_groups(
        self,
        samples: np.ndarray,
        offsets: np.ndarray,
        cleared: np.ndarray,
        share: float,
        pool: ThreadPoolExecutor | None = None,
    ) -> np.ndarray | None:
        """Which groups of ``samples`` are at least ``share`` hidden among the frame's points
        without the ``cleared`` ones (each sample decided exactly, as a point added to them
        alone); ``None`` when the per-point test does not apply (``R`` not above the ranges,
        points at the viewpoint). A group is decided as soon as its count allows: samples the
        plane normal to their ray shows visible first, the others then one by one. Samples the
        test gives up on (its budget of full scans per group spent) count as visible. ``pool``
        may lend a thread (the answer does not depend on it).

        Args:
            samples: ``(S, 3)`` points, metres.
            offsets: ``int (M + 1,)`` group ``m`` is ``samples[offsets[m]:offsets[m + 1]]``.
            cleared: ``bool (N,)`` frame points left out.
            share: fraction in ``[0, 1]``; a group without samples is never hidden.

        Returns:
            ``bool (M,)``.
        """
        n = self.size
        cleared = _check_query(cleared, n)
        xyz = _check_points(samples)
        offsets = np.asarray(offsets, dtype=np.int64).reshape(-1)
        if len(offsets) < 1 or offsets[0] != 0 or offsets[-1] != len(xyz):
            raise ValueError(f"offsets must run from 0 to {len(xyz)} (the samples' number)")
        if (np.diff(offsets) < 0).any():
            raise ValueError("offsets must not decrease")
        if not 0.0 <= share <= 1.0:
            raise ValueError(f"share must be in [0, 1], got {share}")
        hidden = np.zeros(len(offsets) - 1, dtype=bool)
        if not len(xyz) or not n:
            return hidden
        rel = xyz - self.center
        ranges = _norms(rel)
        r_min = min(self._r_min, float(ranges.min()))
        r_max = max(self._r_max, float(ranges.max()))
        if not (np.isfinite(ranges).all() and self._local_applies(n, r_min, r_max, "local")):
            return None
        order = self._add(rel, ranges)
        position = np.empty(len(xyz), dtype=np.int64)
        position[order] = n + np.arange(len(xyz))
        absent = np.zeros(n + len(xyz), dtype=bool)
        absent[:n] = cleared[self._order]
        rho_max = 2.0 * self.radius - r_min
        cones = _first_cones(ranges, r_min, rho_max)
        sizes = np.diff(offsets)
        allowed = sizes - np.ceil(share * sizes - 1e-9).astype(np.int64)  # visible ones allowed
        scene = self._scene(n + len(xyz), absent)

        def kernel(part: np.ndarray) -> None:
            lo, hi = part[0], part[-1] + 1
            _hidden_groups(
                position,
                cones,
                offsets[lo : hi + 1],
                allowed[lo:hi],
                self.radius,
                *scene,
                r_min,
                rho_max,
                _GROUP_BRUTE_BUDGET,
                hidden[lo:hi],
            )

        parts = [part for part in np.array_split(np.arange(len(hidden)), 4) if len(part)]
        _shared_chunks(kernel, parts, pool)
        return hidden

    def _verdicts(
        self,
        scene: tuple,
        r_min: float,
        rho_max: float,
        workers: int,
        pool: ThreadPoolExecutor | None,
        queries: np.ndarray,
    ) -> np.ndarray:
        """:func:`_insertion_verdicts` of the sorted ``queries``, on two threads when worth it."""
        if not len(queries):
            return np.zeros(0, dtype=np.int8)
        cones = _first_cones(self._ranges[queries], r_min, rho_max)
        parallel = workers > 1 and len(queries) >= (
            _FRAME_PARALLEL_MIN if pool is not None else _PARALLEL_MIN
        )
        parts = np.array_split(np.arange(len(queries)), _FRAME_CHUNKS if parallel else 1)

        def kernel(part: np.ndarray) -> np.ndarray:
            return _insertion_verdicts(
                queries[part],
                cones[part],
                self.size,
                self.radius,
                *scene,
                r_min,
                rho_max,
                _BRUTE_BUDGET,
            )

        return np.concatenate(_shared_chunks(kernel, parts, pool, start=parallel))

    def _scene(self, count: int, absent: np.ndarray) -> tuple:
        """The kernels' view of the first ``count`` sorted points, ``absent`` ones skipped."""
        used = slice(0, count)
        return (
            self._rays[used],
            self._rel[used],
            self._ranges[used],
            self._rho[used],
            self._elevation[used],
            self._azimuth[used],
            self._starts,
            absent,
            *self._geometry,
        )

    def _local_applies(self, count: int, r_min: float, r_max: float, method: str) -> bool:
        """Whether :func:`hidden_point_removal` would take the per-point test for the frame
        with the objects, and the set without them (``count`` points, ranges within ``[r_min,
        r_max]``), and no point sits at the viewpoint (see :func:`_resolve_method`). Not
        :data:`AUTO_CROWDED`'s test: a frame grid holds LiDAR frames, never that crowded."""
        if method not in ("auto", "local") or r_min <= _AT_VIEWPOINT * (1.0 + r_max):
            return False
        if not 2.0 * self.radius > r_max * (1.0 + 1e-12):
            return False
        # "auto": many points, and R far above the ranges (the spread bounds the median's)
        return method == "local" or (
            count > AUTO_REFERENCE_MAX and r_max - r_min <= _LOCAL_MAX_CONE**2 * self.radius
        )

    def _add(self, rel: np.ndarray, ranges: np.ndarray) -> np.ndarray:
        """Write the inserted points (``rel`` ``(K, 3)``, ``ranges`` ``(K,)``) after the frame's,
        sorted into the same cells; returns each sorted one's index among the inserted."""
        n, k = self.size, len(ranges)
        if n + k > len(self._ranges):  # more than the spare room: grow (rare)
            total = n + 2 * k
            for name in ("_rays", "_rel", "_ranges", "_rho", "_elevation", "_azimuth"):
                old = getattr(self, name)
                grown = np.empty((total, *old.shape[1:]))
                grown[:n] = old[:n]
                setattr(self, name, grown)
        azimuth, elevation = np.empty(k), np.empty(k)
        _directions(rel, np.zeros(3), np.empty((k, 3)), azimuth, elevation)
        order = self._sort(elevation, azimuth, ranges, 1, n)
        np.take(rel, order, axis=0, out=self._rel[n : n + k])
        np.take(ranges, order, out=self._ranges[n : n + k])
        np.subtract(2.0 * self.radius, self._ranges[n : n + k], out=self._rho[n : n + k])
        np.divide(self._rel[n : n + k], self._ranges[n : n + k, None], out=self._rays[n : n + k])
        np.take(elevation, order, out=self._elevation[n : n + k])
        np.take(azimuth, order, out=self._azimuth[n : n + k])
        return order

    def _undecided(
        self,
        frame_verdicts: np.ndarray,
        frame_rows: np.ndarray,
        inserted_rows: np.ndarray,
        cleared: np.ndarray,
        inserted: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Settle the points the kernel gave up on (its budget of full scans spent) with the
        plain passes of :func:`hidden_point_removal`: the frame points ``frame_rows`` (with
        their kernel verdicts) and the inserted points ``inserted_rows``. Returns whether each
        is to be removed."""
        originals = np.flatnonzero(~cleared)
        points = np.concatenate([_check_points(self._points)[originals], inserted])
        row_of = np.full(self.size, -1, dtype=np.int64)
        row_of[originals] = np.arange(len(originals))
        with_objects = frame_verdicts == _VERDICT_UNDECIDED_WITH
        without = frame_verdicts == _VERDICT_UNDECIDED_WITHOUT
        if without.any():  # only the frame points visible without the objects can go
            query = np.zeros(len(originals), dtype=bool)
            query[row_of[frame_rows[without]]] = True
            visible = hidden_point_removal(
                points[: len(originals)], self.center, self.radius, method="local", query=query
            )
            with_objects[without] = visible[row_of[frame_rows[without]]]
        query = np.zeros(len(points), dtype=bool)
        query[row_of[frame_rows[with_objects]]] = True
        query[len(originals) + inserted_rows] = True
        removed_frame = np.zeros(len(frame_rows), dtype=bool)
        removed_inserted = np.zeros(len(inserted_rows), dtype=bool)
        if query.any():
            visible = hidden_point_removal(
                points, self.center, self.radius, method="local", query=query
            )
            removed_frame[with_objects] = ~visible[row_of[frame_rows[with_objects]]]
            removed_inserted = ~visible[len(originals) + inserted_rows]
        return removed_frame, removed_inserted


_VERDICT_KEEP, _VERDICT_REMOVE, _VERDICT_UNDECIDED_WITHOUT, _VERDICT_UNDECIDED_WITH = 0, 1, 2, 3
# A frame point among the frame's points alone (see _without_state).
_WITHOUT_CLEAR, _WITHOUT_HIDDEN, _WITHOUT_VISIBLE, _WITHOUT_UNRESOLVED = range(1, 5)


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
    every ray within ``reach`` radians of the ray at elevation ``el``, azimuth ``az``. Rows are
    clamped both ways, as points beyond the grid's rows are stored in its edge rows."""
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
def _radial_pass(
    todo,
    first_cone,
    rays,
    rel,
    ranges,
    rho,
    elevation,
    azimuth,
    starts,
    absent,
    origin,
    size,
    rows,
    columns,
):
    """``bool`` per point of ``todo``: visible by the plane normal to its ray (the pre-filter);
    ``False`` means undecided."""
    empty = np.empty(0)
    settled = np.empty(todo.shape[0], dtype=np.bool_)
    for slot in range(todo.shape[0]):
        i = todo[slot]
        found = _gather(
            i,
            first_cone[i],
            True,
            _ORIGINALS,
            rays,
            rel,
            ranges,
            rho,
            elevation,
            azimuth,
            starts,
            absent,
            origin,
            size,
            rows,
            columns,
            empty,
            empty,
            empty,
        )
        settled[slot] = found >= 0
    return settled


@nb.njit(cache=True, nogil=True)
def _gather(
    i,
    cone,
    radial_only,
    members,
    rays,
    rel,
    ranges,
    rho,
    elevation,
    azimuth,
    starts,
    absent,
    origin,
    size,
    rows,
    columns,
    out_s1,
    out_s2,
    out_t,
):
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
    ux, uy, uz = rays[i, 0], rays[i, 1], rays[i, 2]
    e1x, e1y, e1z, e2x, e2y, e2z = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    if not radial_only:
        e1x, e1y, e1z, e2x, e2y, e2z = _tangent_basis(ux, uy, uz)
    ri = ranges[i]
    reach = min(cone * (1.0 + 1e-9) + 1e-12, math.pi)
    half = math.sin(reach / 2.0)
    chord2 = 4.0 * half * half * (1.0 + 1e-12) + 1e-300
    if reach >= math.pi:
        chord2 = 5.0
    masked = absent.shape[0] > 0
    near = np.empty(64, dtype=np.int64)
    certify = members & _CERTIFY != 0
    quadrants = 0
    capacity = out_t.shape[0]
    count = 0
    row_lo, row_hi, col_lo, col_n = _cell_range(
        elevation[i], azimuth[i], reach, origin, size, rows, columns
    )
    for member in range(starts.shape[0]):
        if not members & (1 << member):
            continue
        for row in range(row_lo, row_hi + 1):
            lo0, hi0, lo1, hi1 = _row_runs(starts, member, row, col_lo, col_n, columns)
            for run in range(2):
                lo, hi = (lo0, hi0) if run == 0 else (lo1, hi1)
                if hi - lo > near.shape[0]:
                    near = np.empty(2 * (hi - lo), dtype=np.int64)
                # The points within the chord first, without branches (the cheaper scan), then
                # only those.
                found = 0
                for j in range(lo, hi):
                    dx = rays[j, 0] - ux
                    dy = rays[j, 1] - uy
                    dz = rays[j, 2] - uz
                    near[found] = j
                    found += dx * dx + dy * dy + dz * dz <= chord2
                for f in range(found):
                    j = near[f]
                    if j == i or (masked and absent[j]):
                        continue
                    dx = rays[j, 0] - ux
                    dy = rays[j, 1] - uy
                    dz = rays[j, 2] - uz
                    d2 = dx * dx + dy * dy + dz * dz
                    if (
                        d2 == 0.0
                        and rel[j, 0] == rel[i, 0]
                        and rel[j, 1] == rel[i, 1]
                        and rel[j, 2] == rel[i, 2]
                    ):
                        continue  # an exact duplicate (equal points have equal rays)
                    t = 0.5 * d2 - (ri - ranges[j]) / rho[j]
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


@nb.njit(cache=True, nogil=True)
def _gather_grown(
    i,
    cone,
    members,
    rays,
    rel,
    ranges,
    rho,
    elevation,
    azimuth,
    starts,
    absent,
    origin,
    size,
    rows,
    columns,
    s1,
    s2,
    t,
):
    """:func:`_gather` into buffers that are replaced by larger ones until every constraint
    fits; returns the count and the (possibly new) buffers."""
    while True:
        count = _gather(
            i,
            cone,
            False,
            members,
            rays,
            rel,
            ranges,
            rho,
            elevation,
            azimuth,
            starts,
            absent,
            origin,
            size,
            rows,
            columns,
            s1,
            s2,
            t,
        )
        if count <= t.shape[0]:
            return count, s1, s2, t
        s1 = np.empty(2 * count)
        s2 = np.empty(2 * count)
        t = np.empty(2 * count)


@nb.njit(cache=True, nogil=True)
def _line_interval(a, b, c, fa, fb, da, db, lo, hi):
    """Clip the parameter interval ``[lo, hi]`` of the line ``f + lam d`` by the constraint
    ``a x + b y <= c``. Returns ``(lo, hi, ok)``; ``ok`` is False when the constraint excludes
    the whole line (a parallel constraint that coincides with the line up to rounding counts as
    satisfied)."""
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
            lo, hi, ok = _line_interval(_BOX_A[side], _BOX_B[side], box, fa, fb, da, db, lo, hi)
            inside = inside and ok
        if not inside:
            return 0, 0.0, 0.0
        for previous in range(k):
            i = (previous * stride) % count
            lo, hi, ok = _line_interval(s1[i], s2[i], t[i] - _SLACK, fa, fb, da, db, lo, hi)
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
def _decide(
    i,
    first_cone,
    members,
    rays,
    rel,
    ranges,
    rho,
    elevation,
    azimuth,
    starts,
    absent,
    origin,
    size,
    rows,
    columns,
    r_min,
    rho_max,
    s1,
    s2,
    t,
    brutes,
    brute_budget,
):
    """State (hidden 0, visible 1, unresolved 2) of sorted point ``i`` among the member sets
    ``members``, which the plane normal to its ray leaves undecided (see :func:`_radial_pass`).
    Returns it with the full scans made so far and the (possibly grown) buffers.

    Hidden is proven by a neighbourhood where no plane fits (hidden in a subset implies
    hidden); visible by the least tilted plane whose danger cone the neighbourhood covers.
    ``members`` may hold the :data:`_CERTIFY` bit (see :func:`_gather`).
    """
    ri = ranges[i]
    cone = max(_FIRST_WIDENING * first_cone, 1e-6)
    # A narrow neighbourhood first: the points hiding a hidden point are usually its
    # nearest, and the full one can hold many times more.
    probe = _PROBE_NARROWING * first_cone
    if probe > 1e-6:
        count, s1, s2, t = _gather_grown(
            i,
            probe,
            members,
            rays,
            rel,
            ranges,
            rho,
            elevation,
            azimuth,
            starts,
            absent,
            origin,
            size,
            rows,
            columns,
            s1,
            s2,
            t,
        )
        if count == _NO_PLANE or _min_tilt(s1, s2, t, count)[0] == 0:
            return _STATE_HIDDEN, brutes, s1, s2, t
    while True:
        everything = cone >= _BRUTE_ANGLE
        if everything:
            if brutes >= brute_budget:
                return _STATE_UNRESOLVED, brutes, s1, s2, t
            brutes += 1
            cone = math.pi
        count, s1, s2, t = _gather_grown(
            i,
            cone,
            members,
            rays,
            rel,
            ranges,
            rho,
            elevation,
            azimuth,
            starts,
            absent,
            origin,
            size,
            rows,
            columns,
            s1,
            s2,
            t,
        )
        if count == _NO_PLANE:
            return _STATE_HIDDEN, brutes, s1, s2, t
        status, a, b = _min_tilt(s1, s2, t, count)
        if status == 0:
            return _STATE_HIDDEN, brutes, s1, s2, t
        if everything:
            return _STATE_VISIBLE, brutes, s1, s2, t
        alpha, gamma = _danger_cone(math.sqrt(a * a + b * b), ri, r_min, rho_max)
        if alpha + gamma <= cone * (1.0 - 1e-9):
            return _STATE_VISIBLE, brutes, s1, s2, t
        cone = max(2.0 * cone, 1.05 * (alpha + gamma))


@nb.njit(cache=True, nogil=True)
def _classify(
    todo,
    first_cone,
    rays,
    rel,
    ranges,
    rho,
    elevation,
    azimuth,
    starts,
    absent,
    origin,
    size,
    rows,
    columns,
    r_min,
    rho_max,
    brute_budget,
):
    """States (hidden 0, visible 1, unresolved 2) of the sorted points ``todo``, which the
    plane normal to their ray leaves undecided (see :func:`_radial_pass`); at most
    ``brute_budget`` full scans, the points that need more are left unresolved."""
    state = np.empty(todo.shape[0], dtype=np.int64)
    s1 = np.empty(256)
    s2 = np.empty(256)
    t = np.empty(256)
    brutes = 0
    for slot in range(todo.shape[0]):
        i = todo[slot]
        state[slot], brutes, s1, s2, t = _decide(
            i,
            first_cone[i],
            _ORIGINALS,
            rays,
            rel,
            ranges,
            rho,
            elevation,
            azimuth,
            starts,
            absent,
            origin,
            size,
            rows,
            columns,
            r_min,
            rho_max,
            s1,
            s2,
            t,
            brutes,
            brute_budget,
        )
    return state


@nb.njit(cache=True, nogil=True)
def _radial_clear(
    i,
    cone,
    members,
    radius,
    rays,
    rel,
    ranges,
    rho,
    elevation,
    azimuth,
    starts,
    absent,
    origin,
    size,
    rows,
    columns,
):
    """Whether no point of the member sets blocks the plane through sorted point ``i`` normal
    to its ray, within its first cone ``cone`` (:func:`_gather`'s radial test; ``radius``:
    ``R``), on cells sorted by range.

    A point ``j`` blocks it when ``2 sin^2(theta / 2) <= (r_i - r_j) / (2R - r_j) + slack``
    (``theta``: the angle between the rays), so none farther than ``r_i + 4 slack R`` does:
    each cell is read only up to the first such point.
    """
    ux, uy, uz = rays[i, 0], rays[i, 1], rays[i, 2]
    ri = ranges[i]
    limit = ri + 4.0 * _SLACK * radius
    reach = min(cone * (1.0 + 1e-9) + 1e-12, math.pi)
    half = math.sin(reach / 2.0)
    chord2 = 4.0 * half * half * (1.0 + 1e-12) + 1e-300
    if reach >= math.pi:
        chord2 = 5.0
    row_lo, row_hi, col_lo, col_n = _cell_range(
        elevation[i], azimuth[i], reach, origin, size, rows, columns
    )
    first = (col_lo % columns + columns) % columns
    masked = absent.shape[0] > 0
    # Cells from the query's own outwards: a blocker, when there is one, usually lies right
    # next to the query's ray, and the answer does not depend on the order.
    n_rows = row_hi - row_lo + 1
    own_row = min(max(math.floor((elevation[i] - origin) / size), row_lo), row_hi) - row_lo
    own_k = math.floor((azimuth[i] + math.pi) / (2.0 * math.pi / columns)) - col_lo
    own_k = min(max(own_k, 0), col_n - 1)
    for member in range(starts.shape[0]):
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
                if column >= columns:
                    column -= columns
                cell = row * columns + column
                for j in range(starts[member, cell], starts[member, cell + 1]):
                    if ranges[j] > limit:
                        break
                    if j == i:
                        continue
                    dx = rays[j, 0] - ux
                    dy = rays[j, 1] - uy
                    dz = rays[j, 2] - uz
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 > chord2 or (masked and absent[j]):
                        continue
                    if (
                        d2 == 0.0
                        and rel[j, 0] == rel[i, 0]
                        and rel[j, 1] == rel[i, 1]
                        and rel[j, 2] == rel[i, 2]
                    ):
                        continue  # an exact duplicate
                    if 0.5 * d2 - (ri - ranges[j]) / rho[j] <= _SLACK:
                        return False
    return True


@nb.njit(cache=True, nogil=True)
def _without_state(
    i,
    cone,
    radius,
    rays,
    rel,
    ranges,
    rho,
    elevation,
    azimuth,
    starts,
    absent,
    origin,
    size,
    rows,
    columns,
    r_min,
    rho_max,
    s1,
    s2,
    t,
    brutes,
    brute_budget,
):
    """State of sorted frame point ``i`` among the frame's points (first cone ``cone``):
    clear (the plane normal to its ray), hidden, visible (a tilted plane) or unresolved; with
    the full scans made so far and the buffers, as :func:`_decide`."""
    if _radial_clear(
        i,
        cone,
        _ORIGINALS,
        radius,
        rays,
        rel,
        ranges,
        rho,
        elevation,
        azimuth,
        starts,
        absent,
        origin,
        size,
        rows,
        columns,
    ):
        return _WITHOUT_CLEAR, brutes, s1, s2, t
    state, brutes, s1, s2, t = _decide(
        i,
        cone,
        _ORIGINALS | _CERTIFY,
        rays,
        rel,
        ranges,
        rho,
        elevation,
        azimuth,
        starts,
        absent,
        origin,
        size,
        rows,
        columns,
        r_min,
        rho_max,
        s1,
        s2,
        t,
        brutes,
        brute_budget,
    )
    if state == _STATE_HIDDEN:
        return _WITHOUT_HIDDEN, brutes, s1, s2, t
    if state == _STATE_VISIBLE:
        return _WITHOUT_VISIBLE, brutes, s1, s2, t
    return _WITHOUT_UNRESOLVED, brutes, s1, s2, t


@nb.njit(cache=True, nogil=True)
def _insertion_verdicts(
    queries,
    cones,
    n_original,
    radius,
    rays,
    rel,
    ranges,
    rho,
    elevation,
    azimuth,
    starts,
    absent,
    origin,
    size,
    rows,
    columns,
    r_min,
    rho_max,
    brute_budget,
):
    """e-HPR's inserted scope for the sorted points ``queries`` (first cones ``cones``) on a
    grid whose cells are sorted by range (``radius``: ``R``): the frame's
    points (positions below ``n_original``) go when visible without the inserted ones and
    hidden with them, inserted points when hidden. Per query: keep 0, remove 1, or which
    verdict it could not settle within ``brute_budget`` full scans: without the inserted
    points 2, with them 3.

    A frame point's plane normal to its ray is checked against the frame's points and the
    inserted ones separately, so that one scan of each decides both sets when it fits;
    otherwise each set is decided as :func:`_classify` does.
    """
    verdicts = np.empty(queries.shape[0], dtype=np.int8)
    s1 = np.empty(256)
    s2 = np.empty(256)
    t = np.empty(256)
    brutes = 0
    for slot in range(queries.shape[0]):
        i = queries[slot]
        cone = cones[slot]
        if i < n_original:
            state, brutes, s1, s2, t = _without_state(
                i,
                cone,
                radius,
                rays,
                rel,
                ranges,
                rho,
                elevation,
                azimuth,
                starts,
                absent,
                origin,
                size,
                rows,
                columns,
                r_min,
                rho_max,
                s1,
                s2,
                t,
                brutes,
                brute_budget,
            )
            if state == _WITHOUT_HIDDEN:
                verdicts[slot] = _VERDICT_KEEP
                continue
            if state == _WITHOUT_UNRESOLVED:
                verdicts[slot] = _VERDICT_UNDECIDED_WITHOUT
                continue
            # visible without the inserted points: by the radial plane unless they block it
            if state == _WITHOUT_CLEAR and _radial_clear(
                i,
                cone,
                _INSERTED,
                radius,
                rays,
                rel,
                ranges,
                rho,
                elevation,
                azimuth,
                starts,
                absent,
                origin,
                size,
                rows,
                columns,
            ):
                verdicts[slot] = _VERDICT_KEEP
                continue
        elif _radial_clear(
            i,
            cone,
            _BOTH,
            radius,
            rays,
            rel,
            ranges,
            rho,
            elevation,
            azimuth,
            starts,
            absent,
            origin,
            size,
            rows,
            columns,
        ):
            verdicts[slot] = _VERDICT_KEEP
            continue
        state, brutes, s1, s2, t = _decide(
            i,
            cone,
            _BOTH | _CERTIFY,
            rays,
            rel,
            ranges,
            rho,
            elevation,
            azimuth,
            starts,
            absent,
            origin,
            size,
            rows,
            columns,
            r_min,
            rho_max,
            s1,
            s2,
            t,
            brutes,
            brute_budget,
        )
        if state == _STATE_HIDDEN:
            verdicts[slot] = _VERDICT_REMOVE
        elif state == _STATE_VISIBLE:
            verdicts[slot] = _VERDICT_KEEP
        else:
            verdicts[slot] = _VERDICT_UNDECIDED_WITH
    return verdicts


@nb.njit(cache=True, nogil=True)
def _hidden_groups(
    position,
    cones,
    offsets,
    allowed,
    radius,
    rays,
    rel,
    ranges,
    rho,
    elevation,
    azimuth,
    starts,
    absent,
    origin,
    size,
    rows,
    columns,
    r_min,
    rho_max,
    brute_budget,
    hidden,
):  # pragma: no cover - numba
    # FrameGrid.hidden_groups: per group, the samples' radial planes first (cheap, and one
    # visible sample more than ``allowed`` settles the group), then the full test.
    s1 = np.empty(256)
    s2 = np.empty(256)
    t = np.empty(256)
    for m in range(offsets.shape[0] - 1):
        lo, hi = offsets[m], offsets[m + 1]
        if hi == lo:
            continue
        brutes = 0  # a budget per group: the verdicts do not depend on how groups are split
        visible = 0
        blocked = np.empty(hi - lo, dtype=np.int64)
        n_blocked = 0
        for k in range(lo, hi):
            if _radial_clear(
                position[k],
                cones[k],
                _ORIGINALS,
                radius,
                rays,
                rel,
                ranges,
                rho,
                elevation,
                azimuth,
                starts,
                absent,
                origin,
                size,
                rows,
                columns,
            ):
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
            state, brutes, s1, s2, t = _decide(
                position[k],
                cones[k],
                _ORIGINALS | _CERTIFY,
                rays,
                rel,
                ranges,
                rho,
                elevation,
                azimuth,
                starts,
                absent,
                origin,
                size,
                rows,
                columns,
                r_min,
                rho_max,
                s1,
                s2,
                t,
                brutes,
                brute_budget,
            )
            if state != _STATE_HIDDEN:
                visible += 1
                if visible > allowed[m]:
                    break
        hidden[m] = visible <= allowed[m]


@nb.njit(cache=True, nogil=True)
def _window_members(
    windows, azimuth, elevation, ranges, starts, origin, height, rows, columns, out
):
    """Mark in ``out`` the sorted points of member set 0 inside any of ``windows`` (see
    :meth:`FrameGrid.in_windows`; distance: ``ranges``), visiting only the cells each window
    overlaps, and one more on every side so that rounding in the cell numbers cannot miss a
    point."""
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


# ----------------------------------------------------------------------------------------------
# Sectors: Qhull per overlapping azimuth sector, verdicts certified, threads
# ----------------------------------------------------------------------------------------------
_SECTOR_POINTS = 3000  # target core points per sector


def _sectors(setup: _Setup, wanted: np.ndarray, workers: int) -> np.ndarray:
    """Visible flags ``(M,)`` from per-sector hulls; uncertified points go to :func:`_local`."""
    distinct, inverse = setup.distinct()
    if distinct is not setup:
        chosen = np.zeros(distinct.size, dtype=bool)
        chosen[inverse[wanted]] = True
        return _sectors(distinct, chosen, workers)[inverse] & wanted
    ranges, radius = setup.ranges, setup.radius
    r_min = float(ranges.min())
    rho_max = 2.0 * radius - r_min
    rays = setup.rays
    azimuth = np.arctan2(rays[:, 1], rays[:, 0])
    elevation = np.arcsin(np.clip(rays[:, 2], -1.0, 1.0))
    # Margin: the widest danger cone of a facet normal to the ray, in azimuth, with room for
    # some tilt; facets that need more are not certified and their points go to "local".
    widest = 2.0 * math.asin(math.sqrt(min(2.0, (float(ranges.max()) - r_min) / rho_max) / 2.0))
    top = min(float(np.abs(elevation).max()) + widest, 1.2)
    margin = 1.5 * math.asin(min(1.0, math.sin(widest) / math.cos(top))) + 1e-6
    count = int(np.clip(setup.size // _SECTOR_POINTS, 1, 64))
    count = min(count, max(1, int(2 * math.pi / (4 * margin))))
    if count < 2:
        decided = _reference(setup, wanted)
        return decided
    order = np.argsort(azimuth, kind="stable")
    sorted_azimuth = azimuth[order]
    bounds = np.linspace(0, setup.size, count + 1).astype(np.int64)
    flipped = setup.flipped()
    jobs = []
    for k in range(count):
        lo, hi = int(bounds[k]), int(bounds[k + 1])
        if hi > lo and wanted[order[lo:hi]].any():
            jobs.append((lo, hi))
    tasks = [
        (lo, hi, order, sorted_azimuth, flipped, margin, rho_max, setup.size) for lo, hi in jobs
    ]
    if workers > 1 and len(tasks) > 1 and setup.size >= _PARALLEL_MIN:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            results = list(pool.map(_sector_verdicts, tasks))
    else:
        results = [_sector_verdicts(task) for task in tasks]
    visible = np.zeros(setup.size, dtype=bool)
    uncertain = np.zeros(setup.size, dtype=bool)
    for core, vertex, certified in results:
        visible[core] = vertex & certified
        uncertain[core] = vertex & ~certified
    uncertain &= wanted
    if uncertain.any():
        visible[uncertain] = _local(setup, uncertain, 1)[uncertain]
    return visible & wanted


def _sector_verdicts(task: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Core points of one sector, whether each is a vertex of the sector's hull, and whether
    that verdict is certified for the whole set."""
    lo, hi, order, sorted_azimuth, flipped, margin, rho_max, total = task
    extended = np.concatenate(
        [sorted_azimuth - 2 * np.pi, sorted_azimuth, sorted_azimuth + 2 * np.pi]
    )
    start = int(np.searchsorted(extended, sorted_azimuth[lo] - margin, "left"))
    stop = int(np.searchsorted(extended, sorted_azimuth[hi - 1] + margin, "right"))
    if stop - start >= total:
        positions = np.arange(total)
        cover = None  # the sector's set is the whole set
    else:
        positions = np.arange(start, stop) % total
        # every point with an azimuth strictly between these two is in the sector's set
        cover = (float(extended[start - 1]), float(extended[stop]))
    members = order[positions]
    core_mask = (positions >= lo) & (positions < hi)
    cloud = np.vstack([flipped[members], np.zeros((1, 3))])
    try:
        # Q5: skip Qhull's final outer-plane correction, which only tightens error bounds
        # (about 15% of a frame's hull time; same vertices on every fixture and test scene).
        hull = ConvexHull(cloud, qhull_options="Q5")
    except (QhullError, ValueError):
        count = int(core_mask.sum())
        return members[core_mask], np.ones(count, bool), np.zeros(count, bool)
    certified_facet = _certified_facets(hull.equations, rho_max, cover)
    vertex = np.zeros(len(cloud), dtype=bool)
    vertex[hull.simplices.ravel()] = True
    certified = np.zeros(len(cloud), dtype=bool)
    certified[hull.simplices[certified_facet].ravel()] = True
    return members[core_mask], vertex[:-1][core_mask], certified[:-1][core_mask]


def _certified_facets(
    equations: np.ndarray, rho_max: float, cover: tuple[float, float] | None
) -> np.ndarray:
    """``bool (F,)``: hull facets whose plane provably bounds the whole set.

    A flipped point at angle ``beta`` from the facet normal lies at most ``rho_max cos(beta)``
    along it, so only points within ``arccos(offset / rho_max)`` of the normal can cross the
    plane; the facet is certified when that cone lies inside the azimuth interval ``cover``
    whose points all took part (``None``: all did).
    """
    normal, offset = equations[:, :3], -equations[:, 3]
    if cover is None:
        return np.ones(len(equations), dtype=bool)
    cone = np.arccos(np.clip(offset / rho_max, -1.0, 1.0))
    elevation = np.arcsin(np.clip(normal[:, 2], -1.0, 1.0))
    ok = (offset > 0) & (cone + np.abs(elevation) < np.pi / 2 - 1e-9)
    with np.errstate(invalid="ignore", divide="ignore"):
        spread = np.arcsin(np.clip(np.sin(cone) / np.cos(elevation), -1.0, 1.0))
    middle, half = (cover[0] + cover[1]) / 2, (cover[1] - cover[0]) / 2
    azimuth = np.arctan2(normal[:, 1], normal[:, 0])
    offset_azimuth = (azimuth - middle + np.pi) % (2 * np.pi) - np.pi
    return ok & (np.abs(offset_azimuth) + spread < half * (1 - 1e-12))
