"""``drcpo build-db`` on a cluster: actors each hold the data set (sent once) and cut the objects
out of chunks of frames; the driver takes the chunks in frame order, so the database is the one
a single process builds (the same checksum)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import closing
from typing import Any

from drcpo.database import GroundTruthDatabase, ObjectRecord
from drcpo.database.build import (
    DEFAULT_CLASSES,
    build_database,
    build_database_from,
    frame_records,
)
from drcpo.distributed.cluster import (
    LOCAL,
    Cluster,
    connected,
    in_order,
    kill_actors,
    require_ray,
    run_on_actors,
)

__all__ = ["FrameReader", "build_database_cluster", "build_dataset_cluster"]

#: Chunks per worker: small enough to balance the load, large enough to keep calls few.
CHUNKS_PER_WORKER = 8


class FrameReader:
    """One worker (a Ray actor): the data set and the classes; :meth:`records` of frames."""

    def __init__(self, dataset: Any, classes: tuple[str, ...] | None) -> None:
        self.dataset = dataset
        self.classes = classes

    def records(self, frame_ids: list[str]) -> list[list[ObjectRecord]]:
        """:func:`~drcpo.database.build.frame_records` of each frame, in the order given."""
        return [frame_records(self.dataset.frame(i), self.classes) for i in frame_ids]


def cluster_frames(connection: Cluster, workers: int) -> Callable[..., Iterator]:
    """A ``map_frames`` for :func:`~drcpo.database.build.build_database` on ``workers`` actors."""

    def map_frames(
        dataset: Any,
        classes: tuple[str, ...] | None,
        _: int,
        progress: Callable[[int, int], None] | None,
    ) -> Iterator[list[ObjectRecord]]:
        ids = list(dataset.frame_ids)
        if not ids:
            return
        ray = require_ray()
        count = min(workers, len(ids))
        size = max(1, len(ids) // (count * CHUNKS_PER_WORKER))
        chunks = [ids[i : i + size] for i in range(0, len(ids), size)]
        actor_class = ray.remote(num_cpus=1)(FrameReader)
        actors = [actor_class.remote(dataset, classes) for _ in range(count)]
        try:
            done = 0
            results = run_on_actors(actors, lambda a, chunk: a.records.remote(chunk), chunks)
            with closing(results):
                for chunk in in_order(results):
                    for frame_objects in chunk:
                        done += 1
                        if progress is not None:
                            progress(done, len(ids))
                        yield frame_objects
        finally:
            kill_actors(actors)

    return map_frames


def build_database_cluster(
    root: str | os.PathLike,
    split: str,
    out: str | os.PathLike,
    classes: Sequence[str] | str = DEFAULT_CLASSES,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    cluster: str | Cluster | None = LOCAL,
    workers: int = 2,
) -> GroundTruthDatabase:
    """:func:`~drcpo.database.build.build_database` with the frames read by ``workers`` actors
    of ``cluster`` (:func:`~drcpo.distributed.cluster.connect`); the same database. A cluster
    this call started is shut down at its end."""
    with connected(cluster, workers) as connection:
        return build_database(
            root,
            split,
            out,
            classes,
            workers=workers,
            overwrite=overwrite,
            progress=progress,
            map_frames=cluster_frames(connection, workers),
        )


def build_dataset_cluster(
    dataset: Any,
    out: str | os.PathLike,
    classes: Sequence[str] | str = DEFAULT_CLASSES,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    cluster: str | Cluster | None = LOCAL,
    workers: int = 2,
    parameters: dict[str, Any] | None = None,
) -> GroundTruthDatabase:
    """:func:`~drcpo.database.build.build_database_from` (any data set of frames, e.g. a
    nuScenes-style one) with the frames read by ``workers`` actors of ``cluster``; the same
    database. The data set object goes to each actor, so it must pickle (the readers do)."""
    with connected(cluster, workers) as connection:
        return build_database_from(
            dataset,
            out,
            classes,
            workers=workers,
            overwrite=overwrite,
            progress=progress,
            parameters=parameters,
            map_frames=cluster_frames(connection, workers),
        )
