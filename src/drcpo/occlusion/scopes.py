"""The paper's uses of HPR: s-HPR (:func:`self_occlusion`, per placed object), e-HPR
(:func:`external_occlusion`, the whole frame; :func:`hidden_by_insertion`, its ``inserted``
scope) and :func:`azimuth_focus`. Imports the other :mod:`drcpo.occlusion` modules.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from drcpo.errors import ConfigError, DataError
from drcpo.occlusion.checks import (
    _check_points,
    _check_query,
    _check_radius,
    _check_viewpoint,
    _check_workers,
)
from drcpo.occlusion.flip import _Setup
from drcpo.occlusion.frame_grid import FrameGrid
from drcpo.occlusion.hpr import HPR_METHODS, _crowded, _resolve_method, hidden_point_removal
from drcpo.occlusion.local import _local_grid
from drcpo.occlusion.presets import HPR_PRESETS
from drcpo.occlusion.threads import _shared_chunks
from drcpo.occlusion.zbuffer import range_image_occlusion

__all__ = [
    "azimuth_focus",
    "external_occlusion",
    "hidden_by_insertion",
    "self_occlusion",
    "self_occlusion_many",
]


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

    The hulls (:mod:`drcpo.occlusion.hull`'s numba kernel, or Qhull) release the GIL while they are
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
