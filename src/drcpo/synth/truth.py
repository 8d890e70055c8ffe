"""Ground truth for occlusion and insertion: which points the sensor at the origin truly sees,
and what it would have recorded had an object really stood where augmentation put one.

A point is visible when the ray from the sensor towards it meets no surface before it (closer
than ``distance - tolerance``); a point on a surface is therefore visible iff it is the first hit
of its ray. This is the reference HPR-based occlusion is scored against.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drcpo.geometry import bev_overlap_area, rotate_points_z, rotation_matrix_z
from drcpo.synth.actors import Actor, make_actor
from drcpo.synth.raycast import MISS, Scene
from drcpo.synth.scan import Sweep, scan_rays
from drcpo.synth.sensor import LidarConfig
from drcpo.synth.solids import BOX, CYLINDER, MATERIAL_NAMES, Solids
from drcpo.synth.world import World

__all__ = [
    "MATERIAL_CATEGORY",
    "InsertedTruth",
    "PlacedObjectTruth",
    "boxes_cut_solids",
    "free_pose",
    "place_object",
    "solid_categories",
    "solids_in_box",
    "true_ground_height",
    "true_inserted_returns",
    "true_object_returns",
    "truth_actor",
    "visible_points",
]


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


# --------------------------------------------------------------------------------------------
# Truth of inserted objects: ground under them, solids they cut into, their returns
# --------------------------------------------------------------------------------------------
#: What each static material belongs to (actors' solids are named after their class).
MATERIAL_CATEGORY: dict[str, str] = {
    "facade": "building",
    "window": "building",
    "metal": "pole",
    "sign": "sign",
    "bark": "trunk",
    "foliage": "crown",
    "plastic": "clutter",
    "concrete": "sidewalk",
}


def true_ground_height(world: World, xy: np.ndarray) -> np.ndarray:
    """``float64 (N,)``: height (metres, LiDAR frame) of what one stands on at points ``xy``
    ``(N, 2+)``: a sidewalk's top where there is one, else the ground."""
    xy = np.atleast_2d(np.asarray(xy, dtype=np.float64))
    return np.asarray(world.support_height(xy[:, 0], xy[:, 1]), dtype=np.float64)


def solid_categories(world: World) -> np.ndarray:
    """``str (S,)``: the category of each row of ``world.solids`` (:data:`MATERIAL_CATEGORY`
    for static solids, the lower-case class name for an actor's)."""
    solids = world.solids
    names = np.array([MATERIAL_CATEGORY.get(name, name) for name in MATERIAL_NAMES], dtype=object)[
        solids.material
    ]
    actor = solids.owner >= 0
    names[actor] = np.char.lower(world.names[solids.owner[actor]].astype(str))
    return names.astype(str)


def solids_in_box(world: World, box: np.ndarray, margin: float = 0.02) -> frozenset[str]:
    """The categories (:func:`solid_categories`: ``building``, ``pole``, ``trunk``, ``car``,
    ...) of the world's solids that intersect ``box (7,)`` shrunk by ``margin`` metres on every
    side (so that a box standing on a surface does not count as cutting into it)."""
    hit = boxes_cut_solids(world.solids, np.asarray(box, dtype=np.float64)[None], margin)[0]
    return frozenset(solid_categories(world)[hit].tolist())


