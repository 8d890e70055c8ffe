"""e-HPR, the paper's external occlusion of a frame after insertion.

* Over the whole frame, as published: :func:`external_occlusion` removes every hidden point (a
  library routine; DR.CPO does not use it: it drops the sampled objects that others hide and
  trains a worse detector, ``docs/detection.md``).
* Scoped to the inserted objects, as DR.CPO (:class:`drcpo.transforms.drcpo.DRCPO`) runs it:
  :func:`inserted_scope` in two steps that return data. Step 1 decides
  the inserted points (:attr:`InsertedScope.removed_inserted`); the caller then works out
  which objects it drops (too few points left) and the view windows of the others
  (:mod:`drcpo.occlusion.view_windows`); step 2, :meth:`InsertedScope.removed_behind`,
  decides the original points in those windows: those hidden with the objects but visible
  without them go.

Imports the other :mod:`drcpo.occlusion` modules, never anything above.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence

import numpy as np

from drcpo.errors import ConfigError
from drcpo.occlusion.checks import (
    _check_points,
    _check_query,
    _check_radius,
    _check_viewpoint,
)
from drcpo.occlusion.flip import _Setup
from drcpo.occlusion.frame_grid import FrameGrid, GridInsertion
from drcpo.occlusion.hpr import HPR_METHODS, _crowded, _resolve_method, hidden_point_removal
from drcpo.occlusion.local import _local_grid
from drcpo.occlusion.view_windows import in_windows

__all__ = [
    "InsertedScope",
    "external_occlusion",
    "inserted_scope",
]


def external_occlusion(
    points: np.ndarray,
    radius: float = 1e5,
    viewpoint_z: float = 0.0,
    *,
    method: str = "auto",
) -> np.ndarray:
    """e-HPR over a whole frame (after insertion), as the paper publishes it, from the
    viewpoint ``(0, 0, viewpoint_z)``.

    Args:
        points: ``(N, 3 + C)`` the frame's points (metres).
        radius, viewpoint_z: HPR radius ``R`` and viewpoint height, metres (the defaults:
            PV-RCNN++'s in the paper; the detector presets' YAML files hold the others, e.g.
            ``load_config("second").drcpo.external_occlusion``).
        method: as in :func:`hidden_point_removal`.

    Returns:
        ``bool (N,)``: points kept (visible).
    """
    xyz = _check_points(points)
    return hidden_point_removal(xyz, (0.0, 0.0, float(viewpoint_z)), radius, method=method)


class InsertedScope(ABC):
    """e-HPR's ``inserted`` scope after step 1 (see :func:`inserted_scope`; one subclass per
    path, which it picks).

    Attributes:
        removed_inserted: ``bool (K,)`` inserted points to remove (hidden), in their order.
    """

    removed_inserted: np.ndarray

    def removed_behind(self, windows: np.ndarray | None) -> np.ndarray:
        """Step 2: ``bool (M,)`` original points (in their order) to remove among those in
        ``windows`` (``(W, 5)`` rows of
        :func:`~drcpo.occlusion.view_windows.window_spans`; ``None``: every direction):
        hidden with the inserted points and visible without them."""
        return self.removed_of(self.in_windows(windows))

    @abstractmethod
    def in_windows(self, windows: np.ndarray | None) -> np.ndarray:
        """``bool (M,)``: original points in ``windows`` (as :meth:`removed_behind`)."""

    @abstractmethod
    def removed_of(self, behind: np.ndarray) -> np.ndarray:
        """Step 2 for a given set: ``bool (M,)`` original points of ``behind`` (``bool (M,)``)
        to remove."""


class _GridScope(InsertedScope):
    """Both steps on a :class:`FrameGrid` of the frame (the original points are its points
    without the cleared ones)."""

    def __init__(self, grid: FrameGrid, step: GridInsertion) -> None:
        self._grid, self._step = grid, step
        self.removed_inserted = step.removed_inserted

    def in_windows(self, windows: np.ndarray | None) -> np.ndarray:
        kept = ~self._step.cleared
        if windows is None:
            return np.ones(int(kept.sum()), dtype=bool)
        return self._grid.in_windows(windows)[kept]

    def removed_of(self, behind: np.ndarray) -> np.ndarray:
        kept = ~self._step.cleared
        frame = np.zeros(len(kept), dtype=bool)
        frame[kept] = behind
        return self._step.hidden_behind(frame)[kept]


class _PointsScope(InsertedScope):
    """Both steps on the points themselves, by HPR's plain passes."""

    def __init__(
        self,
        xyz: np.ndarray,
        inserted: np.ndarray,
        viewpoint: np.ndarray,
        radius: float,
        method: str = "auto",
    ) -> None:
        self._xyz, self._inserted, self._viewpoint = xyz, inserted, viewpoint
        self._radius, self._method = radius, method
        self._original = np.flatnonzero(~inserted)
        self.removed_inserted = self._hidden(inserted)[inserted]

    def _hidden(self, query: np.ndarray) -> np.ndarray:
        """``bool (N,)``: points of ``query`` hidden among all points."""
        if not query.any():
            return np.zeros(len(query), dtype=bool)
        return query & ~hidden_point_removal(
            self._xyz,
            self._viewpoint,
            self._radius,
            method=self._method,
            query=query,
        )

    def in_windows(self, windows: np.ndarray | None) -> np.ndarray:
        return in_windows(self._xyz[self._original], windows, self._viewpoint)

    def removed_of(self, behind: np.ndarray) -> np.ndarray:
        query = np.zeros(len(self._xyz), dtype=bool)
        query[self._original] = behind
        suspects = self._hidden(query)
        if suspects.any():
            # Original points hidden even without the inserted objects stay: HPR's own
            # verdicts on the original frame never delete a point.
            suspects[self._original] &= self.visible_without(suspects[self._original])
        return suspects[self._original]

    def visible_without(self, wanted: np.ndarray) -> np.ndarray:
        """``bool (M,)``: original points visible among the original points alone (``True``
        outside ``wanted``, ``bool (M,)``)."""
        originals = self._xyz[self._original]
        return hidden_point_removal(
            originals,
            self._viewpoint,
            self._radius,
            method=self._method,
            query=wanted,
        )


