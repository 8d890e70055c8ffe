"""The ``"local"`` method's driver: the set-up's points sorted into the per-point test's grid
(:class:`_LocalState`), the pre-filter and the plane test, and the fallbacks for points the test
gives up on. Imports the grid, flip and kernel modules of :mod:`drcpo.occlusion` only.
"""

from __future__ import annotations

import numpy as np

from drcpo.occlusion.flip import _hull_vertices, _Setup
from drcpo.occlusion.grid import _build_grid, _Grid
from drcpo.occlusion.kernels import (
    _BRUTE_BUDGET,
    _STATE_HIDDEN,
    _STATE_UNRESOLVED,
    _STATE_VISIBLE,
    Scene,
    _classify,
    _radial_pass,
)

__all__: list[str] = []  # internal to drcpo.occlusion, whose __init__ has the API


def _local(setup: _Setup, wanted: np.ndarray) -> np.ndarray:
    """Visible flags ``(M,)`` (``False`` where not wanted) by the per-point plane test."""
    return _LocalState.build(setup).visible(wanted)


def _first_cones(ranges: np.ndarray, r_min: float, rho_max: float) -> np.ndarray:
    """Radius (radians) of the neighbourhood that can cross the plane normal to the ray of a
    point at each of ``ranges`` (see :mod:`~drcpo.occlusion.hpr`), for any set whose ranges are
    at least ``r_min`` (a lower ``r_min`` only widens the cones). In place: no temporary per
    step."""
    cone = np.subtract(ranges, r_min)
    cone /= rho_max
    np.clip(cone, 0, 2, out=cone)
    cone /= 2.0
    np.sqrt(cone, out=cone)
    np.arcsin(cone, out=cone)
    cone *= 2.0
    return cone


def _local_grid(setup: _Setup) -> _Grid:
    """The grid the per-point test sorts the set-up's points into (as :class:`_LocalState`)."""
    r_min = float(setup.ranges.min())
    return _build_grid(setup.rays, _first_cones(setup.ranges, r_min, 2.0 * setup.radius - r_min))


_NONE_ABSENT = np.zeros(0, dtype=bool)  # a Scene's ``absent`` when no point is skipped


class _LocalState:
    """The per-point test's inputs: the points sorted into the grid, as the kernels take them.

    Attributes:
        setup: the set-up.
        order: ``(M,)`` set-up index of each sorted position.
        first_cone: ``(M,)`` sorted first cones, radians.
        scene: the kernels' view of the sorted points.
    """

    def __init__(
        self, setup: _Setup, order: np.ndarray, first_cone: np.ndarray, scene: Scene
    ) -> None:
        self.setup = setup
        self.order = order
        self.first_cone = first_cone
        self.scene = scene

    @property
    def size(self) -> int:
        return len(self.order)

    @property
    def starts(self) -> np.ndarray:
        """``(cells + 1,)`` first sorted position of each grid cell."""
        return self.scene.starts[0]

    @classmethod
    def build(cls, setup: _Setup) -> _LocalState:
        ranges, radius = setup.ranges, setup.radius
        r_min = float(ranges.min())
        rho_max = 2.0 * radius - r_min
        first_cone = _first_cones(ranges, r_min, rho_max)
        grid = _build_grid(setup.rays, first_cone)
        order = grid.order
        sorted_ranges = np.ascontiguousarray(ranges[order])
        scene = Scene(
            rays=setup.rays.take(order, axis=0),  # take: much faster than fancy indexing
            rel=setup.rel.take(order, axis=0),
            ranges=sorted_ranges,
            rho=2.0 * radius - sorted_ranges,
            elevation=grid.elevation,
            azimuth=grid.azimuth,
            starts=grid.starts[None],
            absent=_NONE_ABSENT,
            origin=grid.origin,
            size=grid.size,
            rows=grid.rows,
            columns=grid.columns,
            radius=radius,
            r_min=r_min,
            rho_max=rho_max,
        )
        return cls(setup, order, first_cone[order], scene)

    def visible(self, wanted: np.ndarray) -> np.ndarray:
        """Visible flags ``(M,)`` of the set-up's points (``False`` where not wanted)."""
        order, scene, cones = self.order, self.scene, self.first_cone
        todo = np.flatnonzero(wanted[order])
        settled = _radial_pass(todo, cones, scene)
        pending = todo[~settled]
        visible_sorted = np.zeros(self.size, dtype=bool)
        visible_sorted[todo[settled]] = True
        if len(pending):
            state = _classify(pending, cones, scene, _BRUTE_BUDGET)
            unresolved = state == _STATE_UNRESOLVED
            if unresolved.any():
                state[unresolved] = _resolve_unresolved(pending[unresolved], self)
            visible_sorted[pending] = state == _STATE_VISIBLE
        visible = np.zeros(self.size, dtype=bool)
        visible[order] = visible_sorted
        return visible


def _resolve_unresolved(unresolved: np.ndarray, state: _LocalState) -> np.ndarray:
    """States of the (sorted) points the neighbourhood search gave up on: a full scan each when
    they are few, else (and for any the scan cannot settle) one reference hull."""
    verdicts = np.full(len(unresolved), _STATE_UNRESOLVED, dtype=np.int64)
    if len(unresolved) <= 4 * _BRUTE_BUDGET:
        verdicts = _classify(unresolved, state.first_cone, state.scene, len(unresolved) + 1)
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
