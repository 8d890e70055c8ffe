"""s-HPR, the paper's self-occlusion of each placed object (:func:`self_occlusion`,
:func:`self_occlusion_many`); e-HPR is in :mod:`drcpo.occlusion.external`. Imports the other
:mod:`drcpo.occlusion` modules.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from drcpo.errors import DataError
from drcpo.occlusion.checks import (
    _check_radius,
    _check_workers,
)
from drcpo.occlusion.hpr import hidden_point_removal
from drcpo.occlusion.threads import _shared_chunks

__all__ = ["self_occlusion", "self_occlusion_many"]


def self_occlusion(
    points: np.ndarray,
    box: np.ndarray,
    radius_factor: float = 200.0,
    *,
    viewpoint: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    method: str = "auto",
    workers: int | None = 1,
) -> np.ndarray:
    """s-HPR: the paper's self-occlusion of one placed object, seen from the sensor.

    Args:
        points: ``(N, 3 + C)`` the object's points in the LiDAR frame (metres).
        box: ``(7,)`` (or ``(1, 7)``) the object's box; ``R = diagonal * radius_factor``.
        radius_factor: the paper uses 200.
        viewpoint: ``(3,)`` the sensor position, metres (the origin in the paper).
        method, workers: as in :func:`hidden_point_removal` (one thread by default: objects
            are small).

    Returns:
        ``bool (N,)``: points kept (visible).
    """
    box = np.asarray(box, dtype=np.float64)
    if box.size != 7:
        raise DataError(f"self_occlusion: box must have 7 values, got shape {box.shape}")
    # geometry.box_diagonal's sum, in the same order, without its array overhead (per object)
    dx, dy, dz = box.reshape(7)[3:6].tolist()
    diagonal = math.sqrt(dx * dx + dy * dy + dz * dz)
    factor = _check_radius(radius_factor, "radius_factor")
    if not diagonal > 0.0:
        raise DataError(f"self_occlusion: the box has no extent (diagonal {diagonal})")
    return hidden_point_removal(
        points, viewpoint, diagonal * factor, method=method, workers=workers
    )


def self_occlusion_many(
    objects: Sequence[tuple[np.ndarray, np.ndarray]],
    radius_factor: float = 200.0,
    *,
    viewpoint: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    method: str = "auto",
    workers: int | None = None,
    pool: ThreadPoolExecutor | None = None,
) -> list[np.ndarray]:
    """:func:`self_occlusion` of several objects, spread over ``workers`` threads.

    The hulls (:mod:`drcpo.occlusion.hull`'s numba kernel, or Qhull) release the GIL while they are
    built, so two objects' hulls can run at once. Each object's answer is exactly
    :func:`self_occlusion`'s, whichever thread computes it; the calling thread does part of the
    work.

    Args:
        objects: ``(points (N_i, 3 + C), box (7,))`` pairs, as :func:`self_occlusion` takes.
        radius_factor, viewpoint, method: as in :func:`self_occlusion`.
        workers: threads (``None``: up to two of the CPUs this process may use).
        pool: a running pool whose thread takes part when it is free (else, with
            ``workers > 1``, one is started for the call and shut down after it).

    Returns:
        ``bool (N_i,)`` visible masks, in the order of ``objects``.
    """
    workers = _check_workers(workers)
    # Largest first, so that the threads finish together; the order does not change answers.
    order = sorted(range(len(objects)), key=lambda k: -len(objects[k][0]))
    masks = _shared_chunks(
        lambda k: self_occlusion(
            *objects[k], radius_factor, viewpoint=viewpoint, method=method, workers=1
        ),
        order,
        pool if workers > 1 else None,
        start=workers > 1,
    )
    results: list[np.ndarray | None] = [None] * len(objects)
    for k, mask in zip(order, masks, strict=True):
        results[k] = mask
    return results  # type: ignore[return-value]
