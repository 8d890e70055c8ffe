"""``drcpo augment`` on a cluster: long-lived Ray actors each open the memory-mapped database and
index once, rebuild the transform from its config and load its compiled kernels once
(:func:`drcpo.warmup.warmup`), then augment the frames handed to them in order. Each frame uses
its own generator (:func:`~drcpo.datasets.export.frame_seed`) and is written atomically into
the run's staging directory (:func:`~drcpo.datasets.export.augment_frame`), so the output is the
same bytes as the one-process run and a killed run resumes."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import closing
from pathlib import Path
from typing import Any

from drcpo.database import GroundTruthDatabase
from drcpo.datasets.export import augment_frame, augment_kitti
from drcpo.datasets.kitti import KittiDataset
from drcpo.distributed.cluster import (
    LOCAL,
    Cluster,
    connected,
    kill_actors,
    peak_rss_mb,
    require_ray,
    run_on_actors,
)
from drcpo.errors import ConfigError
from drcpo.index import INDEX_DIRNAME, load_index
from drcpo.transforms.base import Transform, transform_from_config
from drcpo.warmup import warmup

__all__ = ["FrameWorker", "augment_kitti_cluster", "transform_sources"]


class FrameWorker:
    """One worker's state (a Ray actor on the cluster): the split, the transform over the
    memory-mapped database and index, the kernels loaded; :meth:`augment` writes one frame."""

    def __init__(
        self,
        root: str,
        split: str,
        config: dict[str, Any],
        database: str | None,
        index: str | None,
        seed: int,
        fov_only: bool,
    ) -> None:
        start = time.perf_counter()
        self.dataset = KittiDataset(root, split)
        # The driver verified the database; workers map it without reading it all again.
        db = None if database is None else GroundTruthDatabase.open(database, verify=False)
        candidates = None if index is None else load_index(db, index)
        self.transform = transform_from_config(config, database=db, index=candidates)
        self.warmup_s = warmup(self.transform)
        self.startup_s = time.perf_counter() - start
        self.seed, self.fov_only = int(seed), bool(fov_only)

    def augment(self, staging: str, number: int) -> int:
        augment_frame(self.dataset, self.transform, staging, number, self.seed, self.fov_only)
        return number

    def info(self) -> dict[str, Any]:
        """pid, start-up and warm-up seconds, peak resident memory (MB) of this worker."""
        return {
            "pid": os.getpid(),
            "startup_s": self.startup_s,
            "warmup_s": self.warmup_s,
            "peak_rss_mb": peak_rss_mb(),
        }


def augment_kitti_cluster(
    root: str | os.PathLike,
    split: str,
    transform: Transform,
    out: str | os.PathLike,
    frames: int | None = None,
    seed: int = 0,
    fov_only: bool = True,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    inputs: Sequence[str | os.PathLike] = (),
    cluster: str | Cluster | None = LOCAL,
    workers: int = 2,
    index_path: str | os.PathLike | None = None,
) -> dict[str, Any]:
    """:func:`~drcpo.datasets.export.augment_kitti` with the frames spread over ``workers``
    actors of ``cluster`` (:func:`~drcpo.distributed.cluster.connect`): the same output bytes,
    the same staging directory (a run stopped on one engine resumes on the other).

    The actors rebuild ``transform`` from :meth:`~drcpo.transforms.base.Transform.to_config`
    (a registered transform) over its database opened from disk (``database.path``) and, when it
    holds a candidate index, the index at ``index_path`` (default ``database.path / "index"``).
    The summary adds ``cluster``: the address, ``startup_s`` (connecting, starting the actors
    and warming them up), ``frames_s`` (from then to the last frame written) and per worker its
    :meth:`FrameWorker.info`. A cluster this call
    started is shut down at its end; a :class:`~drcpo.distributed.cluster.Cluster` passed in
    stays up.
    """
    require_ray()
    database, index = transform_sources(transform, index_path)
    args = (str(Path(root).resolve()), split, transform.to_config(), database, index)
    report: dict[str, Any] = {}
    start = time.perf_counter()

    def map_frames(staging: Path, numbers: list[int]) -> Iterator[int]:
        if not numbers:
            return
        ray = require_ray()
        actor_class = ray.remote(num_cpus=1)(FrameWorker)
        actors = [
            actor_class.remote(*args, seed, fov_only) for _ in range(min(workers, len(numbers)))
        ]
        try:
            ready = ray.get([actor.info.remote() for actor in actors])
            report["startup_s"] = time.perf_counter() - start
            ready_at = time.perf_counter()
            work = run_on_actors(actors, lambda a, n: a.augment.remote(str(staging), n), numbers)
            with closing(work):  # frames being written end before the actors are killed
                for _, number in work:
                    yield number
            report["frames_s"] = time.perf_counter() - ready_at
            final = ray.get([actor.info.remote() for actor in actors])
            report["workers"] = [
                {**first, "peak_rss_mb": last["peak_rss_mb"]}
                for first, last in zip(ready, final, strict=True)
            ]
        finally:
            kill_actors(actors)

    with connected(cluster, workers) as connection:
        summary = augment_kitti(
            root,
            split,
            transform,
            out,
            frames,
            seed,
            fov_only,
            overwrite,
            progress,
            inputs,
            map_frames=map_frames,
        )
    summary["cluster"] = {"address": connection.address, **report}
    return summary


def transform_sources(
    transform: Transform, index_path: str | os.PathLike | None
) -> tuple[Any, Any]:
    """Paths of the database and index the transform draws from (``None`` where it has none)."""
    stages = getattr(transform, "transforms", (transform,))
    found = (t.database for t in stages if getattr(t, "database", None) is not None)
    database = next(found, None)
    if database is None:
        return None, None
    if database.path is None:
        raise ConfigError(
            "the workers open the database from disk: save it first "
            "(GroundTruthDatabase.save) and open it from there"
        )
    needs_index = any(getattr(t, "index", None) is not None for t in stages)
    if not needs_index:
        return str(Path(database.path).resolve()), None
    index = Path(index_path) if index_path is not None else Path(database.path) / INDEX_DIRNAME
    return str(Path(database.path).resolve()), str(index.resolve())