def boxes_cut_solids(solids: Solids, boxes: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """``bool (B, S)``: box b ``(B, 7)``, shrunk by ``margin`` metres per side, shares volume
    with solid s.

    Exact for box solids (two vertical prisms: their height intervals and bird's-eye
    rectangles overlap) and cylinders (heights, and the circle against the rectangle); for an
    ellipsoid, the box point of least ellipsoid norm, found by projected gradient descent.
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7).copy()
    boxes[:, 3:6] = np.maximum(boxes[:, 3:6] - 2.0 * margin, 1e-6)
    out = np.zeros((len(boxes), len(solids)), dtype=bool)
    if out.size == 0:
        return out
    extent = solids.local_extent()
    reach = solids.horizontal_radius()[None, :] + np.hypot(boxes[:, 3], boxes[:, 4])[:, None] / 2
    near = np.hypot(*(boxes[:, None, :2] - solids.centre[None, :, :2]).transpose(2, 0, 1)) < reach
    near &= np.abs(boxes[:, None, 2] - solids.centre[None, :, 2]) < (
        boxes[:, None, 5] / 2 + extent[None, :, 2]
    )
    for b, s in zip(*np.nonzero(near), strict=True):
        out[b, s] = _box_cuts_solid(boxes[b], solids, int(s))
    return out


def _box_cuts_solid(box: np.ndarray, solids: Solids, s: int) -> bool:
    kind, centre, half, yaw = solids.kind[s], solids.centre[s], solids.half[s], solids.yaw[s]
    if kind == BOX:
        prism = np.array([[*centre, *(2 * half), yaw]])
        return bool(bev_overlap_area(box[None], prism)[0, 0] > 0)
    local = rotate_points_z((centre - box[:3])[None], -box[6])[0]
    if kind == CYLINDER:
        nearest = np.clip(local[:2], -box[3:5] / 2, box[3:5] / 2)
        return bool(np.hypot(*(local[:2] - nearest)) < half[0])
    return _ellipsoid_norm_over_box(box, centre, half, yaw) < 1.0


def _ellipsoid_norm_over_box(box, centre, half, yaw, iterations: int = 300) -> float:
    """min over the box of ``|(p - centre) / half|^2`` in the ellipsoid's frame (convex)."""
    # p = box centre + R_box u, u in [-h, h]; ellipsoid coordinates e = D R_e^T (p - centre)
    rot_box, rot_e = rotation_matrix_z(box[6]), rotation_matrix_z(yaw)
    a = (rot_e.T @ rot_box) / half[:, None]
    d = (rot_e.T @ (box[:3] - centre)) / half
    limit = box[3:6] / 2
    u = np.clip(rot_box.T @ (centre - box[:3]), -limit, limit)
    step = 0.5 / max(np.linalg.norm(a, 2) ** 2, 1e-12)
    for _ in range(iterations):
        u = np.clip(u - step * 2.0 * a.T @ (a @ u + d), -limit, limit)
    return float(np.sum((a @ u + d) ** 2))


def truth_actor(name: str, box: np.ndarray, rng: np.random.Generator) -> Actor:
    """An actor of class ``name`` whose tight box has exactly the size of ``box (7,)``.

    The procedural builder only comes close to the size it is asked for, so its solids are
    scaled per axis to fit (exact for boxes and ellipsoids, which actors hold unrotated; a
    cylinder's radius takes the mean of the two horizontal scales).
    """
    dims = np.asarray(box, dtype=np.float64)[3:6]
    actor = make_actor(name, rng, dims)
    scale = dims / actor.dims
    s = actor.solids
    half = s.half * scale
    round_xy = np.sqrt(scale[0] * scale[1])
    cylinder = s.kind == CYLINDER
    half[cylinder, :2] = s.half[cylinder, :2] * round_xy
    fitted = Solids(s.kind, s.centre * scale, half, s.yaw, s.material, s.owner)
    return Actor(name, fitted, dims.copy())


@dataclass(frozen=True, eq=False)
class InsertedTruth:
    """What the sensor would have recorded with objects inserted into a swept world.

    Attributes:
        solids: the inserted actors' solids (object k has owner ``len(world.actors) + k``).
        returns: ``float32 (R, 4)`` the inserted objects' true returns (x, y, z, intensity),
            with the sweep's range noise, dropout and intensity model.
        owner: ``int64 (R,)`` the object each return belongs to.
        ray: ``int64 (R,)`` each return's ray in the sweep's grid.
        counts: ``int64 (K,)`` true returns per object.
        hidden_by: ``int64 (N,)`` per point of the original sweep, the object that now meets
            its ray first (so the point is truly hidden), -1 for a point still visible.
    """

    solids: Solids
    returns: np.ndarray
    owner: np.ndarray
    ray: np.ndarray
    counts: np.ndarray
    hidden_by: np.ndarray

    @property
    def hidden(self) -> np.ndarray:
        """``bool (N,)``: original sweep points an inserted object truly hides."""
        return self.hidden_by >= 0


def true_inserted_returns(
    world: World,
    sweep: Sweep,
    names: Sequence[str],
    boxes: np.ndarray,
    rng: np.random.Generator,
    config: LidarConfig | None = None,
) -> InsertedTruth:
    """The truth of objects inserted at ``boxes (K, 7)`` (classes ``names``) into ``world``:
    an actor of each class, fitted to its box (:func:`truth_actor`), placed at the box's
    pose, and the sweep's own rays cast again with the world's solids, its actors and every
    inserted object in place (inserted objects hide each other as they would).

    An original point is truly hidden when its ray now meets an inserted object first (which
    is then necessarily nearer than the surface the point came from).
    """
    config = config or LidarConfig()
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    if len(names) != len(boxes):
        raise ValueError(f"{len(names)} names for {len(boxes)} boxes")
    first = len(world.actors)
    solids = Solids.concatenate(
        [
            truth_actor(str(name), box, rng).placed(box, first + k)
            for k, (name, box) in enumerate(zip(names, boxes, strict=True))
        ]
    )
    swept = scan_rays(world, sweep.grid, rng, config, scene=world.with_extra(solids))
    mine = swept.owner >= first
    owner = swept.owner[mine].astype(np.int64) - first
    ray_owner = swept.ray_owner[sweep.ray].astype(np.int64)
    hidden_by = np.where(ray_owner >= first, ray_owner - first, -1)
    return InsertedTruth(
        solids=solids,
        returns=swept.points[mine],
        owner=owner,
        ray=swept.ray[mine],
        counts=np.bincount(owner, minlength=len(boxes)).astype(np.int64),
        hidden_by=hidden_by,
    )


def true_object_returns(
    world: World,
    sweep: Sweep,
    name: str,
    box: np.ndarray,
    rng: np.random.Generator,
    config: LidarConfig | None = None,
) -> InsertedTruth:
    """:func:`true_inserted_returns` of one object of class ``name`` at ``box (7,)``."""
    return true_inserted_returns(world, sweep, [name], np.asarray(box)[None], rng, config)
