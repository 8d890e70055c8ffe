"""Load a transform's compiled kernels ahead of time, so that forked workers inherit them.

drcpo's kernels are compiled with numba and cached on disk; a process still pays for loading
them on its first call (more on a cold cache). Data loaders fork their workers from the
main process, often anew every epoch: calling :func:`warmup` once in the main process, before the
loader starts, makes every worker's first call as fast as its later ones. The warm-up frame's
C-ordered arrays stand for any input: a :class:`~drcpo.frame.Frame` makes its points and boxes
C-contiguous and writeable, so a worker given, say, Fortran-ordered points (mmdet3d's) calls the
same kernel specialisations.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from drcpo.frame import Frame

__all__ = ["warmup", "warmup_frame"]

#: Height of the warm-up frame's flat ground below the sensor (metres; KITTI's is about 1.7).
_GROUND_Z = -1.7


def warmup_frame(database: Any = None, point_dim: int = 4) -> Frame:
    """A small synthetic frame: a flat ground grid ``(N, point_dim)`` and, when ``database`` is
    given, its first object of each class standing on it (so every stage has work to do)."""
    if database is not None and len(database):
        point_dim = int(database.points.shape[1])
    x, y = np.meshgrid(np.arange(2.0, 60.0, 0.5), np.arange(-30.0, 30.0, 0.5), indexing="ij")
    ground = np.zeros((x.size, point_dim), dtype=np.float32)
    ground[:, 0], ground[:, 1], ground[:, 2] = x.ravel(), y.ravel(), _GROUND_Z
    if database is None or not len(database):
        return Frame(points=ground, metadata={"frame_id": "warmup"})
    from drcpo.transforms.insertion import placed_objects

    names = database.names
    rows = np.array([np.flatnonzero(names == n)[0] for n in np.unique(names)], dtype=np.int64)
    boxes = np.array(database.boxes[rows], dtype=np.float64).reshape(-1, 7)
    # In a row in front of the sensor, each on the ground, 8 m apart.
    boxes[:, 0] = 10.0 + 8.0 * np.arange(len(rows))
    boxes[:, 1] = 0.0
    boxes[:, 2] = _GROUND_Z + boxes[:, 5] / 2.0
    objects = placed_objects(database, rows, boxes, point_dim)
    return Frame(
        points=np.concatenate([ground, objects]),
        boxes=boxes,
        names=names[rows].astype(str),
        metadata={"frame_id": "warmup"},
    )


def warmup(transform: Any, seed: int = 0) -> float:
    """Run ``transform`` once on :func:`warmup_frame` (with its database, when it has one) to load
    its compiled kernels in this process; returns the seconds it took. The result is discarded
    and nothing else changes (the generator is a fresh one)."""
    start = time.perf_counter()
    database = _database_of(transform)
    transform(warmup_frame(database), np.random.default_rng(seed))
    return time.perf_counter() - start


def _database_of(transform: Any) -> Any:
    """The ground-truth database a transform (or one of a composition's) draws from."""
    for t in getattr(transform, "transforms", (transform,)):
        database = getattr(t, "database", None)
        if database is not None:
            return database
    return None
