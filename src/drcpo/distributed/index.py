"""``drcpo index`` on a cluster: each class's objects are ranked in blocks of query rows
(:func:`~drcpo.index_build.rank_candidates`' blocks) by long-lived actors, which get the class's
arrays once through Ray's shared-memory store; the driver writes the blocks into the table in
block order, so the index is the one a single process builds (the exact first stage included)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from contextlib import closing
from typing import Any

from drcpo.database import GroundTruthDatabase
from drcpo.distributed.cluster import (
    LOCAL,
    Cluster,
    connected,
    in_order,
    kill_actors,
    require_ray,
    run_on_actors,
)
from drcpo.index import CandidateIndex, IndexConfig
from drcpo.index_build import build_index

__all__ = ["BlockRanker", "build_index_cluster"]


class BlockRanker:
    """One worker (a Ray actor): the ranking work of the current class; :meth:`rank` a block."""

    def __init__(self) -> None:
        self.work: Callable[[Any], Any] | None = None

    def load(self, work: Callable[[Any], Any]) -> None:
        self.work = work

    def rank(self, item: Any) -> Any:
        if self.work is None:
            raise RuntimeError("drcpo bug: BlockRanker.rank before load")
        return self.work(item)


class _ClusterBlocks:
    """A ``map_blocks`` for :func:`~drcpo.index_build.build_index`: the same actors for every
    class."""

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self.actors: list[Any] = []

    def __call__(
        self,
        work: Callable[[Any], Any],
        items: Iterable[Any],
        total: int,
        config: IndexConfig,
        progress: Callable[[int, int], None] | None,
    ) -> Iterator[Any]:
        ray = require_ray()
        items = list(items)
        if not self.actors:
            actor_class = ray.remote(num_cpus=1)(BlockRanker)
            self.actors = [actor_class.remote() for _ in range(self.workers)]
        shared = ray.put(work)  # once into the store; each actor maps its arrays from there
        ray.get([actor.load.remote(shared) for actor in self.actors])
        done = 0
        results = run_on_actors(self.actors, lambda a, item: a.rank.remote(item), items)
        with closing(results):  # blocks being ranked end before the actors are reused or killed
            for result in in_order(results):
                done = min(done + config.block_size, total)
                if progress is not None:
                    progress(done, total)
                yield result

    def close(self) -> None:
        if self.actors:
            kill_actors(self.actors)
            self.actors = []


def build_index_cluster(
    database: GroundTruthDatabase,
    config: IndexConfig | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    cluster: str | Cluster | None = LOCAL,
    workers: int = 2,
) -> CandidateIndex:
    """:func:`~drcpo.index_build.build_index` with each class's blocks ranked by ``workers``
    actors of ``cluster`` (:func:`~drcpo.distributed.cluster.connect`); the same index. A cluster
    this call started is shut down at its end."""
    with connected(cluster, workers):
        blocks = _ClusterBlocks(workers)
        try:
            return build_index(database, config, progress, map_blocks=blocks)
        finally:
            blocks.close()
