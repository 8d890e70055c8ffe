"""What :class:`~drcpo.transforms.drcpo.DRCPO` hands from one of its steps to the next: the
objects on their way into the frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Insertion"]


@dataclass(frozen=True, eq=False)
class Insertion:
    """One object on its way into the frame: source row, class, placed box, its label (the
    placed box grown to hold the points, see DRCPO's s-HPR step), placed points."""

    row: int
    name: str
    placed: np.ndarray
    box: np.ndarray
    points: np.ndarray
