"""Procedural street worlds: uneven ground, road, sidewalks with kerbs, buildings, poles, trees,
clutter, and parked or moving cars, pedestrians and cyclists.

The world is built in the LiDAR frame of one sweep (sensor at the origin). The street runs roughly
along x; street coordinates ``(u, v)`` are along and across it, with the centre line at ``v = 0``
and the sensor in a lane at ``(0, sensor_v)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from drcpo.errors import ConfigError
from drcpo.geometry import bev_overlap_area
from drcpo.synth.actors import Actor, make_actor
from drcpo.synth.raycast import Ground, Scene
from drcpo.synth.solids import BOX, CYLINDER, ELLIPSOID, MATERIAL_ID, Solids, make_solids

__all__ = [
    "Range",
    "Street",
    "World",
    "WorldConfig",
    "footprints",
    "generate_world",
    "support_height",
]

Range = tuple[float, float]


@dataclass(frozen=True)
class WorldConfig:
    """Parameters of the procedural street (ranges are sampled uniformly per world).

    Lengths in metres; counts are inclusive ranges of how many objects the world tries to place
    (a placement that would overlap another box or an obstacle is skipped).
    """

    half_length: float = 90.0
    road_width: Range = (7.0, 14.0)
    sidewalk_width: Range = (2.0, 4.5)
    kerb_height: Range = (0.1, 0.18)
    street_yaw: Range = (-0.1, 0.1)
    ground_amplitude: Range = (0.02, 0.05)
    ground_wavelength: Range = (30.0, 90.0)
    ground_waves: int = 3
    building_height: Range = (4.0, 22.0)
    building_length: Range = (8.0, 30.0)
    cross_street_probability: float = 0.5
    tree_probability: float = 0.6
    cars: tuple[int, int] = (8, 18)
    moving_car_fraction: float = 0.35
    pedestrians: tuple[int, int] = (2, 10)
    cyclists: tuple[int, int] = (1, 4)
    object_u_range: Range = (-45.0, 75.0)

    def __post_init__(self) -> None:
        for name in (
            "road_width",
            "sidewalk_width",
            "kerb_height",
            "ground_amplitude",
            "ground_wavelength",
            "building_height",
            "building_length",
            "cars",
            "pedestrians",
            "cyclists",
            "object_u_range",
            "street_yaw",
        ):
            low, high = getattr(self, name)
            if not low <= high:
                raise ConfigError(f"WorldConfig.{name} = {(low, high)} must have low <= high")
        if self.road_width[0] < 5.0 or self.half_length < 20.0:
            raise ConfigError("WorldConfig: road_width >= 5 m and half_length >= 20 m required")
        if min(self.cars[0], self.pedestrians[0], self.cyclists[0]) < 0:
            raise ConfigError("WorldConfig: object counts must be non-negative")

    def with_street_angle(self, degrees: float) -> WorldConfig:
        """This configuration with streets at yaws uniform in ``[-degrees, +degrees]`` from the
        sensor's x axis (the default ``street_yaw`` is +-0.1 rad, about 5.7 degrees).

        Parked and moving objects follow the street, so this also spreads their headings.
        Raises :class:`ConfigError` unless ``0 <= degrees <= 90``.
        """
        if not np.isfinite(degrees) or not 0.0 <= degrees <= 90.0:
            raise ConfigError(f"street angle must be in [0, 90] degrees, got {degrees}")
        limit = float(np.radians(degrees))
        return replace(self, street_yaw=(-limit, limit))


@dataclass(frozen=True)
class Street:
    """Street layout: ``yaw`` of its axis, the sensor's across-street offset ``sensor_v``,
    road half width, sidewalk width, kerb height, and an optional cross street at ``cross_u``
    (``cross_half`` metres half width; ``nan`` when there is none)."""

    yaw: float
    sensor_v: float
    road_half: float
    sidewalk: float
    kerb: float
    cross_u: float = float("nan")
    cross_half: float = 0.0

    def to_street(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cos, sin = np.cos(self.yaw), np.sin(self.yaw)
        return cos * x + sin * y, -sin * x + cos * y + self.sensor_v

    def to_lidar(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cos, sin = np.cos(self.yaw), np.sin(self.yaw)
        v = np.asarray(v) - self.sensor_v
        return cos * u - sin * v, sin * u + cos * v

    def in_cross(self, u: np.ndarray, margin: float = 0.0) -> np.ndarray:
        if np.isnan(self.cross_u):
            return np.zeros(np.shape(u), dtype=bool)
        return np.abs(np.asarray(u) - self.cross_u) <= self.cross_half + margin


@dataclass(frozen=True, eq=False)
class World:
    """One procedural world in the LiDAR frame of the sensor at the origin.

    Attributes:
        ground: the height field.
        street: the street layout.
        static: solids of the static world (owner -1).
        actors: the placed objects; actor i has box ``boxes[i]`` and class ``names[i]``.
        boxes: ``float64 (M, 7)`` tight boxes of the actors (OpenPCDet convention).
        names: ``(M,)`` class names.
    """

    ground: Ground
    street: Street
    static: Solids
    actors: tuple[Actor, ...]
    boxes: np.ndarray
    names: np.ndarray
    sidewalks: Solids = field(default_factory=Solids.empty)
    obstacles: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))

    def support_height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height (metres) of what stands at ``x, y``: a sidewalk's top, else the ground."""
        return support_height(self.ground, self.sidewalks, x, y)

    def free(self, boxes: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """``bool (B,)``: boxes ``(B, 7)`` whose footprint (grown by ``margin``) overlaps no
        actor's box and no obstacle (walls, poles, trunks, clutter)."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7).copy()
        boxes[:, 3:5] += 2 * margin
        taken = np.concatenate([_ActorPlacer.EGO, self.obstacles, self.boxes])
        return ~(bev_overlap_area(boxes, taken) > 0).any(axis=1)

    @cached_property
    def solids(self) -> Solids:
        """Every solid: the static world, then each actor's (owner = actor index)."""
        placed = [
            a.placed(b, i) for i, (a, b) in enumerate(zip(self.actors, self.boxes, strict=True))
        ]
        return Solids.concatenate([self.static, *placed])

    @cached_property
    def scene(self) -> Scene:
        return Scene(self.solids, self.ground)

    def with_extra(self, extra: Solids) -> Scene:
        """A scene of this world plus ``extra`` solids (their rows follow :attr:`solids`)."""
        return Scene(Solids.concatenate([self.solids, extra]), self.ground)

    def ground_material(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Material ids ``(N,)`` of the bare ground at ``x, y``: asphalt, road markings, grass."""
        s = self.street
        u, v = s.to_street(np.asarray(x), np.asarray(y))
        road = (np.abs(v) <= s.road_half) | s.in_cross(u)
        centre_line = (np.abs(v) < 0.075) & (np.mod(u, 9.0) < 3.0) & ~s.in_cross(u)
        edge_line = (np.abs(np.abs(v) - (s.road_half - 0.35)) < 0.06) & ~s.in_cross(u)
        material = np.where(road, MATERIAL_ID["asphalt"], MATERIAL_ID["grass"])
        return np.where(road & (centre_line | edge_line), MATERIAL_ID["marking"], material)


def generate_world(
    rng: np.random.Generator, config: WorldConfig | None = None, mount_height: float = 1.73
) -> World:
    """A random street world; the same generator state gives the same world."""
    config = config or WorldConfig()
    ground = _random_ground(rng, config, mount_height)
    street = _random_street(rng, config)
    builder = _StaticBuilder(street, ground, config.half_length)
    slabs = builder.sidewalks()
    buildings = builder.buildings(rng, config)
    poles, trees, clutter = builder.poles(rng), builder.trees(rng, config), builder.clutter(rng)
    static = Solids.concatenate([slabs, buildings, poles, trees, clutter])
    obstacles = footprints(Solids.concatenate([buildings, poles, trees, clutter]))
    placer = _ActorPlacer(rng, street, ground, slabs, obstacles)
    placer.place_all(config)
    return World(
        ground=ground,
        street=street,
        static=static,
        actors=tuple(placer.actors),
        boxes=np.array(placer.boxes, dtype=np.float64).reshape(-1, 7),
        names=np.array([a.name for a in placer.actors], dtype=str),
        sidewalks=slabs,
        obstacles=obstacles,
    )


def support_height(ground: Ground, sidewalks: Solids, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height (metres) at ``x, y`` of a sidewalk slab's top where one is, else of the ground."""
    x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    z = ground.height(x, y)
    s = sidewalks
    if len(s) == 0:
        return z
    dx = x[..., None] - s.centre[:, 0]
    dy = y[..., None] - s.centre[:, 1]
    cos, sin = np.cos(s.yaw), np.sin(s.yaw)
    under = (np.abs(cos * dx + sin * dy) <= s.half[:, 0]) & (
        np.abs(-sin * dx + cos * dy) <= s.half[:, 1]
    )
    top = np.where(under, s.centre[:, 2] + s.half[:, 2], -np.inf).max(axis=-1)
    return np.maximum(z, top)


def _random_ground(rng: np.random.Generator, config: WorldConfig, mount_height: float) -> Ground:
    k = config.ground_waves
    wavelength = rng.uniform(*config.ground_wavelength, k)
    direction = rng.uniform(0, 2 * np.pi, k)
    wave = 2 * np.pi / wavelength
    return Ground(
        -mount_height,
        rng.uniform(*config.ground_amplitude, k),
        wave * np.cos(direction),
        wave * np.sin(direction),
        rng.uniform(0, 2 * np.pi, k),
    )


def _random_street(rng: np.random.Generator, config: WorldConfig) -> Street:
    road_half = rng.uniform(*config.road_width) / 2
    sensor_v = -rng.uniform(1.2, max(1.3, road_half - 1.6))
    cross_u, cross_half = float("nan"), 0.0
    if rng.random() < config.cross_street_probability:
        cross_u = float(rng.choice([-1, 1], p=[0.3, 0.7]) * rng.uniform(15, 60))
        cross_half = rng.uniform(4.0, 7.0)
    return Street(
        yaw=float(rng.uniform(*config.street_yaw)),
        sensor_v=float(sensor_v),
        road_half=float(road_half),
        sidewalk=float(rng.uniform(*config.sidewalk_width)),
        kerb=float(rng.uniform(*config.kerb_height)),
        cross_u=cross_u,
        cross_half=float(cross_half),
    )


class _StaticBuilder:
    """Static solids laid out in street coordinates and moved to the LiDAR frame."""

    SLAB_LENGTH = 10.0

    def __init__(self, street: Street, ground: Ground, half_length: float) -> None:
        self.street, self.ground, self.half_length = street, ground, half_length

    def _solid(self, kind, u, v, z_bottom_above_ground, height, half_uv, material, yaw=0.0):
        """A solid standing on the ground at (u, v), ``height`` tall, bottom offset from ground."""
        x, y = self.street.to_lidar(u, v)
        base = float(self.ground.height(x, y))
        z = base + z_bottom_above_ground + height / 2
        half = (half_uv[0], half_uv[1], height / 2)
        return (kind, (float(x), float(y), z), half, self.street.yaw + yaw, material)

    def _segments(self, rng, length: Range, gap_probability: float, gap: Range):
        u = -self.half_length
        while u < self.half_length:
            span = rng.uniform(*length)
            yield u, min(u + span, self.half_length)
            u += span + (rng.uniform(*gap) if rng.random() < gap_probability else 0.0)

    def _clear_of_cross(self, start: float, end: float, margin: float) -> list[tuple[float, float]]:
        s = self.street
        if np.isnan(s.cross_u):
            return [(start, end)]
        lo, hi = s.cross_u - s.cross_half - margin, s.cross_u + s.cross_half + margin
        pieces = [(start, min(end, lo)), (max(start, hi), end)]
        return [(a, b) for a, b in pieces if b - a > 0.5]

    def sidewalks(self) -> Solids:
        s, rows = self.street, []
        depth = 0.5  # the slab reaches below the uneven ground, so no gap shows under the kerb
        edges = np.arange(-self.half_length, self.half_length, self.SLAB_LENGTH)
        for side in (-1, 1):
            v = side * (s.road_half + s.sidewalk / 2)
            for start in edges:
                for a, b in self._clear_of_cross(start, start + self.SLAB_LENGTH, 0.0):
                    rows.append(
                        self._solid(
                            BOX,
                            (a + b) / 2,
                            v,
                            -depth,
                            s.kerb + depth,
                            ((b - a) / 2, s.sidewalk / 2),
                            "concrete",
                        )
                    )
        return make_solids(rows)

    def buildings(self, rng: np.random.Generator, config: WorldConfig) -> Solids:
        s, rows = self.street, []
        for side in (-1, 1):
            for start, end in self._segments(rng, config.building_length, 0.35, (1.0, 8.0)):
                for a, b in self._clear_of_cross(start, end, 1.0):
                    setback = rng.uniform(0.0, 2.5)
                    depth = rng.uniform(6.0, 15.0)
                    height = rng.uniform(*config.building_height)
                    facade_v = s.road_half + s.sidewalk + setback
                    v = side * (facade_v + depth / 2)
                    rows.append(
                        self._solid(
                            BOX,
                            (a + b) / 2,
                            v,
                            -0.5,
                            height + 0.5,
                            ((b - a) / 2, depth / 2),
                            "facade",
                        )
                    )
                    rows += self._ribbon_windows(rng, a, b, side, facade_v, height)
        return make_solids(rows)

    def _ribbon_windows(self, rng, a, b, side, facade_v, height):
        """Glass bands 3 cm proud of the facade, one per storey (glass returns little)."""
        if b - a < 3.0 or rng.random() < 0.25:
            return []
        first = rng.uniform(0.9, 3.5)
        levels = np.arange(first, height - 1.2, 3.0)
        v = side * (facade_v - 0.015)
        return [
            self._solid(BOX, (a + b) / 2, v, z, 1.4, ((b - a) / 2 - 0.5, 0.03), "window")
            for z in levels
        ]

    def poles(self, rng: np.random.Generator) -> Solids:
        s, rows = self.street, []
        for side in (-1, 1):
            u = -self.half_length + rng.uniform(0, 20)
            v = side * (s.road_half + 0.35)
            while u < self.half_length:
                if not s.in_cross(u, 1.0):
                    radius, height = rng.uniform(0.07, 0.15), rng.uniform(3.0, 9.0)
                    rows.append(
                        self._solid(
                            CYLINDER, u, v, s.kerb - 0.2, height + 0.2, (radius, radius), "metal"
                        )
                    )
                    if rng.random() < 0.35:
                        rows.append(
                            self._solid(
                                BOX, u, v - side * 0.05, s.kerb + 2.2, 0.6, (0.03, 0.3), "sign"
                            )
                        )
                u += rng.uniform(12, 35)
        return make_solids(rows)

    def trees(self, rng: np.random.Generator, config: WorldConfig) -> Solids:
        s, rows = self.street, []
        for side in (-1, 1):
            if rng.random() >= config.tree_probability:
                continue
            u = -self.half_length + rng.uniform(0, 12)
            v = side * (s.road_half + s.sidewalk * 0.65)
            while u < self.half_length:
                if not s.in_cross(u, 2.0):
                    trunk_r, trunk_h = rng.uniform(0.1, 0.22), rng.uniform(1.8, 3.2)
                    crown_r, crown_h = rng.uniform(1.2, 2.6), rng.uniform(1.4, 2.8)
                    rows.append(
                        self._solid(
                            CYLINDER, u, v, s.kerb - 0.2, trunk_h + 0.2, (trunk_r, trunk_r), "bark"
                        )
                    )
                    rows.append(
                        self._solid(
                            ELLIPSOID,
                            u,
                            v,
                            s.kerb + trunk_h - 0.3 * crown_h,
                            2 * crown_h,
                            (crown_r, crown_r),
                            "foliage",
                        )
                    )
                u += rng.uniform(7, 18)
        return make_solids(rows)

    def clutter(self, rng: np.random.Generator) -> Solids:
        """Unlabelled bins and boxes on the sidewalks (like KITTI's unlabelled street furniture)."""
        s, rows = self.street, []
        for _ in range(rng.integers(0, 7)):
            u = rng.uniform(-self.half_length + 5, self.half_length - 5)
            if s.in_cross(u, 1.0):
                continue
            v = rng.choice([-1, 1]) * (s.road_half + rng.uniform(0.6, s.sidewalk - 0.4))
            size = rng.uniform(0.4, 0.9, 2)
            rows.append(
                self._solid(
                    BOX,
                    u,
                    v,
                    s.kerb,
                    rng.uniform(0.8, 1.3),
                    size / 2,
                    "plastic",
                    yaw=rng.uniform(0, np.pi),
                )
            )
        return make_solids(rows)


def footprints(solids: Solids) -> np.ndarray:
    """BEV boxes ``(S, 7)`` covering each solid's footprint (tree crowns by their trunks' box).

    Foliage is skipped: objects may stand under tree crowns but not in trunks, poles or walls.
    """
    keep = solids.material != MATERIAL_ID["foliage"]
    s = solids.take(np.flatnonzero(keep))
    half = np.where((s.kind == CYLINDER)[:, None], s.half[:, [0, 0]], s.half[:, :2])
    return np.column_stack([s.centre, 2 * half, 2 * s.half[:, 2:3], s.yaw])


class _ActorPlacer:
    """Places actors one by one, skipping any whose box would overlap a box or an obstacle."""

    EGO = np.array([[-0.5, 0.0, -1.0, 7.0, 2.6, 2.0, 0.0]])  # the recording car around the sensor

    def __init__(self, rng, street: Street, ground: Ground, slabs: Solids, obstacles: np.ndarray):
        self.rng, self.street, self.ground, self.slabs = rng, street, ground, slabs
        self.blocked = np.concatenate([self.EGO, obstacles])
        self.actors: list[Actor] = []
        self.boxes: list[np.ndarray] = []

    def try_place(self, name: str, u: float, v: float, heading_uv: float, margin: float) -> bool:
        actor = make_actor(name, self.rng)
        x, y = self.street.to_lidar(u, v)
        heading = float(
            np.arctan2(np.sin(heading_uv + self.street.yaw), np.cos(heading_uv + self.street.yaw))
        )
        ground_z = float(support_height(self.ground, self.slabs, x, y))
        box = actor.box(float(x), float(y), ground_z, heading)
        grown = box.copy()
        grown[3:5] += 2 * margin
        others = np.concatenate([self.blocked, np.array(self.boxes).reshape(-1, 7)])
        if (bev_overlap_area(grown[None], others) > 0).any():
            return False
        self.actors.append(actor)
        self.boxes.append(box)
        return True

    def place_all(self, config: WorldConfig) -> None:
        rng, s = self.rng, self.street
        lo, hi = config.object_u_range
        cars = rng.integers(config.cars[0], config.cars[1] + 1)
        for _ in range(cars):
            u = rng.uniform(lo, hi)
            if rng.random() < config.moving_car_fraction:
                self._moving_car(u)
            elif not s.in_cross(u, 3.0):
                side = rng.choice([-1, 1])
                v = side * (s.road_half - 0.9 - rng.uniform(0.1, 0.35))
                heading = (0.0 if side < 0 else np.pi) + (np.pi if rng.random() < 0.15 else 0.0)
                self.try_place("Car", u, v, heading + rng.normal(0, 0.04), 0.3)
        for _ in range(rng.integers(config.pedestrians[0], config.pedestrians[1] + 1)):
            self._pedestrian_group(rng.uniform(lo, hi))
        for _ in range(rng.integers(config.cyclists[0], config.cyclists[1] + 1)):
            u, side = rng.uniform(lo, hi), rng.choice([-1, 1])
            v = side * (s.road_half - rng.uniform(0.7, 1.4))
            self.try_place("Cyclist", u, v, (0.0 if side < 0 else np.pi) + rng.normal(0, 0.08), 0.4)

    def _moving_car(self, u: float) -> None:
        rng, s = self.rng, self.street
        if s.in_cross(u) and rng.random() < 0.7:
            v = rng.choice([-1, 1]) * rng.uniform(s.road_half + 3, 60)
            lane = rng.choice([-1, 1])
            heading = lane * np.pi / 2
            self.try_place("Car", s.cross_u - lane * s.cross_half / 2, v, heading, 0.8)
            return
        lane = rng.choice([-1, 1])
        v = lane * s.road_half / 2 + rng.normal(0, 0.2)
        heading = (0.0 if lane < 0 else np.pi) + rng.normal(0, 0.03)
        self.try_place("Car", u, v, heading, 0.8)

    def _pedestrian_group(self, u: float) -> None:
        rng, s = self.rng, self.street
        if rng.random() < 0.12:
            v0, heading = (
                rng.uniform(-s.road_half + 0.5, s.road_half - 0.5),
                rng.choice([-1, 1]) * np.pi / 2,
            )
        else:
            v0 = rng.choice([-1, 1]) * (s.road_half + rng.uniform(0.5, max(0.6, s.sidewalk - 0.5)))
            heading = rng.uniform(-np.pi, np.pi)
        for k in range(1 if rng.random() < 0.6 else rng.integers(2, 5)):
            du, dv = (rng.uniform(0.6, 1.4, 2) * rng.choice([-1, 1], 2)) if k else (0.0, 0.0)
            self.try_place("Pedestrian", u + du, v0 + dv, heading + rng.normal(0, 0.3), 0.05)
