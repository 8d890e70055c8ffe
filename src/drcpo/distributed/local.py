"""``drcpo augment --workers N`` on this machine: N worker processes, each pinned to one core, each
with the state of a cluster's worker (:class:`~drcpo.distributed.augment.FrameWorker`: the
memory-mapped database and index, the transform rebuilt from its config, the kernels loaded).
Ray is not needed. Each frame uses its own generator and is written atomically into the run's
staging directory, so the output is the same bytes as the one-process run, and a stopped run
resumes on either."""

from __future__ import annotations

import itertools
import multiprocessing
import os
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from drcpo.datasets.export import augment_kitti
from drcpo.distributed.augment import FrameWorker, transform_sources
from drcpo.transforms.base import Transform

__all__ = ["augment_kitti_processes"]

_WORKER: list[FrameWorker] = []  # this worker process's state, set by _start


def _start(args: tuple[Any, ...], cores: Any) -> None:
    core = cores.get()
    if core is not None and hasattr(os, "sched_setaffinity"):
        # one core each: the frames, not threads inside one frame's call, use the machine
        os.sched_setaffinity(0, {core})
    _WORKER.append(FrameWorker(*args))


def _augment(staging: str, number: int) -> int:
    return _WORKER[0].augment(staging, number)


def augment_kitti_processes(
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
    workers: int = 2,
    index_path: str | os.PathLike | None = None,
) -> dict[str, Any]:
    """:func:`~drcpo.datasets.export.augment_kitti` with the frames spread over ``workers``
    local processes: the same output bytes and the same staging directory.

    The processes rebuild ``transform`` from :meth:`~drcpo.transforms.base.Transform.to_config`
    (a registered transform) over its database opened from disk, and its index (default
    ``database.path / "index"``). At most two frames per worker are handed out ahead; when the
    run stops (an error, ``progress`` raising), the frames being written are finished before
    the processes go. A worker's error is raised here as it was raised there.
    """
    database, index = transform_sources(transform, index_path)
    args = (str(Path(root).resolve()), split, transform.to_config(), database, index)
    args += (seed, fov_only)

    def map_frames(staging: Path, numbers: list[int]) -> Iterator[int]:
        if not numbers:
            return
        count = min(int(workers), len(numbers))
        context = multiprocessing.get_context("spawn")  # no state of this process is inherited
        cores = context.Queue()
        available = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
        for k in range(count):
            cores.put(available[k % len(available)] if len(available) >= count else None)
        with context.Pool(count, initializer=_start, initargs=(args, cores)) as pool:
            todo = iter(numbers)
            pending = deque(
                pool.apply_async(_augment, (str(staging), n))
                for n in itertools.islice(todo, 2 * count)
            )
            try:
                while pending:
                    number = pending.popleft().get()
                    for n in itertools.islice(todo, 1):
                        pending.append(pool.apply_async(_augment, (str(staging), n)))
                    yield number
            finally:
                for job in pending:  # no frame is cut off half-way when the pool goes
                    job.wait()

    return augment_kitti(
        root, split, transform, out, frames, seed, fov_only, overwrite, progress, inputs,
        map_frames=map_frames,
    )  # fmt: skip
