""":class:`FrameGrid`: a frame's points sorted once into the per-point test's grid, for
e-HPR's inserted scope with any inserted objects, groups of samples hidden by the frame, and
points by direction. Imports :mod:`drcpo.occlusion.hpr` and the modules below it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial

import numpy as np

from drcpo.errors import DataError
from drcpo.occlusion.checks import (
    _check_points,
    _check_query,
    _check_radius,
    _check_viewpoint,
)
from drcpo.occlusion.flip import _AT_VIEWPOINT
from drcpo.occlusion.frame_kernels import (
    _VERDICT_REMOVE,
    _VERDICT_UNDECIDED_WITH,
    _VERDICT_UNDECIDED_WITHOUT,
    _hidden_groups,
    _insertion_verdicts,
    _window_members,
)
from drcpo.occlusion.grid import (
    GridMemory,
    _build_frame_grid,
    _cell_numbers,
    _counting_sort_into,
    _directions,
    _norms,
    _sort_cells,
)
from drcpo.occlusion.hpr import _LOCAL_MAX_CONE, AUTO_REFERENCE_MAX, hidden_point_removal
from drcpo.occlusion.kernels import _BRUTE_BUDGET, _GROUP_BRUTE_BUDGET, Scene
from drcpo.occlusion.local import _NONE_ABSENT, _first_cones

__all__ = ["FrameGrid", "GridInsertion"]

# Grid cells of a FrameGrid, relative to the typical first neighbourhood (half as wide as the
# generic grid's: its scans read whole runs of cells; docs/measurements.md: finer ones).
_FRAME_ROW_HEIGHT = 1.0
_FRAME_COLUMN_WIDTH = 0.5


class FrameGrid:
    """A frame's points seen from the e-HPR viewpoint, sorted once into the per-point test's
    grid, for e-HPR's ``inserted`` scope on that frame with any inserted objects.

    It depends only on the frame, so the DR.CPO pipeline builds it once and uses it for the
    placement's occlusion test and for e-HPR. :meth:`insert` then adds the inserted points to its
    cells (no re-sorting of the frame) and skips the frame points they displace;
    :meth:`in_windows` selects points by direction cell by cell.

    Directions are ``arctan2(y, x)`` (azimuth) and ``arctan2(z, sqrt(x x + y y))`` (elevation)
    of a point relative to the viewpoint, by libm (as
    :func:`drcpo.occlusion.view_windows.view_windows` computes them).

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
            _window_members(windows, self._scene(self.size, _NONE_ABSENT, self._r_min), found)
            inside[self._order] = found
        return inside

    def applies(self, cleared: np.ndarray, inserted: np.ndarray, method: str = "auto") -> bool:
        """Whether :meth:`insert` serves e-HPR's inserted scope of the frame without its
        ``cleared`` points (``bool (N,)``) plus ``inserted`` ``(K, 3 + C)`` (metres): whether
        :func:`hidden_point_removal` with ``method`` would take the per-point test on that set
        and on it without the inserted points. It does not when there are few points, ``R``
        is not far above the ranges or points sit at the viewpoint; the caller then takes
        the generic path (:func:`drcpo.occlusion.external.inserted_scope` decides this)."""
        cleared = _check_query(cleared, self.size)
        ranges = self._inserted_ranges(inserted)
        r_min, r_max = self._bounds(ranges)
        count = self.size - int(cleared.sum()) + len(ranges)
        return self._local_applies(count, r_min, r_max, method)

    def insert(
        self,
        cleared: np.ndarray,
        inserted: np.ndarray,
        *,
        method: str = "auto",
    ) -> GridInsertion:
        """Step 1 of e-HPR's inserted scope with the per-point test: add the ``inserted``
        points to the grid's cells (no re-sorting of the frame), skip the ``cleared`` frame
        points, and decide the inserted points. Step 2 is the returned object's
        :meth:`GridInsertion.hidden_behind`. Only where :meth:`applies` (else ``ValueError``);
        the grid holds these inserted points until the next call.

        Args:
            cleared: ``bool (N,)`` frame points taken out (room made for the objects).
            inserted: ``(K, 3 + C)`` inserted points, metres.
            method: as in :func:`hidden_point_removal` (``"auto"`` or ``"local"``).
        """
        n = self.size
        cleared = _check_query(cleared, n)
        xyz = _check_points(inserted)
        k = len(xyz)
        rel = xyz - self.center
        ranges = self._inserted_ranges(xyz)
        r_min, r_max = self._bounds(ranges)
        if not self._local_applies(n - int(cleared.sum()) + k, r_min, r_max, method):
            raise ValueError("the per-point test does not apply to this set (see applies)")
        removed_inserted = np.zeros(k, dtype=bool)
        positions = self._add(rel, ranges)
        absent = np.zeros(n + k, dtype=bool)
        absent[:n] = cleared[self._order]
        decide = partial(self._verdicts, self._scene(n + k, absent, r_min))
        verdicts = decide(n + np.arange(k))
        removed_inserted[positions] = verdicts == _VERDICT_REMOVE
        undecided = positions[verdicts == _VERDICT_UNDECIDED_WITH]
        if len(undecided):
            nothing = np.zeros(0, dtype=np.int64)
            removed_inserted[undecided] = self._undecided(
                nothing, nothing, undecided, cleared, xyz
            )[1]
        return GridInsertion(self, cleared, xyz, removed_inserted, decide)

    def _inserted_ranges(self, inserted: np.ndarray) -> np.ndarray:
        """Distances ``(K,)`` of the inserted points from the viewpoint (metres), checked."""
        ranges = _norms(_check_points(inserted) - self.center)
        if not np.isfinite(ranges).all():
            row = int(np.flatnonzero(~np.isfinite(ranges))[0])
            raise DataError(f"inserted points: row {row} is too far from the viewpoint for float64")
        return ranges

    def _bounds(self, ranges: np.ndarray) -> tuple[float, float]:
        """The least and greatest range of the frame's points and ``ranges`` (metres)."""
        r_min = min(self._r_min, float(ranges.min(initial=np.inf)))
        return r_min, max(self._r_max, float(ranges.max(initial=0.0)))

    def groups_apply(self, samples: np.ndarray) -> bool:
        """Whether :meth:`hidden_groups` decides ``samples`` ``(S, 3)`` (metres) against this
        frame: the per-point test applies to the frame with them (``R`` above every range, no
        point at the viewpoint), or there is nothing to decide (no samples, no frame point).
        Where it does not, the caller decides (DR.CPO: no group hidden)."""
        xyz = _check_points(samples)
        if not len(xyz) or not self.size:
            return True
        return self._samples_apply(_norms(xyz - self.center))

    def _samples_apply(self, ranges: np.ndarray) -> bool:
        """:meth:`groups_apply` for samples at distances ``ranges`` ``(S,)`` (metres, S > 0)."""
        if not np.isfinite(ranges).all():
            return False
        r_min = min(self._r_min, float(ranges.min()))
        r_max = max(self._r_max, float(ranges.max()))
        return self._local_applies(self.size, r_min, r_max, "local")

    def hidden_groups(
        self,
        samples: np.ndarray,
        offsets: np.ndarray,
        cleared: np.ndarray,
        share: float,
    ) -> np.ndarray:
        """Which groups of ``samples`` are at least ``share`` hidden among the frame's points
        without the ``cleared`` ones (each sample decided exactly, as a point added to them
        alone); only where :meth:`groups_apply` (else ``ValueError``). A group is decided as
        soon as its count allows: samples the plane normal to their ray shows visible first,
        the others then one by one. Samples the test gives up on (its budget of full scans per
        group spent) count as visible.

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
        if not self._samples_apply(ranges):
            raise ValueError(
                "the per-point test does not apply to these samples (see groups_apply)"
            )
        r_min = min(self._r_min, float(ranges.min()))
        order = self._add(rel, ranges)
        position = np.empty(len(xyz), dtype=np.int64)
        position[order] = n + np.arange(len(xyz))
        absent = np.zeros(n + len(xyz), dtype=bool)
        absent[:n] = cleared[self._order]
        rho_max = 2.0 * self.radius - r_min
        cones = _first_cones(ranges, r_min, rho_max)
        sizes = np.diff(offsets)
        allowed = sizes - np.ceil(share * sizes - 1e-9).astype(np.int64)  # visible ones allowed
        scene = self._scene(n + len(xyz), absent, r_min)
        if len(hidden):
            _hidden_groups(position, cones, offsets, allowed, scene, _GROUP_BRUTE_BUDGET, hidden)
        return hidden

    def _verdicts(self, scene: Scene, queries: np.ndarray) -> np.ndarray:
        """:func:`_insertion_verdicts` of the sorted ``queries``."""
        if not len(queries):
            return np.zeros(0, dtype=np.int8)
        cones = _first_cones(self._ranges[queries], scene.r_min, scene.rho_max)
        return _insertion_verdicts(queries, cones, self.size, scene, _BRUTE_BUDGET)

    def _scene(self, count: int, absent: np.ndarray, r_min: float) -> Scene:
        """The kernels' view of the first ``count`` sorted points, ``absent`` ones skipped;
        ``r_min``: the least range among them (metres)."""
        used = slice(0, count)
        origin, size, rows, columns = self._geometry
        return Scene(
            rays=self._rays[used],
            rel=self._rel[used],
            ranges=self._ranges[used],
            rho=self._rho[used],
            elevation=self._elevation[used],
            azimuth=self._azimuth[used],
            starts=self._starts,
            absent=absent,
            origin=origin,
            size=size,
            rows=rows,
            columns=columns,
            radius=self.radius,
            r_min=r_min,
            rho_max=2.0 * self.radius - r_min,
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


class GridInsertion:
    """The state of e-HPR's inserted scope on a :class:`FrameGrid` after step 1
    (:meth:`FrameGrid.insert`): the inserted points decided, the frame points not yet.

    Attributes:
        removed_inserted: ``bool (K,)`` inserted points to remove (hidden).
        cleared: ``bool (N,)`` the frame points taken out.
    """

    def __init__(
        self,
        grid: FrameGrid,
        cleared: np.ndarray,
        inserted: np.ndarray,
        removed_inserted: np.ndarray,
        decide: Callable[[np.ndarray], np.ndarray],
    ) -> None:
        self._grid = grid
        self.cleared = cleared
        self._inserted = inserted
        self.removed_inserted = removed_inserted
        self._decide = decide

    def hidden_behind(self, behind: np.ndarray) -> np.ndarray:
        """Step 2: ``bool (N,)`` frame points of ``behind`` (``bool (N,)``; cleared ones are
        ignored) to remove: hidden with the inserted points, visible without them. Valid
        until the grid's next :meth:`FrameGrid.insert`."""
        grid = self._grid
        n = grid.size
        removed = np.zeros(n, dtype=bool)
        behind = _check_query(behind, n) & ~self.cleared
        if not behind.any():
            return removed
        queries = np.flatnonzero(behind[grid._order])
        verdicts = self._decide(queries)
        frame_rows = grid._order[queries]
        removed[frame_rows] = verdicts == _VERDICT_REMOVE
        pending = verdicts >= _VERDICT_UNDECIDED_WITHOUT
        if pending.any():
            removed[frame_rows[pending]] = grid._undecided(
                verdicts[pending],
                frame_rows[pending],
                np.zeros(0, np.int64),
                self.cleared,
                self._inserted,
            )[0]
        return removed
