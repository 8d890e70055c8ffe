"""What :class:`~drcpo.transforms.drcpo.DRCPO` hands from one of its steps to the next: the
placed boxes (with what e-HPR needs of them) and the objects on their way into the frame."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["Insertion", "Placed"]


@dataclass(frozen=True, eq=False)
class Placed:
    """What e-HPR needs of the placed boxes alone (worked out while the objects are built):
    the boxes ``(A, 7)``; per frame point, the last box holding it (``int64 (N,)``, -1:
    none); each box's source row; their view windows."""

    boxes: np.ndarray
    owners: np.ndarray
    rows: np.ndarray  # each box's source row
    windows: tuple[np.ndarray, ...]  # box_windows of the boxes grown by WINDOW_SLACK

    def windows_of(self, insertions: Sequence[Insertion]) -> tuple[np.ndarray, ...]:
        """The view windows of the boxes of ``insertions``, some of the placed objects in their
        order (a box's window does not depend on the others)."""
        index, k = [], 0
        for insertion in insertions:
            while int(self.rows[k]) != insertion.row:
                k += 1
            index.append(k)
            k += 1
        return tuple(values[np.array(index, dtype=np.int64)] for values in self.windows)


@dataclass(frozen=True, eq=False)
class Insertion:
    """One object on its way into the frame: source row, class, placed box, its label (the
    placed box grown to hold the points, see DRCPO's s-HPR step), placed points."""

    row: int
    name: str
    placed: np.ndarray
    box: np.ndarray
    points: np.ndarray
