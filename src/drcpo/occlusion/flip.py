"""The spherical flip's inputs (:class:`_Setup`: the points not at the viewpoint, as rays and
ranges) and one Qhull hull of the flipped set (:func:`_hull_vertices`).

Imports :mod:`drcpo.errors` and :mod:`drcpo.occlusion.grid` only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from drcpo.errors import DataError
from drcpo.occlusion.grid import _norms

__all__: list[str] = []  # internal to drcpo.occlusion, whose __init__ has the API

# Points this close to the viewpoint, relative to (1 + max range), count as "at the viewpoint".
_AT_VIEWPOINT = 1e-9


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
