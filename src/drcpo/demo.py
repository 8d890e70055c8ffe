"""``drcpo demo``: run every stage that exists on built-in data, on a fresh machine."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drcpo.database import GroundTruthDatabase, ObjectRecord
from drcpo.geometry import points_in_boxes, rotate_points_z, to_canonical

_CLASS_SIZES = {
    "Car": (3.9, 1.6, 1.56),
    "Pedestrian": (0.8, 0.6, 1.73),
    "Cyclist": (1.76, 0.6, 1.73),
}


def tiny_scene(rng: np.random.Generator, objects: int = 12) -> tuple[np.ndarray, np.ndarray, list]:
    """A small scene: flat ground and box-shaped objects sampled on their visible faces."""
    ground = np.column_stack(
        [rng.uniform(0, 60, 20000), rng.uniform(-30, 30, 20000), np.full(20000, -1.73)]
    )
    names = rng.choice(list(_CLASS_SIZES), size=objects)
    dims = np.array([_CLASS_SIZES[n] for n in names]) * rng.uniform(0.9, 1.1, (objects, 3))
    centres = np.column_stack(
        [rng.uniform(5, 55, objects), rng.uniform(-25, 25, objects), -1.73 + dims[:, 2] / 2]
    )
    boxes = np.column_stack([centres, dims, rng.uniform(-np.pi, np.pi, objects)])
    surface = []
    for box in boxes:
        local = rng.uniform(-0.5, 0.5, (600, 3)) * box[3:6]
        face = rng.integers(0, 3, 600)
        local[np.arange(600), face] = np.sign(local[np.arange(600), face]) * box[3 + face] / 2
        surface.append(rotate_points_z(local, box[6]) + box[:3])
    xyz = np.concatenate([ground, *surface])
    points = np.column_stack([xyz, rng.uniform(0, 1, len(xyz))]).astype(np.float32)
    return points, boxes, names.tolist()


def run_demo(out: Path, seed: int = 0) -> GroundTruthDatabase:
    """Build a ground-truth database from a tiny built-in scene under ``out``."""
    rng = np.random.default_rng(seed)
    points, boxes, names = tiny_scene(rng)
    inside = points_in_boxes(points, boxes)
    records = [
        ObjectRecord(to_canonical(points[inside[:, i]], boxes[i]), names[i], boxes[i], "demo", i)
        for i in range(len(boxes))
    ]
    database = GroundTruthDatabase.from_records(records)
    database.save(out / "gt_database", parameters={"source": "built-in demo scene"}, overwrite=True)
    return GroundTruthDatabase.open(out / "gt_database")
