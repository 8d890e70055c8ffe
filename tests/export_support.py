"""What tests of offline generation share: a small KITTI root, a cheap random transform, the
bytes of an output tree."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drcpo.datasets.export import TIMINGS_FILE
from drcpo.transforms import Compose, GlobalFlip, GlobalRotation, GlobalScaling


def small_kitti(root: Path, frames: int = 6, points: int = 2000) -> Path:
    """A KITTI root written with drcpo's writer: ``frames`` frames of split train, two cars each."""
    from drcpo.datasets.kitti_writer import reference_calibration, write_frame, write_image_sets

    rng = np.random.default_rng(11)
    ids = [f"{i:06d}" for i in range(frames)]
    for frame_id in ids:
        xyz = np.column_stack(
            [rng.uniform(5, 40, points), rng.uniform(-10, 10, points), rng.uniform(-1.5, 1, points)]
        )
        cloud = np.column_stack([xyz, rng.uniform(0, 1, points)]).astype(np.float32)
        boxes = np.array(
            [[15.0, 0.0, -0.8, 4.0, 1.7, 1.5, 0.3], [25.0, 3.0, -0.8, 4.2, 1.8, 1.5, 1]]
        )
        write_frame(root, frame_id, cloud, boxes, ["Car", "Car"], reference_calibration())
    write_image_sets(root, {"train": ids})
    return root


def random_transform() -> Compose:
    """Global augmentation: cheap, and every frame's output depends on its generator."""
    return Compose([GlobalFlip(0.5), GlobalRotation((-0.5, 0.5)), GlobalScaling((0.9, 1.1))])


def tree_bytes(root: Path, timings: bool = False) -> dict[str, bytes]:
    """Every file under ``root`` (relative path -> bytes); ``timings.jsonl`` only if asked."""
    files = {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }
    if not timings:
        files.pop(TIMINGS_FILE, None)
    return files


def drcpo_world(tmp_path: Path):
    """A small KITTI root, a database built from it and its saved candidate index."""
    from drcpo.database.build import build_database
    from drcpo.index import IndexConfig
    from drcpo.index_build import build_index

    root = small_kitti(tmp_path / "kitti")
    db = build_database(root, "train", tmp_path / "db")
    index = build_index(db, IndexConfig(k=5))
    index.save(db.path)
    return root, db, index
