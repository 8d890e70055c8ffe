"""Random placement of objects in a frame (DR.CPO, step 2), checked before any construction.

A pose is a heading uniform in ``[-pi, pi)`` and a position uniform over the placement area such
that the whole BEV footprint lies inside it (with ``fov_only``, also inside the camera's field of
view: every footprint corner at an azimuth ``|atan2(y, x)| <= fov_half_angle``; KITTI's camera 2
sees about 41 degrees to each side); with ``height="observed"``, uniform over the area where the
frame observed ground (the ground cells, and those bridged between scan rings, whose centre lies
in the area and field of view; :mod:`drcpo.poses` draws the poses). The box bottom is put on
the ground estimated from the frame's own points (``height="ground"``), or the box keeps its
source height (``"source"``, the reference implementation), or it stands on the ground the
frame observed under its footprint (``"observed"``): the footprint's four corners and centre
(with the clearance) must lie on ground cells or between two scan rings on their sensor ray
(``ground_gap``; see :meth:`drcpo.ground.GroundModel.observed_height_at`: no height borrowed
from cells metres away, no plane); the bottom goes to the median of the five heights: on a
plane it is the centre's height (the corners pair around it), and unlike the mean it ignores
one corner on a kerb.

A placement is rejected, for one reason counted per attempt, when

* ``"out_of_range"``: the footprint cannot fit in the area (or field of view; with
  ``"observed"``, none of the positions drawn on observed ground fits);
* ``"collision"``: its BEV box overlaps (area > 0) an existing box of the frame, a box placed
  earlier in this call, or an earlier box of the same batch (first come, first placed);
* ``"obstacle"``: its box holds more than ``max_non_ground_points`` frame points that are more
  than ``ground_tolerance`` above the ground (walls, trees, unlabelled objects); with
  ``"observed"``, above the observed ground at the point (above the box bottom where the point's
  cell saw no ground), so that ground returns under the box are never obstacles;
* ``"no_ground"`` (``"observed"`` only): a sampled footprint point has no observed ground (or
  the frame observed none in the area and field of view);
* ``"slope"`` (``"observed"`` only): the five heights spread (max - min) by more than
  ``max_slope`` times the footprint's diagonal;
* ``"occluded"``: the caller rejects it after the checks above (:class:`PlacementRounds` hands
  each round's boxes to the caller and takes its verdict; DR.CPO's test: the box would be
  hidden behind the frame's points, see :class:`drcpo.transforms.drcpo.DRCPO`).

Objects are tried up to ``attempts`` times (a fresh pose each time); the paper tries once.
``max_attempts_per_frame`` caps the poses of one call in all, so that a crowded frame cannot
loop for long: the round that reaches the cap draws poses for the first pending objects only,
and objects that never got a pose end with the reason ``"budget"`` (counted per object, not per
attempt). The budget counts poses, not seconds, so that the same seed gives the same output.

The hot loops are numba kernels bit for bit equal to the reference numpy arithmetic:
collisions a separating-axis test (:func:`bev_collisions`), the points in each box from a
coarse cell index (:func:`box_members`, see ``_Obstacles``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numba
import numpy as np

from drcpo import collisions
from drcpo.collisions import bev_collisions
from drcpo.config_fields import Checked, spec
from drcpo.errors import DataError
from drcpo.frame import Frame
from drcpo.geometry import box_members, heading_terms, in_box
from drcpo.ground import GroundModel
from drcpo.poses import (
    CentreCells,
    check_dims,
    draw_poses,
    footprint_ground,
    observed_cells,
    own_poses,
    source_heights,
)

__all__ = [
    "CAMERA_FOV_MODES",
    "HEIGHT_MODES",
    "KITTI_FOV_HALF_ANGLE",
    "LOCATION_MODES",
    "REASONS",
    "PlacementConfig",
    "PlacementResult",
    "PlacementRounds",
    "Round",
    "frame_ground",
    "place_objects",
    "sample_poses",
]


REASONS = ("out_of_range", "collision", "obstacle", "occluded", "no_ground", "slope", "budget")
HEIGHT_MODES = ("ground", "source", "observed")
CAMERA_FOV_MODES = ("auto", "always", "never")
LOCATION_MODES = ("random", "source")
#: Half of KITTI camera 2's horizontal field of view (radians), rounded up.
KITTI_FOV_HALF_ANGLE = float(np.deg2rad(41.0))


@dataclass(frozen=True, eq=False)
class PlacementConfig(Checked):
    """Parameters of :func:`sample_poses` and :func:`place_objects` (paper defaults): the config
    section ``drcpo.placement``, whose keys are the first fourteen fields.

    Attributes:
        x_range, y_range: placement area (metres, LiDAR frame); the whole footprint stays inside.
        location: ``"random"`` (the paper: the centre uniform over the area) or ``"source"``
            (the object's own centre in the frame it was taken from: the paper's "fixed
            location" ablation, as ground-truth sampling places objects).
        heading_range: ``None`` (the paper: heading uniform over the circle) or the half-width
            (radians) of a uniform turn from the object's own heading (the paper's rotation
            range ablation: pi / 4 ... pi).
        height: ``"ground"`` (bottom on the estimated ground), ``"source"`` or ``"observed"``
            (bottom on the ground the frame observed under the footprint, the centre drawn
            where the frame observed ground; see the module).
        max_non_ground_points: most non-ground frame points a placed box may hold.
        ground_tolerance: points more than this (metres) above the ground are non-ground.
        attempts: poses tried per object.
        max_slope: with ``"observed"``: most ground rise over the footprint's diagonal
            (the spread of the five sampled heights over the diagonal; 0.1 = 5.7 degrees).
        ground_gap: with ``"observed"``: bridge the gaps between scan rings up to this share
            of the range (``max_gap`` of :meth:`drcpo.ground.GroundModel.observed_height_at`).
        max_attempts_per_frame: poses tried in all per call, over every object (``None``: no
            cap); a count, not a time budget, so that the same seed gives the same output.
        poses_per_round: poses drawn per object and round (within its ``attempts``), tried in
            turn: the first that passes every check is placed and the object's later ones
            are left unused (not counted as attempts). More per round, fewer rounds.
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
    height: str = field(
        default="ground",
        metadata=spec(
            "choice", "box bottom on the local ground, or source height", choices=HEIGHT_MODES
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
    attempts: int = field(
        default=1,
        metadata=spec("int", "poses tried per sampled object (the paper: 1)", low=1, high=1000),
    )
    max_slope: float = field(
        default=0.1,
        metadata=spec(
            "float",
            'height "observed": most ground rise under a footprint over its diagonal',
            low=0.0,
            high=10.0,
        ),
    )
    ground_gap: float = field(
        default=0.3,
        metadata=spec(
            "float",
            'height "observed": a footprint point between scan rings stands on observed ground '
            "when ground cells lie on its sensor ray before and beyond it within this share of "
            "its range (0: its own cell only)",
            low=0.0,
            high=1.0,
        ),
    )
    max_attempts_per_frame: int | None = field(
        default=None,
        metadata=spec(
            "int",
            "poses tried in all per frame, every object together (a count, not a time budget, "
            "so that the same seed gives the same output; null: no cap)",
            low=1,
            high=1_000_000,
            optional=True,
        ),
    )
    poses_per_round: int = field(
        default=1,
        metadata=spec(
            "int",
            "poses drawn per object and round, tried in turn until one is placed (fewer "
            "rounds for the same attempts; 1: one per round)",
            low=1,
            high=100,
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
        rejected: attempts rejected per reason (every reason in :data:`REASONS` present);
            ``"budget"``: the objects that got no pose (``max_attempts_per_frame``), so
            ``attempts == len(accepted) + sum(rejected.values()) - rejected["budget"]``.
        reasons: ``(K,)`` per object: ``""`` when placed, else the reason of its last attempt
            (``"budget"``: it had none).
        attempts: poses tried in all.
    """

    boxes: np.ndarray
    accepted: np.ndarray
    rejected: dict[str, int]
    reasons: np.ndarray
    attempts: int


def sample_poses(
    dims: np.ndarray,
    rng: np.random.Generator,
    config: PlacementConfig | None = None,
    cells: CentreCells | None = None,
    source: np.ndarray | None = None,
) -> np.ndarray:
    """Random boxes ``float64 (K, 7)`` of sizes ``dims`` ``(K, 3)`` (metres).

    Heading uniform in ``[-pi, pi)``; centre uniform over the positions whose whole footprint
    lies in the area (and field of view when ``fov_only``), with ``cells`` only over those in
    the cells (:class:`PlacementRounds` gives the observed ground's,
    :func:`drcpo.poses.observed_cells`, with ``height="observed"``); ``z = dz / 2`` (bottom at
    0). Rows that cannot fit have NaN x and y. ``source`` ``(K, 7)``: the objects' own boxes,
    for ``location="source"`` or a ``heading_range``. See :func:`drcpo.poses.draw_poses`.
    """
    config = config or PlacementConfig()
    half_angle = float(config.fov_half_angle) if config.fov_only else None
    own = (config.location, config.heading_range, source)
    return draw_poses(dims, rng, config.x_range, config.y_range, half_angle, cells, own)


def place_objects(
    frame: Frame | dict,
    dims: np.ndarray,
    source_boxes: np.ndarray | None,
    rng: np.random.Generator,
    config: PlacementConfig | None = None,
    ground: GroundModel | None = None,
) -> PlacementResult:
    """Place objects of sizes ``dims`` ``(K, 3)`` at random, collision- and obstacle-free.

    The same as :class:`PlacementRounds` with every round's boxes accepted (no ``"occluded"``
    test).

    Args:
        frame: the :class:`Frame` (or OpenPCDet dict) receiving the objects; its boxes are
            obstacles to avoid and its points the background checked for non-ground points.
        dims: box sizes dx, dy, dz (metres) of the objects, in the order they are tried.
        source_boxes: ``(K, 7)`` the objects' original boxes; only their z is used, and only
            with ``height="source"`` (may be ``None`` otherwise).
        rng: the only source of randomness.
        config: :class:`PlacementConfig` (defaults when ``None``).
        ground: the frame's :class:`GroundModel`; estimated from the frame's points (with its
            ``plane`` and ``calib`` metadata, when both are present) when ``None``.
    """
    rounds = PlacementRounds(frame, dims, source_boxes, rng, config, ground)
    while rounds.next_round() is not None:
        rounds.settle()
    return rounds.result()


@dataclass(frozen=True, eq=False)
class Round:
    """One round of :class:`PlacementRounds`: fresh poses for the objects not placed yet.

    Attributes:
        boxes: ``float64 (B, 7)`` the boxes that passed the geometric checks (area, collision,
            obstacle), the objects' own sizes (without the clearance), in the order they are
            tried: object order, each object's first pose, then its second, ... (with
            ``poses_per_round`` > 1; a caller's verdict takes them in this order and keeps
            at most one per object, the first it accepts).
        placed: ``float64 (P, 7)`` the boxes placed in earlier rounds, in object order.
        objects: ``int64 (B,)`` the object (index into ``dims``) of each of ``boxes``.
        conflicts: ``bool (B, B)`` with ``poses_per_round`` > 1, the pairs of ``boxes`` of two
            objects whose footprints (with their clearance) overlap: taken in turn, a box is
            rejected (``"collision"``) when it conflicts with one taken before (with one pose
            per round, the boxes that did already went, and none is left).
    """

    boxes: np.ndarray
    placed: np.ndarray
    objects: np.ndarray
    conflicts: np.ndarray


class PlacementRounds:
    """:func:`place_objects` one round at a time, so that the caller can reject boxes that
    pass the geometric checks (DR.CPO's ``"occluded"`` test, see
    :class:`drcpo.transforms.drcpo.DRCPO`) without placement calling back into it.

    Each round draws a pose for every object not placed yet (up to ``attempts`` rounds):
    :meth:`next_round` draws and checks them and returns the :class:`Round` (``None`` when
    done); :meth:`settle` takes the caller's verdict on that round's boxes before the next
    round is drawn; :meth:`result` gives the outcome. The random draws are those of
    :func:`place_objects`, in the same order, whatever the verdicts.

    Args: as :func:`place_objects`; ``cells``: :attr:`cells`, when known (same ground and area).
    """

    def __init__(
        self,
        frame: Frame | dict,
        dims: np.ndarray,
        source_boxes: np.ndarray | None,
        rng: np.random.Generator,
        config: PlacementConfig | None = None,
        ground: GroundModel | None = None,
        cells: CentreCells | None = None,
    ) -> None:
        self._config = config = config or PlacementConfig()
        frame = Frame.from_dict(frame) if isinstance(frame, dict) else frame
        self._dims = dims = check_dims(dims)
        self._source_z = source_heights(source_boxes, len(dims), config.height)
        self._source = None
        if config.location == "source" or config.heading_range is not None:
            self._source = own_poses(source_boxes, len(dims))
        self._rng = rng
        if ground is None:
            ground = frame_ground(frame)
        observed = config.height == "observed"
        self._obstacles = _Obstacles(frame.points, ground, config.ground_tolerance, observed)
        #: with "observed", the centres' cells: where the frame saw ground (drawn over the whole
        #: area, most poses of a street scene land behind buildings); else ``None``
        self.cells = cells if observed else None
        if observed and cells is None:
            half_angle = float(config.fov_half_angle) if config.fov_only else None
            area = (config.x_range, config.y_range, half_angle, config.ground_gap)
            self.cells = observed_cells(ground, *area)
        self._placed = np.full((len(dims), 7), np.nan)
        # 0: placed, else 1 + REASONS index; "budget" until an object gets its first pose
        self._verdicts = np.full(len(dims), _BUDGET, dtype=np.int64)
        self._counts = np.zeros(len(REASONS) + 1, dtype=np.int64)
        self._occupied = frame.boxes
        # each footprint with its clearance: sampled and checked for collisions
        self._room = dims.copy()
        self._room[:, :2] += 2.0 * config.clearance
        self._pending = np.arange(len(dims))
        self._tries = np.zeros(len(dims), dtype=np.int64)  # poses tried per object
        self._attempts = 0
        self._open: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    def next_round(self) -> Round | None:
        """Draw and check the next round's poses; ``None`` when every object is placed or has
        had its ``attempts`` poses, or ``max_attempts_per_frame`` poses were drawn in all (the
        round reaching it draws for the first pending objects only). Call :meth:`settle`
        before the next round."""
        if self._open is not None:
            raise RuntimeError("settle the current round before drawing the next")
        config = self._config
        cap = config.max_attempts_per_frame
        spent = cap is not None and self._attempts >= cap
        pending = self._pending
        if len(pending) == 0 or spent or (self._tries[pending] >= config.attempts).all():
            return None
        # each pending object's poses (within its attempts), its first ones first
        per = np.minimum(config.poses_per_round, config.attempts - self._tries[pending])
        tried = pending
        if (per != 1).any():
            tried = np.concatenate([pending[per > k] for k in range(int(per.max()))])
        if cap is not None:
            tried = tried[: cap - self._attempts]
        self._attempts += len(tried)
        source = None if self._source is None else self._source[tried]
        boxes = sample_poses(self._room[tried], self._rng, config, self.cells, source)
        several = config.poses_per_round > 1
        verdict = _judge(
            boxes,
            tried,
            self._dims,
            self._source_z,
            self._occupied,
            self._obstacles,
            config,
            first_come=not several,
        )
        if self.cells is not None and len(self.cells.corners) == 0:
            verdict[verdict == _OUT_OF_RANGE] = _NO_GROUND  # no observed ground to stand on
        own = boxes.copy()  # the objects' own footprints, without the clearance
        own[:, 3:5] = self._dims[tried, :2]
        passed = np.flatnonzero(verdict == 0)
        # With several poses per object, the round's poses collide only once taken (in turn,
        # see settle): a pose left unused or hidden blocks nothing.
        conflicts = np.zeros((len(passed), len(passed)), dtype=bool)
        if several and len(passed):
            conflicts = bev_collisions(boxes[passed], boxes[passed])
            conflicts &= tried[passed][:, None] != tried[passed][None, :]
        self._open = (tried, boxes, own, verdict, passed, conflicts)
        placed = self._placed[np.isfinite(self._placed[:, 0])]
        return Round(boxes=own[passed], placed=placed, objects=tried[passed], conflicts=conflicts)

    def settle(self, occluded: np.ndarray | None = None) -> None:
        """Close the current round: ``occluded`` ``bool (B,)`` marks its boxes to reject
        (reason ``"occluded"``; tried again like the others), ``None``: none."""
        if self._open is None:
            raise RuntimeError("no round to settle: call next_round first")
        tried, boxes, own, verdict, passed, conflicts = self._open
        if occluded is not None:
            hidden = np.asarray(occluded, dtype=bool).reshape(-1)
            if len(hidden) != len(passed):
                raise ValueError(f"{len(hidden)} occluded verdicts for {len(passed)} boxes")
            verdict[passed[hidden]] = _OCCLUDED
        self._open = None
        if conflicts.any():
            clash = _taken_in_turn(tried[passed], verdict[passed] == 0, conflicts)
            verdict[passed[clash]] = _COLLISION
        ok = verdict == 0
        used = _up_to_first(tried, ok)  # an object's poses after its placed one: unused
        self._attempts -= len(tried) - int(used.sum())
        tried, verdict, boxes, own = (a[used] for a in (tried, verdict, boxes, own))
        ok = verdict == 0
        self._counts += np.bincount(verdict, minlength=len(self._counts))
        np.add.at(self._tries, tried, 1)
        self._verdicts[tried] = verdict  # (each object's last pose tried comes last)
        self._occupied = np.concatenate([self._occupied, boxes[ok]])
        self._placed[tried[ok]] = own[ok]
        self._pending = self._pending[~np.isin(self._pending, tried[ok])]

    def result(self) -> PlacementResult:
        """The outcome of the rounds settled so far."""
        if self._open is not None:
            raise RuntimeError("settle the current round first")
        accepted = np.flatnonzero(self._verdicts == 0)
        counts = self._counts.copy()
        counts[_BUDGET] = np.count_nonzero(self._verdicts == _BUDGET)  # objects, not attempts
        return PlacementResult(
            boxes=self._placed[accepted],
            accepted=accepted.astype(np.int64),
            rejected={reason: int(n) for reason, n in zip(REASONS, counts[1:], strict=True)},
            reasons=_REASON_NAMES[self._verdicts].astype(str),
            attempts=self._attempts,
        )


# verdicts: 1 + index in REASONS
_OUT_OF_RANGE, _COLLISION, _OBSTACLE, _OCCLUDED, _NO_GROUND, _SLOPE, _BUDGET = range(1, 8)
_REASON_NAMES = np.array(["", *REASONS], dtype=object)  # by verdict


def _judge(
    boxes: np.ndarray,
    pending: np.ndarray,
    dims: np.ndarray,
    source_z: np.ndarray | None,
    occupied: np.ndarray,
    obstacles: _Obstacles,
    config: PlacementConfig,
    first_come: bool = True,
) -> np.ndarray:
    """Set each box's height and return its verdict ``int64 (K,)``: 0 (placed) or 1 + the
    index of its rejection reason in :data:`REASONS`. ``boxes`` are the footprints with their
    clearance; the obstacle test takes the objects' own sizes, ``dims[pending]``.
    ``first_come``: a box colliding with an earlier one of the batch that passed goes too."""
    verdict = np.zeros(len(boxes), dtype=np.int64)
    fits = np.isfinite(boxes[:, 0])
    verdict[~fits] = _OUT_OF_RANGE
    live = np.flatnonzero(fits)
    hit = np.zeros(len(live), dtype=bool)
    if len(occupied) and len(live):
        hit = bev_collisions(boxes[live], occupied).any(axis=1)
    if config.height == "ground":
        boxes[live, 2] = obstacles.ground.height_at(boxes[live, :2]) + boxes[live, 5] / 2.0
    elif config.height == "source":
        boxes[live, 2] = source_z[pending[live]]
    verdict[live[hit]] = _COLLISION
    live = live[~hit]
    if config.height == "observed":
        boxes[live, 2], standing = _on_observed_ground(boxes[live], obstacles.ground, config)
        verdict[live] = standing
        live = live[standing == 0]
    own = boxes[live]
    own[:, 3:5] = dims[pending[live], :2]
    blocked = obstacles.count(own) > config.max_non_ground_points
    verdict[live[blocked]] = _OBSTACLE
    live = live[~blocked]
    # First come, first placed: a box loses against earlier boxes of the batch that were placed.
    if not first_come:
        return verdict
    kept = collisions.first_come(boxes[live], pending[live])
    verdict[live[~kept]] = _COLLISION
    return verdict


def _taken_in_turn(objects: np.ndarray, ok: np.ndarray, conflicts: np.ndarray) -> np.ndarray:
    """``bool (B,)``: the ``ok`` boxes that, taken in turn, conflict with one taken before
    (a box is taken when ok, its object has none taken yet and it conflicts with none)."""
    clash, taken = np.zeros(len(objects), dtype=bool), []
    for i in np.flatnonzero(ok).tolist():
        if objects[i] in objects[taken]:
            continue  # its object has one taken: an unused alternative
        clash[i] = conflicts[i, taken].any()
        if not clash[i]:
            taken.append(i)
    return clash


def _up_to_first(objects: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """``bool (T,)``: the poses ``objects`` ``(T,)`` (object of each, in the order tried) up to
    and including each object's first ``ok`` one; the object's later poses are not needed."""
    order = np.arange(len(objects))
    first = np.full(int(objects.max(initial=-1)) + 1, len(objects))
    np.minimum.at(first, objects[ok], order[ok])
    return order <= first[objects]


def _on_observed_ground(
    boxes: np.ndarray, ground: GroundModel, config: PlacementConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Each box's centre z standing on the observed ground (``float64 (L,)``, NaN where it
    cannot) and its verdict (``int64 (L,)``: 0, ``_NO_GROUND`` or ``_SLOPE``); see
    :func:`drcpo.poses.footprint_ground`."""
    z, seen, steep = footprint_ground(boxes, ground, config.max_slope, config.ground_gap)
    verdict = np.where(seen, np.where(steep, _SLOPE, 0), _NO_GROUND).astype(np.int64)
    z[verdict != 0] = np.nan
    return z, verdict


class _Obstacles:
    """Counts of non-ground frame points in candidate boxes.

    The points in each box: in the first rounds one pass over the frame each
    (:func:`drcpo.geometry.box_members`); from round ``_INDEX_AFTER`` on, the points sorted
    once into 1 m cells (about five passes' time), each box visiting only the cells under it
    (the same pairs). Only those are tested against the ground (:meth:`GroundModel.is_ground`;
    with ``observed``: more than ``tolerance`` above the observed ground at the point, or above
    the box's bottom where its cell observed none, :meth:`GroundModel.observed_height_at`).
    """

    def __init__(self, points: np.ndarray, ground: GroundModel, tolerance: float, observed=False):
        self.points, self.ground, self.tolerance = points, ground, tolerance
        self.observed = observed
        self._index: tuple | None = None
        self._calls = 0

    def count(self, boxes: np.ndarray) -> np.ndarray:
        """Non-ground frame points inside each of ``boxes`` ``(M, 7)``: ``int64 (M,)``."""
        if len(boxes) == 0 or len(self.points) == 0:
            return np.zeros(len(boxes), dtype=np.int64)
        point, box = self.members(boxes)
        inside = self.points.take(point, axis=0)
        if self.observed:
            heights, seen = self.ground.observed_height_at(inside[:, :2])
            bottom = boxes[box, 2] - boxes[box, 5] / 2.0
            above = inside[:, 2] > np.where(seen, heights, bottom) + self.tolerance
        else:
            above = ~self.ground.is_ground(inside, self.tolerance)
        return np.bincount(box[above], minlength=len(boxes)).astype(np.int64)

    def members(self, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(point, box)`` ``int64`` pairs of frame points inside ``(M, 7)`` boxes."""
        self._calls += 1
        if self._calls < _INDEX_AFTER:
            return box_members(self.points, boxes)
        if self._index is None:
            self._index = _CellIndex(*_sort_into_cells(np.asarray(self.points), _INDEX_CELLS))
        boxes = np.ascontiguousarray(boxes, dtype=np.float64)
        return _indexed_members(self._index, boxes, *heading_terms(boxes))


class _CellIndex(NamedTuple):
    """The frame's finite-(x, y) points sorted by BEV cell (:func:`_sort_into_cells`)."""

    xyz: np.ndarray  # (P, 3) float64, in cell order
    rows: np.ndarray  # (P,) their rows in the frame
    start: np.ndarray  # (nx * ny + 1,) each cell's first slot
    x0: float  # the grid's corner
    y0: float
    per_metre: float  # cells per metre
    nx: int
    ny: int


_INDEX_AFTER = 3  # the round from which the frame's points are indexed
_INDEX_CELLS = 512  # most index cells along x or y (1 m cells, larger for a huge frame)


@numba.njit(cache=True, nogil=True)
def _sort_into_cells(points, max_cells):  # pragma: no cover - numba
    # The finite-(x, y) points' xyz sorted by BEV cell (a stable counting sort), their rows,
    # each cell's first slot and the grid: x0, y0, cells per metre, nx, ny.
    x0 = y0 = np.inf
    x1 = y1 = -np.inf
    for i in range(points.shape[0]):
        x, y = np.float64(points[i, 0]), np.float64(points[i, 1])
        if np.isfinite(x) and np.isfinite(y):
            x0, x1, y0, y1 = min(x0, x), max(x1, x), min(y0, y), max(y1, y)
    if not x0 <= x1:
        return np.empty((0, 3)), np.empty(0, np.int64), np.zeros(2, np.int64), 0.0, 0.0, 1.0, 1, 1
    per_metre = 1.0 / max(1.0, (x1 - x0) / max_cells, (y1 - y0) / max_cells)
    nx, ny = int((x1 - x0) * per_metre) + 1, int((y1 - y0) * per_metre) + 1
    cells = np.full(points.shape[0], -1, np.int64)
    start = np.zeros(nx * ny + 1, np.int64)
    for i in range(points.shape[0]):
        x, y = np.float64(points[i, 0]), np.float64(points[i, 1])
        if np.isfinite(x) and np.isfinite(y):
            cell = min(int((x - x0) * per_metre), nx - 1) * ny
            cells[i] = cell + min(int((y - y0) * per_metre), ny - 1)
            start[cells[i] + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    xyz = np.empty((start[nx * ny], 3))
    rows = np.empty(start[nx * ny], np.int64)
    for i in range(points.shape[0]):
        if cells[i] >= 0:
            k = fill[cells[i]]
            xyz[k, 0], xyz[k, 1], xyz[k, 2] = points[i, 0], points[i, 1], points[i, 2]
            rows[k] = i
            fill[cells[i]] += 1
    return xyz, rows, start, x0, y0, per_metre, nx, ny


@numba.njit(cache=True, nogil=True)
def _indexed_members(index, boxes, cos, sin):  # pragma: no cover - numba
    # Per box, the points of the cells its BEV bounds cover (with the slack of
    # geometry.box_members, so that rounding never drops a point inside), tested exactly.
    xyz, rows, start, x0, y0 = index.xyz, index.rows, index.start, index.x0, index.y0
    per_metre, nx, ny = index.per_metre, index.nx, index.ny
    found_point = np.empty(64, np.int64)
    found_box = np.empty(64, np.int64)
    found = 0
    for m in range(boxes.shape[0]):
        c, s = abs(cos[m]), abs(sin[m])
        reach_x = (boxes[m, 3] * c + boxes[m, 4] * s) / 2.0 * (1.0 + 1e-9) + 1e-6
        reach_y = (boxes[m, 3] * s + boxes[m, 4] * c) / 2.0 * (1.0 + 1e-9) + 1e-6
        i0 = max(math.floor((boxes[m, 0] - reach_x - x0) * per_metre), 0)
        i1 = min(math.floor((boxes[m, 0] + reach_x - x0) * per_metre), nx - 1)
        j0 = max(math.floor((boxes[m, 1] - reach_y - y0) * per_metre), 0)
        j1 = min(math.floor((boxes[m, 1] + reach_y - y0) * per_metre), ny - 1)
        if j0 > j1:
            continue
        for i in range(i0, i1 + 1):  # a row's cells j0..j1 are one run of slots
            for k in range(start[i * ny + j0], start[i * ny + j1 + 1]):
                if in_box(xyz[k, 0], xyz[k, 1], xyz[k, 2], boxes[m], cos[m], sin[m], 0.0):
                    if found == found_point.shape[0]:
                        found_point = np.concatenate((found_point, np.empty_like(found_point)))
                        found_box = np.concatenate((found_box, np.empty_like(found_box)))
                    found_point[found], found_box[found] = rows[k], m
                    found += 1
    return found_point[:found].copy(), found_box[:found].copy()


def frame_ground(frame: Frame, exclude: np.ndarray | None = None) -> GroundModel:
    """The frame's ground estimate (with its KITTI road plane when it has one and a calib).

    Uses a fixed RANSAC seed, so a frame always gets the same ground.

    Args:
        frame: the frame.
        exclude: ``(M, 7)`` boxes whose points are not the frame's ground (e.g. the objects
            ground-truth sampling added, standing on the ground of the frames they came
            from): the points inside them (:func:`drcpo.geometry.box_members`; grow the boxes
            to leave out more) are left out of the estimate. ``None`` or no box: every point.
    """
    points = frame.points
    if exclude is not None:
        exclude = np.asarray(exclude, dtype=np.float64)
        if exclude.size and (exclude.ndim != 2 or exclude.shape[1] != 7):
            raise DataError(f"exclude boxes must have shape (M, 7), got {exclude.shape}")
        if not np.isfinite(exclude).all():
            raise DataError("exclude boxes hold a non-finite value")
        if exclude.size:
            keep = np.ones(len(points), dtype=bool)
            keep[box_members(points, exclude.reshape(-1, 7))[0]] = False
            points = points[keep]
    plane, calib = frame.metadata.get("plane"), frame.metadata.get("calib")
    if plane is not None and calib is not None:
        return GroundModel.from_points(points, plane=plane, calib=calib)
    return GroundModel.from_points(points)
