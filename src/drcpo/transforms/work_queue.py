"""A two-thread work queue: DR.CPO's s-HPR jobs done by the calling thread and, when the process
may use a second core, one pool thread."""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

__all__ = ["WorkQueue", "result_if_done", "spare_core"]


def result_if_done(future: Future | None) -> Any:
    """A future's result if it has one already, else ``None``."""
    return future.result() if future is not None and future.done() else None


def spare_core() -> bool:
    """Whether this process may use a second CPU (a forked data-loader worker pinned to one
    core may not)."""
    try:
        return len(os.sched_getaffinity(0)) > 1
    except AttributeError:  # not on Linux
        return (os.cpu_count() or 1) > 1


class WorkQueue:
    """Jobs done, in any order, by one thread of ``pool`` whenever it is free (after
    :meth:`start`) and by the calling thread in :meth:`results`. A job's answer must not
    depend on which thread does it."""

    def __init__(self, pool: ThreadPoolExecutor | None) -> None:
        self._pool = pool
        self._jobs: deque[tuple[int, Callable[[], Any]]] = deque()
        self._results: dict[int, Any] = {}
        self._helper: Future | None = None

    def add(self, key: int, job: Callable[[], Any]) -> None:
        self._jobs.append((key, job))

    def start(self) -> None:
        """Let the pool's thread take jobs, unless it is on it already."""
        if self._pool is None or (self._helper is not None and not self._helper.done()):
            return
        if self._helper is not None:
            self._helper.result()  # (raises what a job raised there)
        self._helper = self._pool.submit(self._drain)

    def _drain(self) -> None:
        while True:
            try:
                key, job = self._jobs.popleft()  # atomic: the threads never share a job
            except IndexError:
                return
            self._results[key] = job()

    def results(self) -> dict[int, Any]:
        """Every job's answer by key, once all are done (a pool thread that has not started
        is not waited for)."""
        try:
            self._drain()
        except BaseException:
            self._jobs.clear()  # the pool's thread stops after its current job
            raise
        if self._helper is not None and not self._helper.cancel():
            self._helper.result()
        return self._results
