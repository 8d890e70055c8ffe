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
import queue
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from drcpo.datasets.export import augment_kitti
from drcpo.distributed.augment import FrameWorker, transform_sources
from drcpo.errors import DrcpoError
from drcpo.transforms.base import Transform

__all__ = ["augment_kitti_processes"]

_WORKER: list[FrameWorker] = []  # this worker process's state, set by _start


def _start(args: tuple[Any, ...], cores: Any, ready: Any) -> None:
    core = cores.get()
    if core is not None and hasattr(os, "sched_setaffinity"):
        # one core each: the frames, not threads inside one frame's call, use the machine
        os.sched_setaffinity(0, {core})
    try:
        _WORKER.append(FrameWorker(*args))
    except Exception as exc:
        # Raised here, it would only say that the pool broke: the driver raises it as it was.
        exc.add_note(f"in worker process {os.getpid()}:\n{traceback.format_exc()}")
        try:
            ready.put(exc)
        except Exception:  # an error that does not pickle comes back as its text
            ready.put(RuntimeError(f"{type(exc).__name__}: {exc}"))
        return
    ready.put(_WORKER[0].info())


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
    the processes go. A worker's error is raised here as it was raised there, one raised while
    a worker starts before any frame is written; a worker that dies (killed, out of memory)
    stops the run with a :class:`~drcpo.errors.DrcpoError` saying so (the frames written are
    kept: a new run resumes from them). The summary adds ``processes``:
    ``startup_s`` (spawning the processes up to all of them warmed) and per worker its
    :meth:`~drcpo.distributed.augment.FrameWorker.info` at start-up.
    """
    database, index = transform_sources(transform, index_path)
    args = (str(Path(root).resolve()), split, transform.to_config(), database, index)
    args += (seed, fov_only)

    report: dict[str, Any] = {}

    def map_frames(staging: Path, numbers: list[int]) -> Iterator[int]:
        if not numbers:
            return
        start = time.perf_counter()
        count = min(int(workers), len(numbers))
        context = multiprocessing.get_context("spawn")  # no state of this process is inherited
        cores, ready = context.Queue(), context.Queue()
        available = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
        for k in range(count):
            cores.put(available[k % len(available)] if len(available) >= count else None)
        pool = ProcessPoolExecutor(count, context, _start, (args, cores, ready))
        jobs: dict[Future, int] = {}
        todo = iter(numbers)

        def submit(k: int) -> None:
            for n in itertools.islice(todo, k):
                jobs[pool.submit(_augment, str(staging), n)] = n

        try:
            submit(2 * count)  # (the pool starts its processes as work arrives)
            report["workers"] = _started(ready, count, jobs)
            report["startup_s"] = time.perf_counter() - start
            while jobs:
                # frames come back as they are written, not in order: a slow frame at the
                # head would otherwise leave the other workers idle
                for job in wait(jobs, return_when=FIRST_COMPLETED).done:
                    number = jobs.pop(job)
                    _result(job, number)  # a worker's error raised here
                    submit(1)
                    yield number
        finally:
            # no frame is cut off half-way: those being written finish, the others never start
            pool.shutdown(wait=True, cancel_futures=True)

    summary = augment_kitti(
        root, split, transform, out, frames, seed, fov_only, overwrite, progress, inputs,
        map_frames=map_frames,
    )  # fmt: skip
    summary["processes"] = report
    return summary


def _started(ready: Any, count: int, jobs: dict[Future, int]) -> list[dict[str, Any]]:
    """Each worker's :meth:`~drcpo.distributed.augment.FrameWorker.info` once warmed; its
    start-up error raised as it was raised there, or the pool's if a worker died."""
    started: list[Any] = []
    while len(started) < count:
        try:
            started.append(ready.get(timeout=0.5))
        except queue.Empty:
            for job, number in jobs.items():
                if job.done():
                    _result(job, number)
            if all(job.done() for job in jobs):
                break  # (fewer processes started than asked for: the work was done first)
            continue
        if isinstance(started[-1], Exception):
            raise started[-1]
    return started


def _result(job: Future, number: int) -> int:
    try:
        return job.result()
    except BrokenProcessPool as exc:
        raise DrcpoError(
            f"a worker process died while augmenting frame number {number} (killed, or out of "
            "memory?); the frames written so far are kept and a new run resumes from them"
        ) from exc
