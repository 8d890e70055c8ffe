"""Synthetic KITTI labels and noisy detections, for testing and timing the evaluator.

Labels look like KITTI's: classes in KITTI's proportions (with Van, Truck, Person_sitting,
Misc and DontCare rows), 3D boxes in front of the camera, 2D boxes projected with KITTI's
focal length and clipped to the image, truncation and occlusion levels spread over all
difficulties. Detections are jittered copies of the objects (some missed, some with a wrong
class, some with the heading's sign flipped, some duplicated) plus false positives, a few of
them inside DontCare regions, with random scores.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

FOCAL, CU, CV, WIDTH, HEIGHT = 721.5377, 609.5593, 172.854, 1242.0, 375.0
CLASSES = ("Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Cyclist", "Misc", "DontCare")
SHARES = (0.45, 0.08, 0.03, 0.17, 0.03, 0.08, 0.03, 0.13)
SIZES = {  # mean h, w, l (metres)
    "Car": (1.53, 1.63, 3.88),
    "Van": (2.2, 1.9, 5.1),
    "Truck": (3.2, 2.6, 10.0),
    "Pedestrian": (1.76, 0.66, 0.84),
    "Person_sitting": (1.27, 0.54, 0.8),
    "Cyclist": (1.74, 0.6, 1.76),
    "Misc": (1.9, 1.5, 3.0),
}
CONFUSED = {"Van": "Car", "Car": "Van", "Person_sitting": "Pedestrian", "Cyclist": "Pedestrian"}


def _image_box(location: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Rough 2D boxes (M, 4) of 3D boxes: their projected extent, clipped to the image."""
    x, y, z = location.T
    h, w, length = size.T
    half = np.maximum(w, length) / 2
    left = CU + FOCAL * (x - half) / z
    right = CU + FOCAL * (x + half) / z
    top = CV + FOCAL * (y - h) / z
    bottom = CV + FOCAL * y / z
    box = np.column_stack([left, top, right, bottom])
    return np.clip(box, [0, 0, 0, 0], [WIDTH, HEIGHT, WIDTH, HEIGHT])


def make_labels(rng: np.random.Generator) -> list[tuple]:
    """One frame's label rows: (name, trunc, occ, alpha, bbox(4), hwl(3), xyz(3), ry)."""
    count = int(rng.integers(0, 16))
    names = rng.choice(CLASSES, size=count, p=SHARES)
    rows = []
    for name in names:
        if name == "DontCare":
            left, top = rng.uniform(0, WIDTH - 60), rng.uniform(100, HEIGHT - 40)
            box = (left, top, left + rng.uniform(10, 120), top + rng.uniform(8, 40))
            rows.append((name, -1.0, -1, -10.0, box, (-1, -1, -1), (-1000, -1000, -1000), -10.0))
            continue
        size = np.array(SIZES[name]) * rng.uniform(0.85, 1.15, 3)
        location = np.array([rng.uniform(-18, 18), rng.uniform(1.2, 2.2), rng.uniform(4, 65)])
        ry = rng.uniform(-np.pi, np.pi)
        box = _image_box(location[None], size[None])[0]
        truncation = rng.choice([0.0, 0.0, 0.0, rng.uniform(0, 0.2), rng.uniform(0, 0.9)])
        occlusion = int(rng.choice([0, 0, 1, 1, 2, 3]))
        alpha = ry - np.arctan2(location[0], location[2])
        rows.append((name, truncation, occlusion, alpha, box, size, location, ry))
    return rows


def make_detections(rows: list[tuple], rng: np.random.Generator) -> list[tuple]:
    """Noisy detections of one frame's labels, rows as :func:`make_labels`'s plus a score."""
    out = []
    for name, _, _, alpha, box, size, location, ry in rows:
        if name == "DontCare" or rng.random() < 0.15:
            continue
        copies = 2 if rng.random() < 0.08 else 1
        for _ in range(copies):
            shown = CONFUSED.get(name, name) if rng.random() < 0.12 else name
            spread = 0.03 + 0.003 * location[2]
            loc = location + rng.normal(0, spread, 3) * (1, 0.5, 1.5)
            dims = np.asarray(size) * rng.normal(1, 0.06, 3)
            yaw = ry + rng.normal(0, 0.06)
            if rng.random() < 0.1:
                yaw = -yaw  # heading sign error: the footprint mirrors
            bbox = np.asarray(box) + rng.normal(0, 1 + 25 / location[2], 4)
            score = float(
                np.clip(rng.beta(4, 2) - 0.3 * rng.random() * np.abs(loc - location)[0], 0, 1)
            )
            out.append((shown, -1, -1, alpha + rng.normal(0, 0.2), bbox, dims, loc, yaw, score))
    for _ in range(int(rng.poisson(2.5))):
        name = str(rng.choice(["Car", "Car", "Pedestrian", "Cyclist"]))
        size = np.array(SIZES[name]) * rng.uniform(0.8, 1.2, 3)
        location = np.array([rng.uniform(-18, 18), rng.uniform(1.2, 2.2), rng.uniform(4, 65)])
        ry = rng.uniform(-np.pi, np.pi)
        box = _image_box(location[None], size[None])[0]
        dont_care = [row[4] for row in rows if row[0] == "DontCare"]
        if dont_care and rng.random() < 0.4:  # a detection inside a DontCare region
            left, top, right, bottom = dont_care[int(rng.integers(len(dont_care)))]
            box = np.array([left + 1, top + 1, right - 1, bottom + 30 * rng.random()])
        alpha = ry - np.arctan2(location[0], location[2])
        out.append((name, -1, -1, alpha, box, size, location, ry, float(rng.random() * 0.8)))
    return out


def format_rows(rows: list[tuple], decimals: int = 2) -> str:
    """KITTI label-file text of rows (a score column when rows carry one)."""
    lines = []
    for name, trunc, occ, alpha, box, hwl, xyz, ry, *score in rows:
        numbers = [*box, *hwl, *xyz, ry, *score]
        text = " ".join(f"{float(v):.{decimals}f}" for v in numbers)
        lines.append(f"{name} {float(trunc):.2f} {int(occ)} {float(alpha):.2f} {text}")
    return "".join(line + "\n" for line in lines)


def write_frames(
    gt_dir: Path, dt_dir: Path, frames: int, rng: np.random.Generator, labels=None
) -> list[str]:
    """Write ``frames`` label files and noisy detections (``%06d.txt``); returns the frame ids.

    ``labels``: optional list of label rows to reuse cyclically instead of random ones.
    """
    gt_dir.mkdir(parents=True, exist_ok=True)
    dt_dir.mkdir(parents=True, exist_ok=True)
    ids = [f"{i:06d}" for i in range(frames)]
    for i, frame_id in enumerate(ids):
        rows = labels[i % len(labels)] if labels else make_labels(rng)
        (gt_dir / f"{frame_id}.txt").write_text(format_rows(rows))
        (dt_dir / f"{frame_id}.txt").write_text(format_rows(make_detections(rows, rng), 4))
    return ids


def read_rows(path: Path) -> list[tuple]:
    """Label rows of a KITTI label file, in :func:`make_labels`'s layout."""
    rows = []
    for line in path.read_text().splitlines():
        f = line.split()
        numbers = [float(v) for v in f[1:]]
        rows.append(
            (f[0], numbers[0], int(numbers[1]), numbers[2], numbers[3:7],
             np.array(numbers[7:10]), np.array(numbers[10:13]), numbers[13])
        )  # fmt: skip
    return rows
