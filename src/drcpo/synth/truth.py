"""Ground truth for occlusion: which points the sensor at the origin truly sees.

A point is visible when the ray from the sensor towards it meets no surface before it (closer
than ``distance - tolerance``); a point on a surface is therefore visible iff it is the first hit
of its ray. This is the reference HPR-based occlusion is scored against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drcpo.synth.actors import Actor
from drcpo.synth.raycast import MISS, Scene
from drcpo.synth.solids import Solids
from drcpo.synth.world import World

__all__ = ["PlacedObjectTruth", "free_pose", "place_object", "visible_points"]


def visible_points(scene: Scene, points: np.ndarray, tolerance: float = 0.02) -> np.ndarray:
    """``bool (N,)``: points ``(N, 3+)`` (metres, LiDAR frame) that the sensor sees in ``scene``.

    Points within ``tolerance`` metres of the sensor are visible.
    """
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    if not np.isfinite(xyz).all():
        raise ValueError("points must be finite")
    distance = np.linalg.norm(xyz, axis=1)
    near = distance <= tolerance
    directions = xyz / np.where(near, 1.0, distance)[:, None]
    directions[near] = (0.0, 0.0, 1.0)
    hits = scene.cast(directions, np.maximum(distance - tolerance, 0.0))
    return (hits.hit == MISS) | near


@dataclass(frozen=True, eq=False)
class PlacedObjectTruth:
    """Surface samples of an actor placed in a world, and which of them the sensor sees.

    Attributes:
        points: ``float64 (N, 3)`` samples on the actor's outer surface, LiDAR frame.
        self_visible: ``bool (N,)`` visible with the actor alone (self-occlusion only).
        visible: ``bool (N,)`` visible in the world with the actor inserted.
        solids: the actor's solids at its pose (owner ``len(world.actors)``).
    """

    points: np.ndarray
    self_visible: np.ndarray
    visible: np.ndarray
    solids: Solids


def place_object(
    world: World,
    actor: Actor,
    box: np.ndarray,
    rng: np.random.Generator,
    spacing: float = 0.05,
    tolerance: float = 0.02,
) -> PlacedObjectTruth:
    """Place ``actor`` at pose ``box (7,)`` in ``world``; sample it and ray-cast the truth."""
    solids = actor.placed(np.asarray(box, dtype=np.float64), len(world.actors))
    points, _ = solids.surface_samples(rng, spacing)
    self_visible = visible_points(Scene(solids, None, num_bins=64), points, tolerance)
    visible = visible_points(world.with_extra(solids), points, tolerance)
    return PlacedObjectTruth(points, self_visible, visible, solids)


def free_pose(
    world: World,
    actor: Actor,
    rng: np.random.Generator,
    x_range: tuple[float, float] = (5.0, 60.0),
    y_range: tuple[float, float] = (-20.0, 20.0),
    margin: float = 0.2,
    tries: int = 100,
) -> np.ndarray | None:
    """A random box ``(7,)`` for ``actor`` standing on the world's ground (or a sidewalk) inside
    the ranges (metres), overlapping no actor or obstacle; ``None`` after ``tries`` misses."""
    for _ in range(tries):
        x, y = rng.uniform(*x_range), rng.uniform(*y_range)
        box = actor.box(x, y, float(world.support_height(x, y)), rng.uniform(-np.pi, np.pi))
        if world.free(box[None], margin)[0]:
            return box
    return None
