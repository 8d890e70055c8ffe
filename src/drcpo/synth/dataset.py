"""Synthetic KITTI data sets: worlds swept by the sensor, labelled from ray-cast truth.

Frame i of a data set seeded with ``seed`` uses its own generator
``default_rng(SeedSequence([seed, i]))``, so any frame can be regenerated alone, in any order.
Labels follow KITTI: only objects the camera sees (part of the box inside the image) and the
LiDAR reaches (at least one ray hits them first) are labelled; occlusion levels come from the
blocked fraction of the object's rays, truncation from the fraction of its box outside the image.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drcpo.datasets.kitti_coordinates import DEFAULT_IMAGE_SHAPE, Calibration
from drcpo.datasets.kitti_writer import (
    REFERENCE_CALIB,
    project_boxes,
    reference_calibration,
    write_frame,
    write_image_sets,
)
from drcpo.errors import ConfigError
from drcpo.outputs import OutputKind, write_directory
from drcpo.synth.scan import Sweep, Visibility, actor_visibility, occlusion_level, scan
from drcpo.synth.sensor import LidarConfig
from drcpo.synth.world import World, WorldConfig, generate_world

__all__ = [
    "SYNTH_FORMAT",
    "SYNTH_FORMAT_VERSION",
    "SYNTH_MANIFEST",
    "SYNTH_OUTPUT",
    "SyntheticFrame",
    "frame_rng",
    "matches",
    "split_ids",
    "synth_parameters",
    "synthesize_frame",
    "write_synthetic_kitti",
]

SYNTH_MANIFEST = "synth.json"
SYNTH_FORMAT_VERSION = 1
SYNTH_FORMAT = "drcpo-synthetic-kitti"
SYNTH_OUTPUT = OutputKind(
    "drcpo synthetic KITTI data set", SYNTH_MANIFEST, SYNTH_FORMAT, ("training", "ImageSets")
)


@dataclass(frozen=True, eq=False)
class SyntheticFrame:
    """One generated frame and its truth.

    Attributes:
        world: the world swept.
        sweep: the sensor's returns (``sweep.points`` is the velodyne point cloud).
        visibility: per actor ray counts (reachable alone, seen first in the world).
        labelled: ``int64 (K,)`` actors written to ``label_2``, in label order.
        occlusion: ``int8 (K,)`` KITTI occlusion level of each labelled actor.
        truncation: ``float64 (K,)`` fraction of each labelled box outside the image.
    """

    world: World
    sweep: Sweep
    visibility: Visibility
    labelled: np.ndarray
    occlusion: np.ndarray
    truncation: np.ndarray

    @property
    def boxes(self) -> np.ndarray:
        """LiDAR boxes ``(K, 7)`` of the labelled actors."""
        return self.world.boxes[self.labelled]

    @property
    def names(self) -> np.ndarray:
        return self.world.names[self.labelled]


def frame_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of frame ``index`` of a data set seeded with ``seed``."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))


def synthesize_frame(
    rng: np.random.Generator,
    world_config: WorldConfig | None = None,
    lidar_config: LidarConfig | None = None,
    calib: Calibration | None = None,
    image_shape: tuple[int, int] = DEFAULT_IMAGE_SHAPE,
) -> SyntheticFrame:
    """Generate a world, sweep it, and label it as KITTI would."""
    lidar_config = lidar_config or LidarConfig()
    calib = calib or reference_calibration()
    world = generate_world(rng, world_config, mount_height=lidar_config.mount_height)
    sweep = scan(world, rng, lidar_config)
    visibility = actor_visibility(world, sweep, lidar_config)
    _, truncation = project_boxes(world.boxes, calib, image_shape)
    labelled = np.flatnonzero((truncation < 1.0) & (visibility.seen > 0))
    return SyntheticFrame(
        world=world,
        sweep=sweep,
        visibility=visibility,
        labelled=labelled,
        occlusion=occlusion_level(visibility.blocked[labelled]),
        truncation=truncation[labelled],
    )


def split_ids(frame_ids: list[str], val_fraction: float) -> dict[str, list[str]]:
    """``train`` / ``val`` / ``trainval`` splits: the last ``val_fraction`` of frames are val."""
    if not 0.0 <= val_fraction < 1.0:
        raise ConfigError(f"val_fraction must be in [0, 1), got {val_fraction}")
    val = int(np.floor(len(frame_ids) * val_fraction))
    cut = len(frame_ids) - val
    return {"train": frame_ids[:cut], "val": frame_ids[cut:], "trainval": list(frame_ids)}


def write_synthetic_kitti(
    root: str | os.PathLike,
    frames: int,
    seed: int = 0,
    world_config: WorldConfig | None = None,
    lidar_config: LidarConfig | None = None,
    val_fraction: float = 0.5,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Write ``frames`` synthetic frames in KITTI layout under ``root`` (atomically, as a whole).

    Also writes ``root/synth.json`` with the parameters, so a cache can tell whether a data set
    matches. Returns a summary: frames, points per frame, labelled objects per class, occlusion
    level counts and the mean generation time per frame in ms.
    """
    import time

    if frames < 1:
        raise ConfigError(f"frames must be >= 1, got {frames}")
    world_config = world_config or WorldConfig()
    lidar_config = lidar_config or LidarConfig()
    ids = [f"{i:06d}" for i in range(frames)]
    summary: dict[str, Any] = {"frames": frames, "points": [], "objects": {}, "occlusion": {}}
    timings: list[float] = []

    def write(tmp: Path) -> None:
        for number, frame_id in enumerate(ids):
            start = time.perf_counter()
            frame = synthesize_frame(frame_rng(seed, number), world_config, lidar_config)
            timings.append((time.perf_counter() - start) * 1e3)
            write_frame(
                tmp,
                frame_id,
                frame.sweep.points,
                frame.boxes,
                frame.names.tolist(),
                reference_calibration(),
                occlusion=frame.occlusion,
                truncation=frame.truncation,
                other_matrices=REFERENCE_CALIB,
            )
            summary["points"].append(len(frame.sweep.points))
            for name in frame.names.tolist():
                summary["objects"][name] = summary["objects"].get(name, 0) + 1
            for level in frame.occlusion.tolist():
                summary["occlusion"][str(level)] = summary["occlusion"].get(str(level), 0) + 1
            if progress is not None:
                progress(number + 1, frames)
        write_image_sets(tmp, split_ids(ids, val_fraction))
        manifest = synth_parameters(frames, seed, world_config, lidar_config, val_fraction)
        (tmp / SYNTH_MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")

    write_directory(root, write, SYNTH_OUTPUT, overwrite)
    summary["ms_per_frame"] = float(np.mean(timings))
    return summary


def synth_parameters(
    frames: int,
    seed: int,
    world_config: WorldConfig,
    lidar_config: LidarConfig,
    val_fraction: float,
) -> dict[str, Any]:
    """The parameters that determine a synthetic data set (what ``synth.json`` records)."""
    return {
        "format": SYNTH_FORMAT,
        "format_version": SYNTH_FORMAT_VERSION,
        "frames": int(frames),
        "seed": int(seed),
        "val_fraction": float(val_fraction),
        "world": asdict(world_config),
        "lidar": asdict(lidar_config),
    }


def matches(root: str | os.PathLike, parameters: dict[str, Any]) -> bool:
    """Whether ``root`` holds a complete synthetic data set made with ``parameters``."""
    path = Path(root) / SYNTH_MANIFEST
    try:
        stored = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return False
    return stored == json.loads(json.dumps(parameters))
