"""Synthetic nuScenes-style data sets: the synthetic street world driven through by a car with a
32-beam LiDAR, written in the nuScenes layout (:mod:`drcpo.datasets.nuscenes_writer`).

A scene is one :class:`~drcpo.synth.world.World` (built in the frame ``W`` of the sensor at
time 0, street along x) seen over time: the ego car drives along the street at a constant
speed; some actors (cars, cyclists, pedestrians) move along their heading at constant
velocities, the rest stand. Sweeps come every 50 ms (20 Hz), every tenth a key sweep (a
sample, 2 Hz) that carries the boxes, preceded by ``sweeps_before`` sweeps so that even the
first sample has a history. Each sweep is cast instantaneously at its time (no rolling shutter)
with the sensor and every solid moved into the LiDAR frame of that instant.

Frames, as nuScenes defines them: the ego frame (origin on the ground under the rear axle,
x forward) 0.94 m behind and 1.84 m below the LiDAR; the LiDAR frame x right, y forward
(rotated -90 degrees about z from the ego frame); the global frame ``W`` rotated by a random
yaw and shifted by a random offset (so that no transform is the identity). Classes map to
nuScenes categories (:data:`CATEGORY_OF`); an actor is annotated at every key sample with its
``num_lidar_pts`` (the key sweep's points in its box; the readers drop boxes without any).
Intensity is the world's reflectance times 255; the ring index counts beams from the lowest
(0) up, as Velodyne drivers number them.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from drcpo.datasets.nuscenes_geometry import yaw_quaternion
from drcpo.datasets.nuscenes_writer import (
    AnnotationRecord,
    SceneRecord,
    SweepRecord,
    write_nuscenes,
)
from drcpo.errors import ConfigError
from drcpo.geometry import bev_overlap_area, points_in_boxes, rotate_points_z, wrap_angle
from drcpo.synth.dataset import frame_rng
from drcpo.synth.raycast import Ground, Scene
from drcpo.synth.scan import scan_rays
from drcpo.synth.sensor import LidarConfig, lidar_preset, ray_grid
from drcpo.synth.solids import Solids
from drcpo.synth.world import World, WorldConfig, generate_world, support_height

__all__ = [
    "CATEGORY_OF",
    "LIDAR_IN_EGO",
    "SPEEDS",
    "NuScenesSynthConfig",
    "SyntheticScene",
    "synthesize_scene",
    "write_synthetic_nuscenes",
]

#: The synthetic world's classes as nuScenes categories (a cyclist's box holds its rider, as
#: nuScenes annotates a ridden bicycle).
CATEGORY_OF = {
    "Car": "vehicle.car",
    "Pedestrian": "human.pedestrian.adult",
    "Cyclist": "vehicle.bicycle",
}
#: Speed range (m/s) of a moving actor per class.
SPEEDS = {"Car": (4.0, 10.0), "Pedestrian": (0.8, 1.6), "Cyclist": (2.5, 5.5)}
#: The LiDAR's place in the ego frame, metres, before its mount height: nuScenes' LIDAR_TOP
#: sits about 0.94 m ahead of the rear axle.
LIDAR_IN_EGO = 0.94
_SWEEP_US = 50_000  # 20 Hz
_EGO_BOX = (4.8, 2.0)  # length, width of the recording car, metres
_FIRST_TIMESTAMP = 1_500_000_000_000_000  # microseconds
_SCENE_SPACING_US = 60_000_000  # a minute between scene starts: longer than any scene


@dataclass(frozen=True)
class NuScenesSynthConfig:
    """Parameters of a synthetic nuScenes-style data set.

    Attributes:
        samples: key samples per scene (2 Hz).
        sweeps_per_sample: sweeps from one key sample to the next (10 at 20 Hz).
        sweeps_before: sweeps before a scene's first key sample.
        ego_speed: range of the ego car's speed, m/s.
        moving_probability: chance that an actor moves.
        sensor: the :func:`~drcpo.synth.sensor.lidar_preset` (``hdl32e``: nuScenes').
    """

    samples: int = 4
    sweeps_per_sample: int = 10
    sweeps_before: int = 10
    ego_speed: tuple[float, float] = (3.0, 8.0)
    moving_probability: float = 0.6
    sensor: str = "hdl32e"
    world: WorldConfig = field(default_factory=WorldConfig)

    def __post_init__(self) -> None:
        checks = {
            "samples": 1 <= self.samples <= 100,
            "sweeps_per_sample": 1 <= self.sweeps_per_sample <= 40,
            "sweeps_before": 0 <= self.sweeps_before <= 100,
            "ego_speed": 0.0 <= self.ego_speed[0] <= self.ego_speed[1] <= 20.0,
            "moving_probability": 0.0 <= self.moving_probability <= 1.0,
        }
        for name, ok in checks.items():
            if not ok:
                raise ConfigError(
                    f"NuScenesSynthConfig.{name} = {getattr(self, name)!r} is out of range"
                )
        lidar_preset(self.sensor)

    @property
    def lidar(self) -> LidarConfig:
        return lidar_preset(self.sensor)

    @property
    def num_sweeps(self) -> int:
        return self.sweeps_before + (self.samples - 1) * self.sweeps_per_sample + 1


@dataclass(frozen=True, eq=False)
class SyntheticScene:
    """One generated scene and its truth.

    Attributes:
        record: what is written (sweeps, annotations, instances).
        world: the world in frame ``W`` at time 0 (moving actors' boxes at their start).
        velocity: ``float64 (M, 2)`` each actor's velocity in ``W``, m/s (0 for standing ones).
        times: ``float64 (T,)`` each sweep's time since the first, seconds.
        sensor_position: ``float64 (T, 3)`` the LiDAR's position in ``W`` per sweep.
        sensor_yaw: ``float64 (T,)`` the LiDAR frame's yaw in ``W`` (its x axis), radians.
        global_yaw, global_offset: ``W`` -> global: rotate by ``global_yaw``, then shift.
    """

    record: SceneRecord | None
    world: World
    velocity: np.ndarray
    times: np.ndarray
    sensor_position: np.ndarray
    sensor_yaw: np.ndarray
    global_yaw: float
    global_offset: np.ndarray

    def boxes_at(self, sweep: int) -> np.ndarray:
        """``(M, 7)`` every actor's box in the LiDAR frame of sweep ``sweep``."""
        boxes = _boxes_in_w(self.world, self.velocity, self.times[sweep])
        return _to_sensor(boxes, self.sensor_position[sweep], self.sensor_yaw[sweep])

    def velocity_at(self, sweep: int) -> np.ndarray:
        """``(M, 2)`` every actor's velocity in the LiDAR frame of sweep ``sweep``, m/s."""
        return rotate_points_z(self.velocity, -self.sensor_yaw[sweep])


def synthesize_scene(
    rng: np.random.Generator,
    name: str,
    config: NuScenesSynthConfig | None = None,
    number: int = 0,
) -> SyntheticScene:
    """Generate, drive through and sweep one scene (the same generator state, the same scene).

    Scene ``number`` of a data set starts :data:`_SCENE_SPACING_US` after the one before, as a
    recording's scenes follow one another (the devkit orders scenes by their start).
    """
    config = config or NuScenesSynthConfig()
    lidar = config.lidar
    world = generate_world(rng, config.world, mount_height=lidar.mount_height)
    times = np.arange(config.num_sweeps) * (_SWEEP_US * 1e-6)
    speed = rng.uniform(*config.ego_speed)
    heading = world.street.yaw
    direction = np.array([math.cos(heading), math.sin(heading), 0.0])
    sensor_position = times[:, None] * speed * direction
    sensor_yaw = np.full(len(times), heading - math.pi / 2)
    world, velocity = _set_in_motion(rng, world, config, times[-1], speed)
    global_yaw = float(rng.uniform(-math.pi, math.pi))
    global_offset = np.array([*rng.uniform(200.0, 2000.0, 2), 0.0])
    scene = SyntheticScene(
        record=None,  # the sweeps are cast from this scene's motion; filled in below
        world=world,
        velocity=velocity,
        times=times,
        sensor_position=sensor_position,
        sensor_yaw=sensor_yaw,
        global_yaw=global_yaw,
        global_offset=global_offset,
    )
    sweeps, annotations = [], []
    for i in range(len(times)):
        key = (
            i >= config.sweeps_before and (i - config.sweeps_before) % config.sweeps_per_sample == 0
        )
        points = _sweep(rng, scene, i, lidar)
        ego_t, ego_q = _ego_pose(scene, i, lidar.mount_height)
        stamp = _FIRST_TIMESTAMP + number * _SCENE_SPACING_US + i * _SWEEP_US
        sweeps.append(SweepRecord(stamp, points, ego_t, ego_q, key))
        if key:
            annotations.append(_annotations(scene, i, points))
    record = SceneRecord(
        name=name,
        sweeps=sweeps,
        annotations=annotations,
        instances=[CATEGORY_OF[str(n)] for n in world.names],
        lidar_translation=np.array([LIDAR_IN_EGO, 0.0, lidar.mount_height]),
        lidar_rotation=yaw_quaternion(-math.pi / 2),
        description=f"drcpo synthetic street, ego at {speed:.1f} m/s",
    )
    return replace(scene, record=record)


def _boxes_in_w(world: World, velocity: np.ndarray, t: float) -> np.ndarray:
    """Actors' boxes at time ``t`` in ``W``: moved along their velocity, standing on what is
    under their new centre."""
    boxes = world.boxes.copy()
    moving = np.any(velocity != 0.0, axis=1)
    boxes[moving, :2] += velocity[moving] * t
    ground = support_height(world.ground, world.sidewalks, boxes[moving, 0], boxes[moving, 1])
    boxes[moving, 2] = ground + boxes[moving, 5] / 2
    return boxes


def _to_sensor(boxes: np.ndarray, position: np.ndarray, yaw: float) -> np.ndarray:
    out = boxes.copy()
    out[:, :3] = rotate_points_z(boxes[:, :3] - position, -yaw)
    out[:, 6] = wrap_angle(boxes[:, 6] - yaw)
    return out


def _set_in_motion(
    rng: np.random.Generator,
    world: World,
    config: NuScenesSynthConfig,
    duration: float,
    speed: float,
) -> tuple[World, np.ndarray]:
    """Draw the actors' velocities; an actor moves only if its swept footprint stays clear of
    the obstacles, of the ego car's path and of the other actors' paths. Actors standing in the
    ego car's path are removed."""
    heading = world.street.yaw
    travel = speed * duration
    ego = np.array(
        [[0.0, 0.0, 0.0, travel + _EGO_BOX[0] + 1.0, _EGO_BOX[1] + 1.0, 2.0, heading]]
    )  # the ego car's path, 0.5 m clear all round
    ego[0, :2] = travel / 2 * np.array([math.cos(heading), math.sin(heading)])
    count = len(world.boxes)
    moves = rng.random(count) < config.moving_probability
    speeds = np.array([rng.uniform(*SPEEDS[str(n)]) for n in world.names])
    paths = world.boxes.copy()
    keep = ~(bev_overlap_area(paths, ego) > 0).any(axis=1)
    velocity = np.zeros((count, 2))
    for i in np.flatnonzero(moves & keep):
        path = _swept(world.boxes[i], speeds[i] * duration)
        others = np.concatenate([paths[keep & (np.arange(count) != i)], world.obstacles, ego])
        if not (bev_overlap_area(path[None], others) > 0).any():
            paths[i] = path
            velocity[i] = speeds[i] * np.array(
                [math.cos(world.boxes[i, 6]), math.sin(world.boxes[i, 6])]
            )
    rows = np.flatnonzero(keep)
    world = World(
        ground=world.ground,
        street=world.street,
        static=world.static,
        actors=tuple(world.actors[i] for i in rows),
        boxes=world.boxes[rows],
        names=world.names[rows],
        sidewalks=world.sidewalks,
        obstacles=world.obstacles,
    )
    return world, velocity[rows]


def _swept(box: np.ndarray, distance: float) -> np.ndarray:
    """The footprint a box covers moving ``distance`` metres along its heading."""
    out = box.copy()
    out[:2] += distance / 2 * np.array([math.cos(box[6]), math.sin(box[6])])
    out[3] += distance
    return out


class _MovedWorld:
    """What :func:`~drcpo.synth.scan.scan_rays` reads of a world (ground materials), in the
    LiDAR frame of one sweep."""

    def __init__(self, world: World, position: np.ndarray, yaw: float) -> None:
        self.world, self.position, self.yaw = world, position, yaw

    def ground_material(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        xy = rotate_points_z(np.column_stack([x, y]), self.yaw) + self.position[:2]
        return self.world.ground_material(xy[:, 0], xy[:, 1])


def _moved_ground(ground: Ground, position: np.ndarray, yaw: float) -> Ground:
    """``ground`` seen from a frame at ``position`` (in ``W``) rotated by ``yaw`` about z: a
    rotated wave vector, a shifted phase and base (the field is a sum of plane waves)."""
    cos, sin = math.cos(yaw), math.sin(yaw)
    wave_x = cos * ground.wave_x + sin * ground.wave_y
    wave_y = -sin * ground.wave_x + cos * ground.wave_y
    phase = ground.phase + ground.wave_x * position[0] + ground.wave_y * position[1]
    return Ground(ground.base - position[2], ground.amplitude, wave_x, wave_y, phase)


def _sweep(
    rng: np.random.Generator, scene: SyntheticScene, i: int, lidar: LidarConfig
) -> np.ndarray:
    """The ``float32 (N, 5)`` points of sweep ``i`` in its LiDAR frame."""
    world, position, yaw = scene.world, scene.sensor_position[i], scene.sensor_yaw[i]
    boxes = _boxes_in_w(world, scene.velocity, scene.times[i])
    placed = [a.placed(b, n) for n, (a, b) in enumerate(zip(world.actors, boxes, strict=True))]
    to_sensor = -rotate_points_z(position[None], -yaw)[0]
    solids = [world.static, *placed]
    moved = [s.placed(*to_sensor, -yaw) for s in solids]
    cast = Scene(Solids.concatenate(moved), _moved_ground(world.ground, position, yaw))
    step = 2 * math.pi / lidar.num_columns
    grid = ray_grid(lidar, azimuth_offset=rng.uniform(0, step))
    sweep = scan_rays(_MovedWorld(world, position, yaw), grid, rng, lidar, scene=cast)
    ring_of_beam = np.argsort(np.argsort(np.asarray(lidar.elevations_deg)))
    ring = ring_of_beam[sweep.ray // lidar.num_columns]
    intensity = np.round(sweep.points[:, 3].astype(np.float64) * 255.0)
    return np.column_stack([sweep.points[:, :3], intensity, ring]).astype(np.float32)


def _ego_pose(scene: SyntheticScene, i: int, mount_height: float) -> tuple[np.ndarray, np.ndarray]:
    """Ego -> global pose of sweep ``i``: translation and ``w, x, y, z`` quaternion."""
    ego_yaw = scene.sensor_yaw[i] + math.pi / 2
    behind = rotate_points_z(np.array([[LIDAR_IN_EGO, 0.0]]), ego_yaw)[0]
    ego_w = np.array(
        [*(scene.sensor_position[i, :2] - behind), scene.sensor_position[i, 2] - mount_height]
    )
    ego_g = _w_to_global(scene, ego_w[None])[0]
    return ego_g, yaw_quaternion(ego_yaw + scene.global_yaw)


def _w_to_global(scene: SyntheticScene, xyz: np.ndarray) -> np.ndarray:
    return rotate_points_z(xyz, scene.global_yaw) + scene.global_offset


def _annotations(scene: SyntheticScene, i: int, points: np.ndarray) -> list[AnnotationRecord]:
    boxes_w = _boxes_in_w(scene.world, scene.velocity, scene.times[i])
    inside = points_in_boxes(points[:, :3], scene.boxes_at(i)).sum(axis=0)
    centre = _w_to_global(scene, boxes_w[:, :3])
    rotation = yaw_quaternion(boxes_w[:, 6] + scene.global_yaw)
    return [
        AnnotationRecord(
            instance=n,
            translation=centre[n],
            size=boxes_w[n, [4, 3, 5]],  # w, l, h
            rotation=rotation[n],
            num_lidar_pts=int(inside[n]),
        )
        for n in range(len(boxes_w))
    ]


def write_synthetic_nuscenes(
    root: str | os.PathLike,
    scenes: int,
    seed: int = 0,
    config: NuScenesSynthConfig | None = None,
    version: str = "v1.0-trainval",
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Write ``scenes`` synthetic scenes (scene ``i`` from ``frame_rng(seed, i)``) in the
    nuScenes layout under ``root``, atomically. Returns a summary: scenes, samples, sweeps,
    points per key sweep, annotated boxes with points per class, moving ones, and the time per
    sweep in ms."""
    if scenes < 1:
        raise ConfigError(f"scenes must be >= 1, got {scenes}")
    config = config or NuScenesSynthConfig()
    summary: dict[str, Any] = {
        "scenes": scenes,
        "samples": 0,
        "sweeps": 0,
        "points": [],
        "objects": {},
        "moving": 0,
    }
    started = time.perf_counter()

    def generate():
        for number in range(scenes):
            scene = synthesize_scene(frame_rng(seed, number), f"scene-{number:04d}", config, number)
            record = scene.record
            summary["samples"] += len(record.annotations)
            summary["sweeps"] += len(record.sweeps)
            summary["moving"] += int(np.any(scene.velocity != 0, axis=1).sum())
            summary["points"] += [len(s.points) for s in record.sweeps if s.key]
            for boxes in record.annotations:
                for box in boxes:
                    if box.num_lidar_pts:
                        name = record.instances[box.instance]
                        summary["objects"][name] = summary["objects"].get(name, 0) + 1
            if progress is not None:
                progress(number + 1, scenes)
            yield record

    manifest = {
        "generator": "drcpo synth",
        "scenes": scenes,
        "seed": int(seed),
        "config": _jsonable(asdict(config)),
    }
    write_nuscenes(root, generate(), version, overwrite, manifest)
    summary["ms_per_sweep"] = (time.perf_counter() - started) * 1e3 / max(summary["sweeps"], 1)
    return summary


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value
