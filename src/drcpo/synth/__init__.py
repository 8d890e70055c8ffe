"""A built-in LiDAR world: a ray-cast HDL-64E-like sensor in procedural streets.

It writes KITTI-layout data with labels computed from true visibility, and tells which points
of an object placed in a frame the sensor truly sees (the reference for HPR occlusion).

Modules: :mod:`.sensor` (sensor model), :mod:`.solids` (primitives), :mod:`.raycast`,
:mod:`.actors` (Car, Pedestrian, Cyclist), :mod:`.world` (procedural street), :mod:`.scan`
(sweeps and per-object visibility), :mod:`.truth` (visibility of arbitrary points),
:mod:`.dataset` (KITTI data sets), :mod:`.nuscenes` (nuScenes-style data sets: scenes of key
samples and 20 Hz sweeps from a 32-beam sensor on a moving car, moving actors).
"""

from drcpo.synth.actors import CLASSES, Actor, make_actor
from drcpo.synth.dataset import (
    SyntheticFrame,
    frame_rng,
    synthesize_frame,
    write_synthetic_kitti,
)
from drcpo.synth.nuscenes import NuScenesSynthConfig, synthesize_scene, write_synthetic_nuscenes
from drcpo.synth.raycast import Ground, RayHits, Scene
from drcpo.synth.scan import Sweep, Visibility, actor_visibility, occlusion_level, scan
from drcpo.synth.sensor import (
    HDL32E_MOUNT_HEIGHT,
    LidarConfig,
    RayGrid,
    hdl32e_elevations,
    hdl64e_elevations,
    lidar_preset,
    ray_grid,
)
from drcpo.synth.solids import Solids
from drcpo.synth.truth import PlacedObjectTruth, free_pose, place_object, visible_points
from drcpo.synth.world import World, WorldConfig, generate_world

__all__ = [
    "CLASSES",
    "HDL32E_MOUNT_HEIGHT",
    "Actor",
    "Ground",
    "LidarConfig",
    "NuScenesSynthConfig",
    "PlacedObjectTruth",
    "RayGrid",
    "RayHits",
    "Scene",
    "Solids",
    "Sweep",
    "SyntheticFrame",
    "Visibility",
    "World",
    "WorldConfig",
    "actor_visibility",
    "frame_rng",
    "free_pose",
    "generate_world",
    "hdl32e_elevations",
    "hdl64e_elevations",
    "lidar_preset",
    "make_actor",
    "occlusion_level",
    "place_object",
    "ray_grid",
    "scan",
    "synthesize_frame",
    "synthesize_scene",
    "visible_points",
    "write_synthetic_kitti",
    "write_synthetic_nuscenes",
]
