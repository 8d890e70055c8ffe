"""One LiDAR sweep of a :class:`~drcpo.synth.world.World`: returns with noise, dropouts and
intensity, plus the noise-free first hit of every ray (the truth the labels are computed from)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drcpo.synth.raycast import GROUND, MISS, RayHits, Scene
from drcpo.synth.sensor import LidarConfig, RayGrid, ray_grid
from drcpo.synth.solids import ALBEDO, EXTRA_DROPOUT
from drcpo.synth.world import World

__all__ = ["Sweep", "Visibility", "actor_visibility", "occlusion_level", "scan", "scan_rays"]

_GRAZING_COS = 0.15  # below this |cos(incidence)| returns get weak and drop out more often


@dataclass(frozen=True, eq=False)
class Sweep:
    """The result of one sweep.

    Attributes:
        points: ``float32 (N, 4)`` x, y, z (metres, LiDAR frame), intensity in ``[0, 1]``.
        owner: ``int32 (N,)`` actor index each point came from, -1 for the static world.
        ray: ``int64 (N,)`` index of each point's ray in ``grid``.
        grid: the sweep's rays.
        hits: noise-free first hits of *all* rays (``t`` is ``inf`` for misses).
        ray_owner: ``int32 (R,)`` actor index of each ray's first hit, -1 for anything else.
    """

    points: np.ndarray
    owner: np.ndarray
    ray: np.ndarray
    grid: RayGrid
    hits: RayHits
    ray_owner: np.ndarray


def scan(world: World, rng: np.random.Generator, config: LidarConfig | None = None) -> Sweep:
    """Sweep ``world`` with the sensor at the origin (fires every beam at every azimuth column)."""
    config = config or LidarConfig()
    step = 2 * np.pi / config.num_columns
    grid = ray_grid(config, azimuth_offset=rng.uniform(0, step))
    return scan_rays(world, grid, rng, config)


def scan_rays(
    world: World, grid: RayGrid, rng: np.random.Generator, config: LidarConfig, scene=None
) -> Sweep:
    """Sweep with the given rays (``scene`` defaults to the world's own)."""
    scene: Scene = scene or world.scene
    hits = scene.cast(grid.directions, config.max_range)
    solids = scene.solids
    ray_owner = np.full(len(hits.hit), -1, dtype=np.int32)
    on_solid = hits.hit >= 0
    ray_owner[on_solid] = solids.owner[hits.hit[on_solid]]

    ray = np.flatnonzero((hits.hit != MISS) & (hits.t >= config.min_range))
    direction, t = grid.directions[ray], hits.t[ray]
    xyz = direction * t[:, None]
    hit = hits.hit[ray]
    material = np.empty(len(ray), dtype=np.int64)
    ground = hit == GROUND
    material[ground] = world.ground_material(xyz[ground, 0], xyz[ground, 1])
    material[~ground] = solids.material[hit[~ground]]

    cos_incidence = np.abs(np.einsum("ij,ij->i", hits.normal[ray], direction))
    albedo = ALBEDO[material]
    intensity = albedo * (0.15 + 0.85 * cos_incidence)
    intensity += rng.normal(0.0, config.intensity_noise, len(ray))
    intensity = np.round(np.clip(intensity, 0.0, 1.0), 2)

    grazing = np.clip((_GRAZING_COS - cos_incidence) / _GRAZING_COS, 0.0, 1.0)
    weak = (t / config.max_range) ** 2 * (1.0 - albedo)
    p_drop = config.dropout + EXTRA_DROPOUT[material] + 0.5 * grazing + 0.3 * weak
    kept = rng.random(len(ray)) >= p_drop

    noisy_t = t + rng.normal(0.0, config.range_noise, len(ray))
    xyz = direction * noisy_t[:, None]
    points = np.column_stack([xyz, intensity])[kept].astype(np.float32)
    return Sweep(points, ray_owner[ray][kept], ray[kept], grid, hits, ray_owner)


@dataclass(frozen=True, eq=False)
class Visibility:
    """Per actor ray counts: ``reachable`` rays would hit the actor alone, ``seen`` of them hit
    it first in the full world. ``blocked = 1 - seen / reachable`` (``nan`` when unreachable)."""

    reachable: np.ndarray
    seen: np.ndarray

    @property
    def blocked(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.reachable > 0, 1.0 - self.seen / self.reachable, np.nan)


def actor_visibility(world: World, sweep: Sweep, config: LidarConfig | None = None) -> Visibility:
    """Which of the rays that would reach each actor (alone) reach it first in the world."""
    config = config or LidarConfig()
    solids = world.scene.solids
    grid = sweep.grid
    beams = len(grid.elevation)
    reachable = np.zeros(len(world.actors), dtype=np.int64)
    seen = np.zeros(len(world.actors), dtype=np.int64)
    for i in range(len(world.actors)):
        own = solids.take(np.flatnonzero(solids.owner == i))
        columns = _columns_facing(own, grid.azimuth)
        if len(columns) == 0:
            continue
        rays = (np.arange(beams)[:, None] * grid.num_columns + columns[None, :]).ravel()
        alone = Scene(own, None, num_bins=64).cast(grid.directions[rays], config.max_range)
        hit_alone = alone.hit != MISS
        reachable[i] = hit_alone.sum()
        seen[i] = (hit_alone & (sweep.ray_owner[rays] == i)).sum()
    return Visibility(reachable, seen)


def _columns_facing(solids, azimuth: np.ndarray) -> np.ndarray:
    """Indices of the sorted column ``azimuth`` values inside the solids' azimuth span."""
    centre_angle = np.arctan2(solids.centre[:, 1], solids.centre[:, 0])
    dist = np.hypot(solids.centre[:, 0], solids.centre[:, 1])
    radius = solids.horizontal_radius()
    if (dist <= radius).any():
        return np.arange(len(azimuth))
    half = np.arcsin(radius / dist)
    # Angles relative to the first solid's direction keep the span contiguous across -pi/pi.
    ref = centre_angle[0]
    rel = np.angle(np.exp(1j * (centre_angle - ref)))
    lo, hi = ref + (rel - half).min(), ref + (rel + half).max()
    rel_columns = np.angle(np.exp(1j * (azimuth - lo)))
    rel_columns = np.where(rel_columns < 0, rel_columns + 2 * np.pi, rel_columns)
    return np.flatnonzero(rel_columns <= hi - lo + 1e-9)


def occlusion_level(blocked: np.ndarray) -> np.ndarray:
    """KITTI occlusion level ``int8`` from the blocked fraction of an object's rays.

    0 fully visible (under 10 % blocked), 1 partly occluded (under 50 %), 2 largely occluded,
    3 unknown (no ray reaches the object, ``nan``).
    """
    blocked = np.asarray(blocked, dtype=np.float64)
    level = np.where(blocked < 0.1, 0, np.where(blocked < 0.5, 1, 2))
    return np.where(np.isnan(blocked), 3, level).astype(np.int8)
