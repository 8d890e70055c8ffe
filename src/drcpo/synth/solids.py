"""Solids the synthetic world is made of: yaw-oriented boxes, ellipsoids and vertical cylinders.

A :class:`Solids` holds many solids as parallel arrays. ``half`` is the box's half size, the
ellipsoid's radii, or ``(radius, radius, half height)`` for a cylinder, all in the solid's own frame
(rotated by ``yaw`` about z around ``centre``). ``owner`` is the object (actor) a solid belongs
to, or -1 for the static world; ``material`` indexes :data:`MATERIALS`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drcpo.geometry import rotate_points_z

__all__ = [
    "ALBEDO",
    "BOX",
    "CYLINDER",
    "ELLIPSOID",
    "EXTRA_DROPOUT",
    "MATERIALS",
    "MATERIAL_ID",
    "MATERIAL_NAMES",
    "Solids",
    "make_solids",
]

BOX, ELLIPSOID, CYLINDER = 0, 1, 2

#: name -> (albedo, extra dropout probability). Glass returns little; paint and signs a lot.
MATERIALS: dict[str, tuple[float, float]] = {
    "asphalt": (0.18, 0.0),
    "marking": (0.75, 0.0),
    "concrete": (0.32, 0.0),
    "grass": (0.28, 0.02),
    "facade": (0.40, 0.0),
    "window": (0.10, 0.65),
    "metal": (0.45, 0.0),
    "sign": (0.90, 0.0),
    "bark": (0.25, 0.0),
    "foliage": (0.30, 0.25),
    "paint": (0.50, 0.0),
    "dark_paint": (0.15, 0.05),
    "glass": (0.08, 0.5),
    "tyre": (0.05, 0.1),
    "cloth": (0.30, 0.02),
    "skin": (0.40, 0.0),
    "plastic": (0.35, 0.0),
}
MATERIAL_NAMES: tuple[str, ...] = tuple(MATERIALS)
MATERIAL_ID: dict[str, int] = {name: i for i, name in enumerate(MATERIAL_NAMES)}
ALBEDO = np.array([MATERIALS[n][0] for n in MATERIAL_NAMES])
EXTRA_DROPOUT = np.array([MATERIALS[n][1] for n in MATERIAL_NAMES])


@dataclass(frozen=True, eq=False)
class Solids:
    """Many solids as parallel arrays (see the module docstring).

    Attributes:
        kind: ``int8 (S,)`` BOX, ELLIPSOID or CYLINDER.
        centre: ``float64 (S, 3)`` metres.
        half: ``float64 (S, 3)`` metres, positive.
        yaw: ``float64 (S,)`` radians about +z.
        material: ``int16 (S,)`` index into :data:`MATERIAL_NAMES`.
        owner: ``int32 (S,)`` actor index, -1 for static solids.
    """

    kind: np.ndarray
    centre: np.ndarray
    half: np.ndarray
    yaw: np.ndarray
    material: np.ndarray
    owner: np.ndarray

    def __post_init__(self) -> None:
        n = len(np.asarray(self.kind))
        casts = {
            "kind": (np.int8, (n,)),
            "centre": (np.float64, (n, 3)),
            "half": (np.float64, (n, 3)),
            "yaw": (np.float64, (n,)),
            "material": (np.int16, (n,)),
            "owner": (np.int32, (n,)),
        }
        for name, (dtype, shape) in casts.items():
            value = np.asarray(getattr(self, name), dtype=dtype).reshape(shape)
            object.__setattr__(self, name, value)
        if n and (self.half <= 0).any():
            raise ValueError("Solids.half must be positive")

    def __len__(self) -> int:
        return len(self.kind)

    @classmethod
    def empty(cls) -> Solids:
        return cls(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), [], [], [])

    @classmethod
    def concatenate(cls, parts: Sequence[Solids]) -> Solids:
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        return cls(
            *(
                np.concatenate([getattr(p, f) for p in parts])
                for f in ("kind", "centre", "half", "yaw", "material", "owner")
            )
        )

    def take(self, rows: np.ndarray) -> Solids:
        return Solids(
            self.kind[rows],
            self.centre[rows],
            self.half[rows],
            self.yaw[rows],
            self.material[rows],
            self.owner[rows],
        )

    def with_owner(self, owner: int) -> Solids:
        return Solids(
            self.kind, self.centre, self.half, self.yaw, self.material, np.full(len(self), owner)
        )

    def placed(self, x: float, y: float, z: float, yaw: float) -> Solids:
        """These solids (given in an object's frame) moved to pose ``(x, y, z, yaw)``."""
        centre = rotate_points_z(self.centre, yaw) + np.array([x, y, z])
        return Solids(self.kind, centre, self.half, self.yaw + yaw, self.material, self.owner)

    def horizontal_radius(self) -> np.ndarray:
        """Radius ``(S,)`` of a vertical cylinder about each centre that holds the solid."""
        return np.where(
            self.kind == BOX,
            np.hypot(self.half[:, 0], self.half[:, 1]),
            np.maximum(self.half[:, 0], self.half[:, 1]),
        )

    def local_extent(self) -> np.ndarray:
        """Axis-aligned half extents ``(S, 3)`` of each solid in the frame its yaw is relative to.

        Exact for every kind: a rotated box's extent comes from its corners, an ellipsoid's from
        its radii, a vertical cylinder's is its radius.
        """
        cos, sin = np.abs(np.cos(self.yaw)), np.abs(np.sin(self.yaw))
        hx, hy, hz = self.half.T
        box = np.column_stack([cos * hx + sin * hy, sin * hx + cos * hy, hz])
        ellipsoid = np.column_stack(
            [np.hypot(cos * hx, sin * hy), np.hypot(sin * hx, cos * hy), hz]
        )
        cylinder = np.column_stack([hx, hx, hz])
        kind = self.kind[:, None]
        return np.where(kind == BOX, box, np.where(kind == ELLIPSOID, ellipsoid, cylinder))

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Tight axis-aligned bounds ``(3,)`` low and high over all solids."""
        extent = self.local_extent()
        return (self.centre - extent).min(axis=0), (self.centre + extent).max(axis=0)

    def contains(self, points: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """``bool (N, K)``: point n is strictly inside solid ``rows[k]`` (default: every solid)."""
        rows = np.arange(len(self)) if rows is None else np.asarray(rows)
        xyz = np.asarray(points, dtype=np.float64)[:, :3]
        out = np.zeros((len(xyz), len(rows)), dtype=bool)
        for k, s in enumerate(rows):
            local = _to_local(xyz, self.centre[s], self.yaw[s]) / self.half[s]
            if self.kind[s] == BOX:
                out[:, k] = (np.abs(local) < 1.0).all(axis=1)
            elif self.kind[s] == ELLIPSOID:
                out[:, k] = (local**2).sum(axis=1) < 1.0
            else:
                out[:, k] = (local[:, 0] ** 2 + local[:, 1] ** 2 < 1.0) & (
                    np.abs(local[:, 2]) < 1.0
                )
        return out

    def surface_samples(
        self, rng: np.random.Generator, spacing: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Points on the solids' outer surface, about one per ``spacing`` x ``spacing`` m^2.

        Samples that fall strictly inside another solid with the same owner (a wheel inside the
        body, say) are dropped: they are not on the object's outside. Returns ``(points (N, 3),
        solid row (N,))``.
        """
        if spacing <= 0:
            raise ValueError("spacing must be positive")
        chunks, rows = [], []
        for s in range(len(self)):
            local = _sample_solid(int(self.kind[s]), self.half[s], rng, spacing)
            chunks.append(_from_local(local, self.centre[s], self.yaw[s]))
            rows.append(np.full(len(local), s))
        if not chunks:
            return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
        points, row = np.concatenate(chunks), np.concatenate(rows)
        keep = np.ones(len(points), dtype=bool)
        for owner in np.unique(self.owner):
            members = np.flatnonzero(self.owner == owner)
            mine = np.isin(row, members)
            inside = self.contains(points[mine], members)
            # A sample never counts as inside its own solid.
            inside[row[mine][:, None] == members[None, :]] = False
            keep[np.flatnonzero(mine)[inside.any(axis=1)]] = False
        return points[keep], row[keep]


def _to_local(xyz: np.ndarray, centre: np.ndarray, yaw: float) -> np.ndarray:
    return rotate_points_z(xyz - centre, -yaw)


def _from_local(local: np.ndarray, centre: np.ndarray, yaw: float) -> np.ndarray:
    return rotate_points_z(local, yaw) + centre


def _sample_solid(kind: int, half: np.ndarray, rng: np.random.Generator, spacing: float):
    hx, hy, hz = half
    if kind == BOX:
        areas = 8.0 * np.array([hy * hz, hx * hz, hx * hy])  # both faces of each axis
        n = max(int(np.ceil(areas.sum() / spacing**2)), 6)
        axis = rng.choice(3, size=n, p=areas / areas.sum())
        local = rng.uniform(-1.0, 1.0, (n, 3)) * half
        sign = rng.choice([-1.0, 1.0], size=n)
        local[np.arange(n), axis] = sign * half[axis]
        return local
    if kind == ELLIPSOID:
        # Knud Thomsen's approximation of the ellipsoid's area sets the sample count; directions
        # are thinned by the local area stretch so that samples are even on the surface.
        p = 1.6075
        area = 4 * np.pi * (((hx * hy) ** p + (hx * hz) ** p + (hy * hz) ** p) / 3) ** (1 / p)
        n = max(int(np.ceil(area / spacing**2)), 8)
        unit = rng.normal(size=(3 * n, 3))
        unit /= np.linalg.norm(unit, axis=1, keepdims=True)
        stretch = np.linalg.norm(unit * np.array([hy * hz, hx * hz, hx * hy]), axis=1)
        keep = rng.uniform(0, stretch.max(), len(unit)) < stretch
        return (unit[keep] * half)[:n]
    side, cap = 2 * np.pi * hx * 2 * hz, np.pi * hx**2
    n = max(int(np.ceil((side + 2 * cap) / spacing**2)), 8)
    on_side = rng.uniform(0, side + 2 * cap, n) < side
    angle = rng.uniform(0, 2 * np.pi, n)
    radius = np.where(on_side, hx, hx * np.sqrt(rng.uniform(0, 1, n)))
    z = np.where(on_side, rng.uniform(-hz, hz, n), rng.choice([-hz, hz], size=n))
    return np.column_stack([radius * np.cos(angle), radius * np.sin(angle), z])


def make_solids(rows: Sequence[tuple], owner: int = -1) -> Solids:
    """Solids from rows ``(kind, (cx, cy, cz), (hx, hy, hz), yaw, material_name)``."""
    if not rows:
        return Solids.empty()
    kind, centre, half, yaw, material = zip(*rows, strict=True)
    return Solids(
        np.array(kind),
        np.array(centre, dtype=np.float64),
        np.array(half, dtype=np.float64),
        np.array(yaw, dtype=np.float64),
        np.array([MATERIAL_ID[m] for m in material]),
        np.full(len(rows), owner),
    )
