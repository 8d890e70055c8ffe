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
from pathlib import Path
from typing import Any

from drcpo.datasets.export import augment_kitti
from drcpo.distributed.augment import FrameWorker, transform_sources
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
        # Raised here, the pool would start a new worker in its place for ever and the run
        # would never end: the driver raises it instead, before any frame is handed out.
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
    the processes go. A worker's error is raised here as it was raised there; one raised while
    a worker starts, before any frame is handed out. The summary adds ``processes``:
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
        cores, ready = context.Queue(), context.SimpleQueue()
        available = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
        for k in range(count):
            cores.put(available[k % len(available)] if len(available) >= count else None)
        with context.Pool(count, initializer=_start, initargs=(args, cores, ready)) as pool:
            started = [ready.get() for _ in range(count)]
            for info in started:
                if isinstance(info, Exception):
                    raise info
            report["startup_s"] = time.perf_counter() - start
            report["workers"] = started
            # Frames come back as they are written, not in order: a slow frame at the head
            # would otherwise leave the other workers idle once the frames ahead are done.
            finished: queue.SimpleQueue[int] = queue.SimpleQueue()
            jobs: dict[int, Any] = {}

            def submit(n: int) -> None:
                jobs[n] = pool.apply_async(
                    _augment, (str(staging), n),
                    callback=lambda _, n=n: finished.put(n),
                    error_callback=lambda _, n=n: finished.put(n),
                )  # fmt: skip

            todo = iter(numbers)
            for n in itertools.islice(todo, 2 * count):
                submit(n)
            try:
                while jobs:
                    number = jobs.pop(finished.get()).get()  # a worker's error raised here
                    for n in itertools.islice(todo, 1):
                        submit(n)
                    yield number
            finally:
                for job in jobs.values():  # no frame is cut off half-way when the pool goes
                    job.wait()

    summary = augment_kitti(
        root, split, transform, out, frames, seed, fov_only, overwrite, progress, inputs,
        map_frames=map_frames,
    )  # fmt: skip
    summary["processes"] = report
    return summary
