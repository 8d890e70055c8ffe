"""CenterPoint-style targets and decoding on the BEV grid (numpy, no torch).

Each object is a peak of its class's heatmap at its centre's output cell (the BEV grid
subsampled by ``STRIDE``), spread by a Gaussian whose radius follows the object's footprint as
in CenterNet; the cell also holds its box code: the centre's offset in the cell (2), z (1),
log length, width, height (3) and sine, cosine of the heading (2).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter

from drcpo.datasets.kitti_coordinates import DEFAULT_IMAGE_SHAPE, Calibration
from drcpo.datasets.kitti_writer import label_lines, project_boxes
from drcpo.frame import Frame
from drcpo.geometry import wrap_angle

from .bev import Grid

CLASSES: tuple[str, ...] = ("Car", "Pedestrian", "Cyclist")
STRIDE = 2  # output cells are STRIDE x STRIDE BEV cells (0.8 m on the default grid)
CODE_SIZE = 8
MIN_OVERLAP = 0.1  # of CenterNet's Gaussian radius: boxes shifted by the radius keep this IoU


def output_shape(grid: Grid) -> tuple[int, int]:
    ny, nx = grid.shape
    return ny // STRIDE, nx // STRIDE


def gaussian_radius(length: np.ndarray, width: np.ndarray, overlap: float = MIN_OVERLAP):
    """CenterNet's radius (in the units of ``length``, ``width``): the largest corner shift
    keeping IoU ``overlap`` with the box, the smallest of its three cases."""
    size, area = length + width, length * width
    r1 = (size + np.sqrt(size**2 - 4 * area * (1 - overlap) / (1 + overlap))) / 2
    r2 = (2 * size + np.sqrt((2 * size) ** 2 - 16 * (1 - overlap) * area)) / 8
    a3, b3 = 4 * overlap, -2 * overlap * size
    r3 = (-b3 + np.sqrt(b3**2 - 4 * a3 * (overlap - 1) * area)) / (2 * a3)
    return np.minimum(np.minimum(r1, r2), r3)


def class_ids(names: Sequence[str]) -> np.ndarray:
    """``int64 (M,)`` index of each name in :data:`CLASSES`, -1 for other classes."""
    lookup = {name: i for i, name in enumerate(CLASSES)}
    return np.array([lookup.get(str(n), -1) for n in names], dtype=np.int64)


def encode_targets(
    boxes: np.ndarray, names: Sequence[str], grid: Grid | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Training targets of LiDAR boxes ``(M, 7)`` (OpenPCDet convention) and their class names.

    Objects of other classes or with centres outside the grid get no target.

    Returns:
        heatmap: ``float32 (len(CLASSES), H, W)``, 1 at each object's centre cell.
        code: ``float32 (CODE_SIZE, H, W)`` box codes at the centre cells, 0 elsewhere.
        mask: ``float32 (H, W)``, 1 at the centre cells.
    """
    grid = grid or Grid()
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    labels = class_ids(names)
    height, width = output_shape(grid)
    size = grid.cell * STRIDE
    col_f = (boxes[:, 0] - grid.x_range[0]) / size
    row_f = (boxes[:, 1] - grid.y_range[0]) / size
    col, row = np.floor(col_f).astype(np.int64), np.floor(row_f).astype(np.int64)
    keep = (labels >= 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    boxes, labels, col, row = boxes[keep], labels[keep], col[keep], row[keep]
    col_f, row_f = col_f[keep], row_f[keep]
    heatmap = np.zeros((len(CLASSES), height, width), dtype=np.float32)
    radius = np.maximum(np.floor(gaussian_radius(boxes[:, 3] / size, boxes[:, 4] / size)), 1)
    sigma = (2 * radius + 1) / 6
    rows, cols = np.arange(height)[None, :, None], np.arange(width)[None, None, :]
    d_row, d_col = rows - row[:, None, None], cols - col[:, None, None]
    window = np.maximum(np.abs(d_row), np.abs(d_col)) <= radius[:, None, None]
    peaks = np.exp(-(d_row**2 + d_col**2) / (2 * sigma[:, None, None] ** 2)) * window
    for k in range(len(CLASSES)):
        if (labels == k).any():
            heatmap[k] = peaks[labels == k].max(axis=0)
    code = np.zeros((CODE_SIZE, height, width), dtype=np.float32)
    code[:, row, col] = np.stack(
        [
            col_f - col,
            row_f - row,
            boxes[:, 2],
            *np.log(boxes[:, 3:6]).T,
            np.sin(boxes[:, 6]),
            np.cos(boxes[:, 6]),
        ]
    )
    mask = np.zeros((height, width), dtype=np.float32)
    mask[row, col] = 1.0
    return heatmap, code, mask


def decode(
    heatmap: np.ndarray,
    code: np.ndarray,
    grid: Grid | None = None,
    max_objects: int = 80,
    threshold: float = 0.05,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes from a predicted heatmap (probabilities, ``(len(CLASSES), H, W)``) and box codes
    ``(CODE_SIZE, H, W)``: the local maxima (3 x 3) above ``threshold``, best ``max_objects``.

    Returns LiDAR boxes ``float64 (D, 7)``, class indices ``int64 (D,)`` and scores
    ``float64 (D,)``, by decreasing score.
    """
    grid = grid or Grid()
    heatmap = np.asarray(heatmap, dtype=np.float64)
    code = np.asarray(code, dtype=np.float64)
    peak = (heatmap == maximum_filter(heatmap, size=(1, 3, 3), mode="constant")) & (
        heatmap > threshold
    )
    label, row, col = np.nonzero(peak)
    scores = heatmap[label, row, col]
    order = np.argsort(-scores, kind="stable")[:max_objects]
    label, row, col, scores = label[order], row[order], col[order], scores[order]
    c = code[:, row, col]
    size = grid.cell * STRIDE
    boxes = np.column_stack(
        [
            grid.x_range[0] + (col + c[0]) * size,
            grid.y_range[0] + (row + c[1]) * size,
            c[2],
            np.exp(np.clip(c[3:6], -5.0, 3.0)).T,
            np.arctan2(c[6], c[7]),
        ]
    )
    return boxes.reshape(-1, 7), label.astype(np.int64), scores


def result_lines(
    boxes: np.ndarray,
    labels: np.ndarray,
    scores: np.ndarray,
    calib: Calibration,
    image_shape: tuple[int, int] = DEFAULT_IMAGE_SHAPE,
) -> list[str]:
    """KITTI result lines (the label format plus a score) of LiDAR boxes ``(D, 7)`` through the
    frame's calibration; boxes entirely outside the image are left out (KITTI labels only what
    the camera sees). Truncation and occlusion are -1 (unknown), as in KITTI results."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    _, truncation = project_boxes(boxes, calib, image_shape)
    seen = truncation < 1.0
    boxes, labels, scores = boxes[seen], np.asarray(labels)[seen], np.asarray(scores)[seen]
    boxes[:, 6] = wrap_angle(boxes[:, 6])
    names = [CLASSES[int(k)] for k in labels]
    unknown = np.full(len(boxes), -1)
    lines = label_lines(boxes, names, calib, unknown, unknown.astype(float), image_shape)
    return [f"{line} {float(s):.4f}" for line, s in zip(lines, scores, strict=True)]


@dataclass(frozen=True)
class Detections:
    """One frame's detections: LiDAR boxes ``(D, 7)``, class indices into
    :data:`~.heads.CLASSES` and scores, by decreasing score."""

    boxes: np.ndarray
    labels: np.ndarray
    scores: np.ndarray

    def names(self) -> list[str]:
        return [CLASSES[int(k)] for k in self.labels]

    def kitti_lines(self, frame: Frame) -> list[str]:
        """KITTI result lines through the frame's calibration (boxes outside the image left out)."""
        shape = frame.metadata.get("image_shape", DEFAULT_IMAGE_SHAPE)
        return result_lines(self.boxes, self.labels, self.scores, frame.metadata["calib"], shape)
