"""KITTI label and result files as the evaluator reads them.

A result (prediction) file is a label file with a 16th column, the score; one file per frame,
named as the frame's label file. Unlike :func:`drcpo.datasets.kitti.read_labels` (which feeds
training), the evaluator keeps ``DontCare`` rows (their image regions excuse detections) and
reads every value in float64, as the KITTI devkit does, so difficulty cut-offs fall exactly as
in its evaluation.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drcpo.datasets.kitti import DONT_CARE, _parse_floats, _read_lines
from drcpo.errors import DataError

__all__ = ["KittiObjects", "read_frames", "read_kitti_objects"]

_FIELDS = 15  # type, truncated, occluded, alpha, bbox (4), h w l, x y z, ry


@dataclass(frozen=True, eq=False)
class KittiObjects:
    """The rows of one label or result file, ``DontCare`` included, in file order.

    Attributes (M rows):
        names: ``(M,)`` class names as written (``Car``, ``DontCare``, ...).
        truncated: ``float64 (M,)`` 0..1 (-1 in result files).
        occluded: ``float64 (M,)`` 0..3 (-1 in result files).
        alpha: ``float64 (M,)`` observation angle, radians (-10 when unknown).
        bbox: ``float64 (M, 4)`` image box left, top, right, bottom, pixels.
        boxes: ``float64 (M, 7)`` camera boxes x, y, z (bottom centre), l, h, w, ry (metres,
            radians), see :mod:`drcpo.evaluation.overlaps`.
        score: ``float64 (M,)`` detection scores (0 in label files).
    """

    names: np.ndarray
    truncated: np.ndarray
    occluded: np.ndarray
    alpha: np.ndarray
    bbox: np.ndarray
    boxes: np.ndarray
    score: np.ndarray

    def __len__(self) -> int:
        return len(self.names)


def read_kitti_objects(path: str | os.PathLike, results: bool = False) -> KittiObjects:
    """Read a KITTI label file, or a result file (``results=True``: a score column required).

    Raises :class:`DataError` naming the file and line for a missing file, a wrong number of
    fields, a non-numeric or non-finite value, or a non-positive size outside ``DontCare``.
    """
    path = Path(path)
    what = "result" if results else "label"
    allowed = (_FIELDS + 1,) if results else (_FIELDS, _FIELDS + 1)
    numbered = [(n, line.split()) for n, line in enumerate(_read_lines(path, what), start=1)]
    numbered = [(n, fields) for n, fields in numbered if fields]
    for number, fields in numbered:
        if len(fields) not in allowed:
            expected = " or ".join(str(n) for n in allowed)
            raise DataError(
                f"{path}:{number}: expected {expected} fields (type, truncated, occluded, alpha, "
                f"bbox x4, h w l, x y z, ry{', score' if results else '[, score]'}), "
                f"got {len(fields)}: {' '.join(fields)!r}"
            )
    names = [fields[0] for _, fields in numbered]
    padded = [fields[1:] if len(fields) > _FIELDS else [*fields[1:], "0"] for _, fields in numbered]
    try:  # one conversion for the whole file; per line only to name a bad one
        table = np.array(padded, dtype=np.float64).reshape(-1, _FIELDS)
    except ValueError:
        for number, fields in numbered:
            _parse_floats(fields[1:], path, number)
        raise DataError(f"{path}: not a number in the file") from None
    bad = ~np.isfinite(table).all(axis=1)
    sized = (table[:, 7:10] <= 0).any(axis=1) & (np.array(names, dtype=str) != DONT_CARE)
    for row in np.flatnonzero(bad | sized)[:1]:
        number, fields = numbered[row]
        if bad[row]:
            raise DataError(f"{path}:{number}: NaN or infinite value in {' '.join(fields)!r}")
        raise DataError(
            f"{path}:{number}: {names[row]} has a non-positive size h, w, l = {table[row, 7:10]}"
        )
    return _objects(names, table)


def _objects(names: list[str], table: np.ndarray) -> KittiObjects:
    h, w, length = table[:, 7], table[:, 8], table[:, 9]
    return KittiObjects(
        names=np.array(names, dtype=str),
        truncated=table[:, 0],
        occluded=table[:, 1],
        alpha=table[:, 2],
        bbox=table[:, 3:7],
        boxes=np.column_stack([table[:, 10:13], length, h, w, table[:, 13]]),
        score=table[:, 14],
    )


def read_frames(
    directory: str | os.PathLike,
    frame_ids: Sequence[str],
    results: bool = False,
    missing_as_empty: bool = False,
) -> list[KittiObjects]:
    """Read ``directory/<id>.txt`` for every frame id, in order.

    Missing files raise :class:`DataError` (naming the first and counting them), as the KITTI
    devkit requires a file per frame; with ``missing_as_empty`` they count as frames with no
    objects (for results: a detector that found nothing and wrote no file).
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise DataError(f"{directory}: {'result' if results else 'label'} directory missing")
    paths = [directory / f"{frame_id}.txt" for frame_id in frame_ids]
    absent = [path for path in paths if not path.is_file()]
    if absent and not missing_as_empty:
        raise DataError(
            f"{absent[0]}: {'result' if results else 'label'} file missing "
            f"({len(absent)} of {len(paths)} frames have none"
            f"{'; --missing-empty counts them as frames without detections' if results else ''})"
        )
    empty = _objects([], np.zeros((0, _FIELDS)))
    missing = set(absent)
    return [empty if path in missing else read_kitti_objects(path, results) for path in paths]
