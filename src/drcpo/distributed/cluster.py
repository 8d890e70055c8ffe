"""Connecting to a Ray cluster: a local one started for the run (``"local"``), or a running
cluster's address. Ray is optional (``pip install drcpo[ray]``); without it every entry point
raises a :class:`~drcpo.errors.ConfigError` saying so. Nothing is downloaded, the dashboard is
off and so are Ray's usage statistics."""

from __future__ import annotations

import logging
import os
import resource
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any

from drcpo.errors import ConfigError, DrcpoError

__all__ = [
    "LOCAL",
    "RAY_MISSING",
    "Cluster",
    "WorkerLost",
    "connect",
    "connected",
    "in_order",
    "kill_actors",
    "peak_rss_mb",
    "require_ray",
    "run_on_actors",
]

LOCAL = "local"
RAY_MISSING = "the cluster needs Ray, which is not installed: pip install drcpo[ray]"
#: Object store of a local cluster, MB: the workers read the database and index memory-mapped
#: from disk, so the store holds only small results.
LOCAL_OBJECT_STORE_MB = 200
#: Longest wait, seconds, for the items workers have started when the work stops early.
SETTLE_TIMEOUT_S = 60.0


class WorkerLost(DrcpoError):
    """A cluster worker died (killed, out of memory, its node lost) before finishing its work."""


def require_ray() -> ModuleType:
    """The ``ray`` module; :class:`ConfigError` naming the install when it is missing."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # read by ray at start-up
    try:
        import ray
    except ImportError as exc:
        raise ConfigError(RAY_MISSING) from exc
    return ray


@dataclass
class Cluster:
    """A connection to a Ray cluster; :meth:`close` shuts down what :func:`connect` started.

    ``workers``: the actors a job starts on it; ``startup_s``: seconds the connection took.
    """

    address: str
    workers: int
    startup_s: float = 0.0
    owned: bool = field(default=False, repr=False)

    def close(self) -> None:
        if self.owned:
            require_ray().shutdown()
            self.owned = False

    def __enter__(self) -> Cluster:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


def connect(
    cluster: str | Cluster | None = LOCAL,
    workers: int = 2,
    object_store_mb: int = LOCAL_OBJECT_STORE_MB,
) -> Cluster:
    """Connect to Ray: ``"local"`` (or ``None``) starts a local cluster of ``workers`` CPUs,
    anything else is a running cluster's address (``"ray://host:10001"``, ``"host:6379"``,
    ``"auto"``). A :class:`Cluster` is returned as it is; when this process is connected
    already, that connection is used (and left open by :meth:`Cluster.close`).

    With an address, every node must see the job's paths (data, database, output) at the same
    places (a shared file system) and have drcpo installed.
    """
    if workers < 1:
        raise ConfigError(f"workers must be >= 1, got {workers}")
    if isinstance(cluster, Cluster):
        return cluster
    ray = require_ray()
    address = LOCAL if cluster in (None, "", LOCAL) else str(cluster)
    if ray.is_initialized():
        return Cluster(address, workers)
    start = time.perf_counter()
    quiet: dict[str, Any] = {
        "include_dashboard": False,
        "logging_level": logging.ERROR,
        "log_to_driver": False,
    }
    try:
        if address == LOCAL:
            ray.init(num_cpus=workers, object_store_memory=object_store_mb << 20, **quiet)
        else:
            ray.init(address=address, **quiet)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise ConfigError(f"cannot connect to the Ray cluster {address!r}: {exc}") from exc
    return Cluster(address, workers, time.perf_counter() - start, owned=True)


@contextmanager
def connected(cluster: str | Cluster | None = LOCAL, workers: int = 2) -> Iterator[Cluster]:
    """:func:`connect` for a ``with`` block: a cluster started here is shut down at its end, one
    given (a :class:`Cluster`) is left as it was."""
    connection = connect(cluster, workers)
    try:
        yield connection
    finally:
        if connection is not cluster:
            connection.close()


def peak_rss_mb() -> float:
    """This process's peak resident memory, MB."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1 << 20) if sys.platform == "darwin" else peak / 1024.0  # bytes vs KiB


def run_on_actors(
    actors: list[Any],
    call: Callable[[Any, Any], Any],
    items: Iterable[Any],
    ahead: int = 2,
) -> Iterator[tuple[int, Any]]:
    """``call(actor, item)`` (an actor method's ``.remote``) for each item, handed out in order
    to whichever actor is free, ``ahead`` queued per actor so none waits between items; yields
    ``(position of the item, result)`` as results arrive (completion order; :func:`in_order`
    restores item order). An error raised by the work is raised here as itself (not Ray's
    wrapper); a lost actor raises :class:`WorkerLost`.

    When the generator ends early (an error, or the caller closes it: use
    :func:`contextlib.closing` so that happens before :func:`kill_actors`), it waits for the
    items already handed out (at most ``ahead`` per actor) to end: a killed worker may outlive
    :func:`kill_actors` for a moment, and one still writing a frame would race the rerun that
    resumes it."""
    ray = require_ray()
    from ray.exceptions import RayActorError, RayTaskError

    queue = list(enumerate(items))[::-1]
    pending: dict[Any, tuple[Any, int]] = {}

    def submit(actor: Any) -> None:
        position, item = queue.pop()
        pending[call(actor, item)] = (actor, position)

    for actor in actors:
        for _ in range(ahead):
            if queue:
                submit(actor)
    try:
        while pending:
            (ready,), _ = ray.wait(list(pending), num_returns=1)
            actor, position = pending.pop(ready)
            try:
                result = ray.get(ready)
            except RayTaskError as exc:
                cause = getattr(exc, "cause", None)
                if isinstance(cause, Exception):
                    raise cause from None
                raise
            except RayActorError as exc:
                raise WorkerLost(
                    f"a cluster worker died ({type(exc).__name__}); rerun the same command to "
                    "continue from what was written"
                ) from exc
            if queue:
                submit(actor)
            yield position, result
    finally:
        _settle(list(pending))


def _settle(refs: list[Any]) -> None:
    """Wait (up to :data:`SETTLE_TIMEOUT_S`) for the tasks of ``refs`` to end, failed or not.

    Not ``ray.cancel``: Ray 2.60 still runs a cancelled task already queued on its actor (it
    only reports it cancelled), so waiting is what tells when the workers are idle."""
    if refs:
        require_ray().wait(refs, num_returns=len(refs), timeout=SETTLE_TIMEOUT_S)


def in_order(results: Iterable[tuple[int, Any]]) -> Iterator[Any]:
    """The results of :func:`run_on_actors` in item order (later ones held until their turn)."""
    held: dict[int, Any] = {}
    nxt = 0
    for position, result in results:
        held[position] = result
        while nxt in held:
            yield held.pop(nxt)
            nxt += 1


def kill_actors(actors: list[Any]) -> None:
    """Stop ``actors`` at once (their queued work is dropped)."""
    ray = require_ray()
    for actor in actors:
        ray.kill(actor, no_restart=True)
