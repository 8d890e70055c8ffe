"""Random placement of objects in a frame (DR.CPO, step 2), checked before any construction.

A pose is a heading uniform in ``[-pi, pi)`` and a position uniform over the placement area such
that the whole BEV footprint lies inside it (with ``fov_only``, also inside the camera's field of
view: every footprint corner at an azimuth ``|atan2(y, x)| <= fov_half_angle``; KITTI's camera 2
sees about 41 degrees to each side); :mod:`drcpo.poses` draws the poses. The box bottom is put
on the ground estimated from the frame's own points.

Each object gets one pose, as in the paper. It is rejected, for one reason, when

* ``"out_of_range"``: the footprint cannot fit in the area (or field of view);
* ``"collision"``: its BEV box overlaps (area > 0) an existing box of the frame or a box placed
  earlier in this call (first come, first placed);
* ``"obstacle"``: its box holds more than ``max_non_ground_points`` frame points that are more
  than ``ground_tolerance`` above the ground (walls, trees, unlabelled objects);
* ``"occluded"``: the caller rejects it after the checks above (:meth:`PlacementResult.reject`;
  DR.CPO's test: the box would be hidden behind the frame's points, see
  :class:`drcpo.transforms.drcpo.DRCPO`).

Collisions are a separating-axis test (:func:`bev_collisions`), the points in each box
:func:`~drcpo.geometry.box_members`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from drcpo import collisions
from drcpo.collisions import bev_collisions
from drcpo.config_fields import Checked, spec
from drcpo.frame import Frame
from drcpo.geometry import box_members
from drcpo.ground import GroundModel
from drcpo.poses import check_dims, draw_poses, own_poses

__all__ = [
    "CAMERA_FOV_MODES",
    "KITTI_FOV_HALF_ANGLE",
    "LOCATION_MODES",
    "REASONS",
    "PlacementConfig",
    "PlacementResult",
    "frame_ground",
    "place_objects",
    "sample_poses",
]


REASONS = ("out_of_range", "collision", "obstacle", "occluded")
CAMERA_FOV_MODES = ("auto", "always", "never")
LOCATION_MODES = ("random", "source")
#: Half of KITTI camera 2's horizontal field of view (radians), rounded up.
KITTI_FOV_HALF_ANGLE = float(np.deg2rad(41.0))


@dataclass(frozen=True, eq=False)
class PlacementConfig(Checked):
    """Parameters of :func:`sample_poses` and :func:`place_objects` (paper defaults): the config
    section ``drcpo.placement``, whose keys are the first eight fields.

    Attributes:
        x_range, y_range: placement area (metres, LiDAR frame); the whole footprint stays inside.
        location: ``"random"`` (the paper: the centre uniform over the area) or ``"source"``
            (the object's own centre in the frame it was taken from: the paper's "fixed
            location" ablation, as ground-truth sampling places objects).
        heading_range: ``None`` (the paper: heading uniform over the circle) or the half-width
            (radians) of a uniform turn from the object's own heading (the paper's rotation
            range ablation: pi / 4 ... pi).
        max_non_ground_points: most non-ground frame points a placed box may hold.
        ground_tolerance: points more than this (metres) above the ground are non-ground.
        occluded_fraction: for the caller's occlusion test (``occluded`` of
            :func:`place_objects`; DR.CPO's rejects a box once e-HPR would hide this share of
            its sensor-facing surface; ``None``: no test).
        camera_fov: when the caller sets ``fov_only``: ``"auto"`` (when the frame is cut to the
            camera's view), ``"always"`` or ``"never"``.

    Set by the caller, not config keys:
        fov_only: restrict positions to the camera's field of view (see ``fov_half_angle``).
        fov_half_angle: largest footprint-corner azimuth ``|atan2(y, x)|`` (radians).
        clearance: metres of room kept free on every side of each placed footprint (for an
            object that may grow its box by that much once built): the footprint grown by it
            must lie in the area and overlap no box, nor any other grown footprint.
    """

    KEY_PATH = "drcpo.placement"

    x_range: list[float] = field(
        default_factory=lambda: [0.0, 70.4],
        metadata=spec("range", "metres, box inside", low=-200.0, high=200.0, strict=True),
    )
    y_range: list[float] = field(
        default_factory=lambda: [-40.0, 40.0],
        metadata=spec("range", "metres, box inside", low=-200.0, high=200.0, strict=True),
    )
    location: str = field(
        default="random",
        metadata=spec(
            "choice", "centre uniform over the area, or the object's own", choices=LOCATION_MODES
        ),
    )
    heading_range: float | None = field(
        default=None,
        metadata=spec(
            "float",
            "half-width (radians) of a uniform turn from the object's own heading (null: "
            "heading uniform over the circle, the paper)",
            low=0.0,
            high=math.pi,
            optional=True,
        ),
    )
    max_non_ground_points: int = field(
        default=10,
        metadata=spec("int", "frame points allowed inside a placed box", low=0, high=1_000_000),
    )
    ground_tolerance: float = field(
        default=0.2,
        metadata=spec(
            "float", "points this far above the ground are non-ground (m)", low=0.0, high=10.0
        ),
    )
    occluded_fraction: float | None = field(
        default=1.0,
        metadata=spec(
            "float",
            "reject a placed box before construction once this share of its sensor-facing "
            "surface e-HPR hides behind the frame's points (it would almost always drop the "
            "object; 1.0: only fully hidden boxes; null: never)",
            low=0.0,
            high=1.0,
            low_open=True,
            optional=True,
        ),
    )
    camera_fov: str = field(
        default="auto",
        metadata=spec(
            "choice",
            "place inside the camera view: auto = when the frame is cut to it",
            choices=CAMERA_FOV_MODES,
        ),
    )
    fov_only: bool = field(
        default=False,
        metadata=spec("bool", set_by="the caller, per frame (DR.CPO: from camera_fov)"),
    )
    fov_half_angle: float = field(
        default=KITTI_FOV_HALF_ANGLE,
        metadata=spec(
            "float",
            low=0.0,
            low_open=True,
            high=math.pi,
            set_by="the caller (KITTI camera 2's by default)",
        ),
    )
    clearance: float = field(
        default=0.0,
        metadata=spec(
            "float", low=0.0, set_by="the caller (DR.CPO: the room its objects' labels need)"
        ),
    )


@dataclass(frozen=True, eq=False)
class PlacementResult:
    """Outcome of :func:`place_objects`.

    Attributes:
        boxes: ``float64 (A, 7)`` placed boxes, in the order of ``accepted``.
        accepted: ``int64 (A,)`` ascending indices (into the ``dims`` given) of placed objects.
        rejected: objects rejected per reason (every reason in :data:`REASONS` present).
        reasons: ``(K,)`` per object: ``""`` when placed, else the reason it was rejected for.
    """

    boxes: np.ndarray
    accepted: np.ndarray
    rejected: dict[str, int]
    reasons: np.ndarray

    def reject(self, mask: np.ndarray, reason: str) -> PlacementResult:
        """The result with the placed boxes of ``mask`` (``bool (A,)``) rejected for
        ``reason`` (one of :data:`REASONS`)."""
        mask = np.asarray(mask, dtype=bool).reshape(-1)
        if len(mask) != len(self.accepted):
            raise ValueError(f"{len(mask)} verdicts for {len(self.accepted)} placed boxes")
        if reason not in REASONS:
            raise ValueError(f"unknown reason {reason!r}; reasons: {', '.join(REASONS)}")
        reasons = self.reasons.astype(object)  # a str array would cut the reason to its width
        reasons[self.accepted[mask]] = reason
        rejected = dict(self.rejected)
        rejected[reason] += int(mask.sum())
        return replace(
            self,
            boxes=self.boxes[~mask],
            accepted=self.accepted[~mask],
            rejected=rejected,
            reasons=reasons.astype(str),
        )


def sample_poses(
    dims: np.ndarray,
    rng: np.random.Generator,
    config: PlacementConfig | None = None,
    source: np.ndarray | None = None,
) -> np.ndarray:
    """Random boxes ``float64 (K, 7)`` of sizes ``dims`` ``(K, 3)`` (metres).

    Heading uniform in ``[-pi, pi)``; centre uniform over the positions whose whole footprint
    lies in the area (and field of view when ``fov_only``); ``z = dz / 2`` (bottom at 0). Rows
    that cannot fit have NaN x and y. ``source`` ``(K, 7)``: the objects' own boxes, for
    ``location="source"`` or a ``heading_range``. See :func:`drcpo.poses.draw_poses`.
    """
    config = config or PlacementConfig()
    half_angle = float(config.fov_half_angle) if config.fov_only else None
    own = (config.location, config.heading_range, source)
    return draw_poses(dims, rng, config.x_range, config.y_range, half_angle, own)


def place_objects(
    frame: Frame | dict,
    dims: np.ndarray,
    source_boxes: np.ndarray | None,
    rng: np.random.Generator,
    config: PlacementConfig | None = None,
    ground: GroundModel | None = None,
) -> PlacementResult:
    """Place objects of sizes ``dims`` ``(K, 3)`` at random, collision- and obstacle-free.

    Args:
        frame: the :class:`Frame` (or OpenPCDet dict) receiving the objects; its boxes are
            obstacles to avoid and its points the background checked for non-ground points.
        dims: box sizes dx, dy, dz (metres) of the objects, in the order they are tried.
        source_boxes: ``(K, 7)`` the objects' original boxes; their centre and heading are used
            with ``location="source"`` or a ``heading_range`` (may be ``None`` otherwise).
        rng: the only source of randomness.
        config: :class:`PlacementConfig` (defaults when ``None``).
        ground: the frame's :class:`GroundModel`; estimated from the frame's points (with its
            ``plane`` and ``calib`` metadata, when both are present) when ``None``.
    """
    config = config or PlacementConfig()
    frame = Frame.from_dict(frame) if isinstance(frame, dict) else frame
    dims = check_dims(dims)
    own = None
    if config.location == "source" or config.heading_range is not None:
        own = own_poses(source_boxes, len(dims))
    # each footprint with its clearance: sampled and checked for collisions
    room = dims.copy()
    room[:, :2] += 2.0 * config.clearance
    boxes = sample_poses(room, rng, config, own)
    ground = frame_ground(frame) if ground is None else ground
    verdict = _judge(boxes, dims, frame, ground, config)
    accepted = np.flatnonzero(verdict == 0)
    placed = boxes[accepted]
    placed[:, 3:5] = dims[accepted, :2]  # the objects' own footprints, without the clearance
    counts = np.bincount(verdict, minlength=len(REASONS) + 1)
    return PlacementResult(
        boxes=placed,
        accepted=accepted.astype(np.int64),
        rejected={reason: int(n) for reason, n in zip(REASONS, counts[1:], strict=True)},
        reasons=_REASON_NAMES[verdict].astype(str),
    )


# verdicts: 1 + index in REASONS
_OUT_OF_RANGE, _COLLISION, _OBSTACLE = range(1, 4)
_REASON_NAMES = np.array(["", *REASONS], dtype=object)  # by verdict


def _judge(
    boxes: np.ndarray,
    dims: np.ndarray,
    frame: Frame,
    ground: GroundModel,
    config: PlacementConfig,
) -> np.ndarray:
    """Set each box's height and return its verdict ``int64 (K,)``: 0 (placed) or 1 + the
    index of its rejection reason in :data:`REASONS`. ``boxes`` are the footprints with their
    clearance; the obstacle test takes the objects' own sizes, ``dims``."""
    verdict = np.zeros(len(boxes), dtype=np.int64)
    fits = np.isfinite(boxes[:, 0])
    verdict[~fits] = _OUT_OF_RANGE
    live = np.flatnonzero(fits)
    hit = np.zeros(len(live), dtype=bool)
    if len(frame.boxes) and len(live):
        hit = bev_collisions(boxes[live], frame.boxes).any(axis=1)
    boxes[live, 2] = ground.height_at(boxes[live, :2]) + boxes[live, 5] / 2.0
    verdict[live[hit]] = _COLLISION
    live = live[~hit]
    own = boxes[live]
    own[:, 3:5] = dims[live, :2]
    blocked = _non_ground_counts(frame.points, own, ground, config.ground_tolerance)
    blocked = blocked > config.max_non_ground_points
    verdict[live[blocked]] = _OBSTACLE
    live = live[~blocked]
    # First come, first placed: a box loses against earlier boxes of the batch that were placed.
    kept = collisions.first_come(boxes[live], live)
    verdict[live[~kept]] = _COLLISION
    return verdict


def _non_ground_counts(
    points: np.ndarray, boxes: np.ndarray, ground: GroundModel, tolerance: float
) -> np.ndarray:
    """Frame points more than ``tolerance`` above the ground inside each of ``boxes``
    ``(M, 7)``: ``int64 (M,)``. Only the points inside a box are tested against the ground."""
    if len(boxes) == 0 or len(points) == 0:
        return np.zeros(len(boxes), dtype=np.int64)
    point, box = box_members(points, boxes)
    above = ~ground.is_ground(points.take(point, axis=0), tolerance)
    return np.bincount(box[above], minlength=len(boxes)).astype(np.int64)


def frame_ground(frame: Frame) -> GroundModel:
    """The frame's ground estimate (with its KITTI road plane when it has one and a calib).

    Uses a fixed RANSAC seed, so a frame always gets the same ground.
    """
    plane, calib = frame.metadata.get("plane"), frame.metadata.get("calib")
    if plane is not None and calib is not None:
        return GroundModel.from_points(frame.points, plane=plane, calib=calib)
    return GroundModel.from_points(frame.points)
