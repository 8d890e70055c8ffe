"""Procedural objects of the three KITTI classes, each built from several solids.

An :class:`Actor` holds its solids in canonical pose: the tight box around all its solids is
centred at the origin with heading 0 and length along x, so placing an actor at a box (OpenPCDet
convention) is a rigid move of its solids, and the label box is exactly the object's tight box.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drcpo.synth.solids import BOX, CYLINDER, ELLIPSOID, Solids, make_solids

__all__ = ["CLASSES", "SIZE_STATS", "Actor", "make_actor", "sample_dims"]

CLASSES: tuple[str, ...] = ("Car", "Pedestrian", "Cyclist")

#: KITTI-like size statistics per class: mean and standard deviation of (length, width, height)
#: in metres, and the clip range as a fraction of the mean.
SIZE_STATS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "Car": ((3.9, 1.6, 1.56), (0.42, 0.1, 0.13)),
    "Pedestrian": ((0.8, 0.6, 1.73), (0.18, 0.08, 0.1)),
    "Cyclist": ((1.76, 0.6, 1.73), (0.15, 0.1, 0.08)),
}
_CLIP = (0.75, 1.3)


@dataclass(frozen=True, eq=False)
class Actor:
    """One object: class name, solids in canonical pose, and its tight box size ``dims (3,)``."""

    name: str
    solids: Solids
    dims: np.ndarray

    def box(self, x: float, y: float, ground_z: float, heading: float) -> np.ndarray:
        """The ``(7,)`` box of this actor standing on ground height ``ground_z`` at ``(x, y)``."""
        return np.array([x, y, ground_z + self.dims[2] / 2, *self.dims, heading])

    def placed(self, box: np.ndarray, owner: int) -> Solids:
        """The actor's solids at pose ``box`` (7,), tagged with ``owner``."""
        return self.solids.placed(box[0], box[1], box[2], box[6]).with_owner(owner)


def sample_dims(name: str, rng: np.random.Generator) -> np.ndarray:
    """A length, width, height ``(3,)`` drawn from the class's KITTI-like size distribution."""
    mean, std = (np.array(v) for v in SIZE_STATS[name])
    return np.clip(rng.normal(mean, std), mean * _CLIP[0], mean * _CLIP[1])


def make_actor(name: str, rng: np.random.Generator, dims: np.ndarray | None = None) -> Actor:
    """A procedural ``Car``, ``Pedestrian`` or ``Cyclist`` of about ``dims`` (l, w, h) metres."""
    if name not in _BUILDERS:
        raise ValueError(f"unknown actor class {name!r}; expected one of {CLASSES}")
    dims = sample_dims(name, rng) if dims is None else np.asarray(dims, dtype=np.float64)
    raw = _BUILDERS[name](dims, rng)
    low, high = raw.bounds()
    centred = raw.placed(
        -(low[0] + high[0]) / 2, -(low[1] + high[1]) / 2, -(low[2] + high[2]) / 2, 0
    )
    return Actor(name, centred, high - low)


def _car(dims: np.ndarray, rng: np.random.Generator) -> Solids:
    length, width, height = dims
    paint = "paint" if rng.random() < 0.6 else "dark_paint"
    wheel_r = float(np.clip(0.3 + 0.08 * (height - 1.5), 0.27, 0.4))
    wheel_half_w = 0.1
    axle_x = length / 2 - max(0.75, 0.21 * length)
    axle_y = width / 2 - wheel_half_w - 0.03
    body_bottom = wheel_r * 0.9
    body_top = body_bottom + (height - body_bottom) * rng.uniform(0.42, 0.5)
    roof = 0.05
    cabin_len = length * rng.uniform(0.45, 0.55)
    cabin_x = -length * rng.uniform(0.02, 0.1)
    cabin_half_w = width / 2 - 0.1
    body = (
        (0, 0, (body_bottom + body_top) / 2),
        (length / 2, width / 2, (body_top - body_bottom) / 2),
    )
    cabin_z = (body_top + height - roof) / 2
    cabin = ((cabin_x, 0, cabin_z), (cabin_len / 2, cabin_half_w, (height - roof - body_top) / 2))
    top = ((cabin_x, 0, height - roof / 2), (cabin_len / 2 - 0.05, cabin_half_w - 0.03, roof / 2))
    wheel = (wheel_r, wheel_half_w, wheel_r)
    rows = [(BOX, *body, 0, paint), (BOX, *cabin, 0, "glass"), (BOX, *top, 0, paint)]
    rows += [
        (ELLIPSOID, (sx * axle_x, sy * axle_y, wheel_r), wheel, 0, "tyre")
        for sx in (-1, 1)
        for sy in (-1, 1)
    ]
    return make_solids(rows)