class _Nothing(InsertedScope):
    """No point takes part (all at the viewpoint): nothing is removed."""

    def __init__(self, inserted: np.ndarray) -> None:
        self._originals = int((~inserted).sum())
        self.removed_inserted = np.zeros(int(inserted.sum()), dtype=bool)

    def in_windows(self, windows: np.ndarray | None) -> np.ndarray:
        return np.zeros(self._originals, dtype=bool)

    def removed_of(self, behind: np.ndarray) -> np.ndarray:
        return np.zeros(self._originals, dtype=bool)


def inserted_scope(
    points: np.ndarray,
    inserted: np.ndarray,
    viewpoint: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    radius: float = 100000.0,
    *,
    grid: FrameGrid | None = None,
    cleared: np.ndarray | None = None,
    method: str = "auto",
) -> InsertedScope:
    """Step 1 of e-HPR's ``inserted`` scope: decide the inserted points; the returned
    object's :meth:`~InsertedScope.removed_behind` is step 2.

    The path is chosen here: a ``grid`` of the frame (points sorted
    once, see :class:`FrameGrid`) where :meth:`FrameGrid.applies`; else, as
    :func:`hidden_point_removal` would, the per-point test on a grid built for the call or
    HPR's plain passes. Each point's verdict is exact against all points whichever path.

    Args:
        points: ``(N, 3 + C)`` the frame after insertion (metres).
        inserted: ``bool (N,)`` the inserted points.
        viewpoint: ``(3,)`` metres; radius: HPR's ``R`` (metres).
        grid: the :class:`FrameGrid` of the frame before insertion, with ``cleared``
            (``bool (grid.size,)``): the frame points taken out. ``points[~inserted]`` must
            be the grid's points without them, in order.
        method: as in :func:`hidden_point_removal`.
    """
    xyz = _check_points(points)
    center = _check_viewpoint(viewpoint)
    radius = _check_radius(radius)
    if method not in HPR_METHODS:
        raise ConfigError(f"method must be one of {', '.join(HPR_METHODS)}, got {method!r}")
    inserted = _check_query(inserted, len(xyz))
    if grid is not None:
        if cleared is None:
            raise ValueError("inserted_scope: a grid needs cleared (the frame points taken out)")
        if grid.applies(cleared, xyz[inserted], method):
            step = grid.insert(cleared, xyz[inserted], method=method)
            return _GridScope(grid, step)
    setup = _Setup.build(xyz, center, radius)
    if setup.size == 0:
        return _Nothing(inserted)
    chosen = _resolve_method(method, setup)
    if chosen == "local" and not (method == "auto" and _crowded(_local_grid(setup).starts, setup)):
        original = np.flatnonzero(~inserted)
        own = FrameGrid.build(xyz[original], center, radius, spare=len(xyz) - len(original))
        none_cleared = np.zeros(len(original), dtype=bool)
        if own.applies(none_cleared, xyz[inserted], "local"):
            step = own.insert(none_cleared, xyz[inserted], method="local")
            return _GridScope(own, step)
    return _PointsScope(xyz, inserted, center, radius, method)
