"""Work spread over threads for the occlusion modules, safe in forked workers.

No pool outlives a call (or the caller owns it), so nothing leaks into a fork. Imports nothing
from drcpo.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

__all__: list[str] = []  # internal to drcpo.occlusion, whose __init__ has the API


def _in_threads(kernel, items: np.ndarray, parts: int) -> list[np.ndarray]:
    """``kernel`` over ``parts`` contiguous chunks of ``items``, on that many threads (the
    kernels release the GIL); the pool lives only for this call, so nothing leaks into a fork."""
    chunks = np.array_split(items, max(1, parts))
    if len(chunks) == 1:
        return [kernel(chunks[0])]
    # The calling thread takes the first chunk: one thread fewer to start (starting one is
    # slow when the other core is busy).
    with ThreadPoolExecutor(max_workers=len(chunks) - 1) as pool:
        others = [pool.submit(kernel, chunk) for chunk in chunks[1:]]
        return [kernel(chunks[0])] + [future.result() for future in others]


def _shared_chunks(
    kernel, parts: Sequence[Any], helper: ThreadPoolExecutor | None, *, start: bool = False
) -> list[Any]:
    """``kernel`` over each of ``parts``, results in order; with ``helper`` (a running pool)
    one of its threads and the calling thread claim parts until none is left, so the work
    splits evenly whatever each part costs and however busy the other core is. A helper still
    busy with earlier work when the calling thread runs out is not waited for. ``start``:
    without ``helper``, start a one-thread pool for the call."""
    results: list[Any] = [None] * len(parts)
    claim = iter(range(len(parts)))  # next() on a range iterator is atomic under the GIL

    def drain() -> None:
        for k in claim:
            results[k] = kernel(parts[k])

    if len(parts) < 2 or (helper is None and not start):
        drain()
        return results
    own = helper is None
    pool = ThreadPoolExecutor(max_workers=1) if own else helper
    try:
        other = pool.submit(drain)
        drain()
        if not other.cancel():  # started: it holds at most the parts it claimed
            other.result()
    finally:
        if own:
            pool.shutdown()
    return results


def _halves(kernel, count: int, helper, minimum: int) -> list[Any]:
    """``kernel(start, stop)`` over the rows ``0..count - 1``: in two contiguous halves, one
    claimed by ``helper``'s thread when it is free (:func:`_shared_chunks`), given a helper
    and at least ``minimum`` rows; else in one call. Results in row order."""
    parts = 1 if helper is None or count < minimum else 2
    bounds = np.linspace(0, count, parts + 1).astype(np.int64)
    return _shared_chunks(lambda k: kernel(bounds[k], bounds[k + 1]), range(parts), helper)