def _pedestrian(dims: np.ndarray, rng: np.random.Generator) -> Solids:
    length, width, height = dims
    leg_r, arm_r, head_r = 0.07, 0.045, 0.1 * height / 1.73
    hip = 0.5 * height
    stride = max(length / 2 - leg_r, 0.0) * rng.uniform(0.6, 1.0)
    swing = max(length / 2 - arm_r, 0.0)
    shoulder = 0.82 * height
    torso_top = height - 2 * head_r - 0.03
    torso_half_w = max(width / 2 - 2 * arm_r - 0.01, 0.12)
    arm_y = torso_half_w + arm_r + 0.005
    torso = (0.13, torso_half_w, (torso_top - hip + 0.05) / 2)
    rows = [
        (CYLINDER, (stride, 0.09, hip / 2), (leg_r, leg_r, hip / 2), 0, "cloth"),
        (CYLINDER, (-stride, -0.09, hip / 2), (leg_r, leg_r, hip / 2), 0, "cloth"),
        (ELLIPSOID, (0, 0, (torso_top + hip - 0.05) / 2), torso, 0, "cloth"),
        (CYLINDER, (-swing, arm_y, shoulder - 0.17), (arm_r, arm_r, 0.17), 0, "cloth"),
        (CYLINDER, (swing, -arm_y, shoulder - 0.17), (arm_r, arm_r, 0.17), 0, "cloth"),
        (ELLIPSOID, (0, 0, height - head_r), (head_r, head_r * 0.85, head_r), 0, "skin"),
    ]
    return make_solids(rows)


def _cyclist(dims: np.ndarray, rng: np.random.Generator) -> Solids:
    length, width, height = dims
    wheel_r = float(np.clip(0.17 * length + 0.04, 0.28, 0.38))
    wheel_x = length / 2 - wheel_r
    s = height / 1.73  # rider scale
    lean = rng.uniform(-0.05, 0.1)  # upright to leaning over the handlebar
    thigh = (0.065, 0.065, 0.28 * s)
    arm = (wheel_x * 0.5, 0.04, 0.04)
    head = (0.11 * s, 0.095, 0.11 * s)
    rows = [
        (ELLIPSOID, (wheel_x, 0, wheel_r), (wheel_r, 0.03, wheel_r), 0, "tyre"),
        (ELLIPSOID, (-wheel_x, 0, wheel_r), (wheel_r, 0.03, wheel_r), 0, "tyre"),
        (BOX, (0, 0, wheel_r + 0.2), (wheel_x * 0.8, 0.03, 0.15), 0, "metal"),
        (BOX, (wheel_x - 0.12, 0, 1.0 * s), (0.03, width / 2, 0.03), 0, "metal"),
        (CYLINDER, (-0.1, 0.12, 0.35 + 0.28 * s), thigh, 0, "cloth"),
        (CYLINDER, (-0.1, -0.12, 0.35 + 0.28 * s), thigh, 0, "cloth"),
        (ELLIPSOID, (lean, 0, 1.2 * s), (0.28, 0.18, 0.3 * s), 0, "cloth"),
        (BOX, (wheel_x * 0.5 - 0.05 + lean / 2, 0.2, 1.15 * s), arm, 0, "cloth"),
        (BOX, (wheel_x * 0.5 - 0.05 + lean / 2, -0.2, 1.15 * s), arm, 0, "cloth"),
        (ELLIPSOID, (0.12 + lean, 0, height - 0.11 * s), head, 0, "skin"),
    ]
    return make_solids(rows)


_BUILDERS = {"Car": _car, "Pedestrian": _pedestrian, "Cyclist": _cyclist}
