"""The figures of ``drcpo demo`` (:mod:`drcpo.demo`), drawn from the frames it augmented:

- ``bev.png`` (:func:`draw_bev`): one frame from above, original, after ground-truth sampling
  and after DR.CPO with each preset, the inserted boxes marked;
- ``density.png`` (:func:`draw_density`): points per object against distance, per class: the
  frames' own objects against those each preset inserted;
- ``side_view.png`` (:func:`draw_side_view`): a real object and one inserted by each preset at
  about the same distance (:func:`closest_match`), as the sensor saw them and from the side;
- ``construction.png`` (:func:`draw_construction`): one sparse Car's iterative construction.

A figure with nothing to draw (no object to show) raises a :class:`~drcpo.errors.DrcpoError`,
which the demo reports as its stage's failure.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from drcpo.construction import ConstructionConfig, construct_object
from drcpo.database import GroundTruthDatabase
from drcpo.errors import DrcpoError
from drcpo.frame import Frame
from drcpo.geometry import points_in_boxes
from drcpo.index import CandidateIndex
from drcpo.partitions import partition_counts
from drcpo.synth.sensor import LidarConfig
from drcpo.viz import (
    BevPanel,
    ConstructionStep,
    DistanceSeries,
    ObjectView,
    bev_figure,
    construction_figure,
    density_figure,
    side_view_figure,
)

__all__ = [
    "CLASSES",
    "closest_match",
    "draw_bev",
    "draw_construction",
    "draw_density",
    "draw_side_view",
    "inserted_mask",
]

#: The classes the demo shows (in its figures and its summary).
CLASSES = ("Car", "Pedestrian", "Cyclist")
MAX_CONSTRUCTION_PANELS = 8
#: The real object of the side view has at least this many points when one has (scan lines show).
SIDE_VIEW_POINTS = 40
#: Colour and marker of each preset's series, in the order the presets are given.
PRESET_STYLES = (("#ff7f0e", "D"), ("#2ca02c", "s"), ("#9467bd", "^"), ("#8c564b", "v"))


def inserted_mask(original: Frame, augmented: Frame) -> np.ndarray:
    """``bool (M,)``: boxes of ``augmented`` that are not boxes of ``original``."""
    if len(original.boxes) == 0:
        return np.ones(len(augmented.boxes), dtype=bool)
    delta = np.abs(augmented.boxes[:, None, :] - original.boxes[None, :, :]).max(axis=2)
    return ~(delta < 1e-6).any(axis=1)


def draw_bev(originals: list[Frame], results: dict[str, list[Frame]], path: Path) -> Path:
    """``bev.png``: from above, the frame the last preset inserted most into, as it was and after
    each transform of ``results`` (``{label: its frames}``), the inserted boxes marked."""
    titles = {"gt sampling": "after ground-truth sampling"}
    shown = _most_inserted(originals, results)
    first = originals[shown]
    title = f"original (frame {first.frame_id})"
    panels = [BevPanel(first.points, first.boxes, first.names.tolist(), title)]
    for label, group in results.items():
        frame = group[shown]
        panels.append(
            BevPanel(
                frame.points,
                frame.boxes,
                frame.names.tolist(),
                titles.get(label, f"after DR.CPO, preset {label}"),
                inserted_mask(first, frame),
            )
        )
    return bev_figure(panels, path)


def draw_density(originals: list[Frame], results: dict[str, list[Frame]], path: Path) -> Path:
    """``density.png``: points per object against distance, per class, of the frames' own objects
    and of those each preset of ``results`` inserted."""
    return density_figure(_density_series(originals, results), path, classes=CLASSES)


def draw_construction(
    database: GroundTruthDatabase, index: CandidateIndex, seed: int, path: Path
) -> Path:
    """``construction.png``: the iterative construction of one sparse indexed Car."""
    name, row, steps = _construction_steps(database, index, seed)
    title = (
        f"iterative construction of database object {row} ({name}), seen from above\n"
        "blue: its own points (mirrored); orange: points added from candidates; "
        "green: share of each column's partitions above the density threshold"
    )
    return construction_figure(steps, path, title)


def _most_inserted(originals: list[Frame], results: dict[str, list[Frame]]) -> int:
    """The augmented frame into which the last transform (the last preset) inserted most."""
    if not results:
        return 0
    group = list(results.values())[-1]
    counts = [int(inserted_mask(o, a).sum()) for o, a in zip(originals, group, strict=True)]
    return int(np.argmax(counts))


def _objects(frames: list[Frame], originals: list[Frame] | None = None) -> dict[str, np.ndarray]:
    """The labelled objects of ``frames`` (only those not in ``originals``, when given), as
    ``frame`` (index into ``frames``), ``box`` (index into its boxes), ``names``, ``distance``
    (metres, from the sensor) and ``points`` (points in the box)."""
    columns: dict[str, list] = {"frame": [], "box": [], "names": [], "distance": [], "points": []}
    for i, frame in enumerate(frames):
        chosen = (
            np.ones(len(frame.boxes), bool)
            if originals is None
            else inserted_mask(originals[i], frame)
        )
        rows = np.flatnonzero(chosen)
        boxes = frame.boxes[rows]
        columns["frame"] += [i] * len(rows)
        columns["box"] += rows.tolist()
        columns["names"] += frame.names[rows].tolist()
        columns["distance"] += np.hypot(boxes[:, 0], boxes[:, 1]).tolist()
        columns["points"] += points_in_boxes(frame.points, boxes).sum(axis=0).tolist()
    return {
        "frame": np.array(columns["frame"], dtype=np.int64),
        "box": np.array(columns["box"], dtype=np.int64),
        "names": np.array(columns["names"], dtype=str),
        "distance": np.array(columns["distance"], dtype=np.float64),
        "points": np.array(columns["points"], dtype=np.int64),
    }


def _density_series(
    originals: list[Frame], results: dict[str, list[Frame]]
) -> list[DistanceSeries]:
    """The frames' own labelled objects, then those each preset inserted."""
    real = _objects(originals)
    series = [
        DistanceSeries(
            "real (the frames' labels)",
            real["distance"],
            real["points"],
            "#1f77b4",
            "o",
            real["names"],
        )
    ]
    for k, (label, group) in enumerate(results.items()):
        colour, marker = PRESET_STYLES[k % len(PRESET_STYLES)]
        new = _objects(group, originals)
        text = f"inserted, preset {label}"
        series.append(
            DistanceSeries(text, new["distance"], new["points"], colour, marker, new["names"])
        )
    return series


def closest_match(reference: np.ndarray, candidates: Sequence[np.ndarray]) -> tuple[int, list[int]]:
    """The reference distance and, from each group of candidate distances, the one nearest it,
    chosen so that the largest gap to the reference is smallest.

    Args:
        reference: ``(R,)`` distances, metres.
        candidates: ``K`` arrays ``(C_k,)`` of distances, metres.

    Returns ``(i, [j_0, ..., j_{K-1}])``; ties go to the lowest index. Raises ``ValueError``
    when ``reference`` or any group is empty.
    """
    reference = np.asarray(reference, dtype=np.float64).reshape(-1)
    groups = [np.asarray(c, dtype=np.float64).reshape(-1) for c in candidates]
    if len(reference) == 0 or any(len(g) == 0 for g in groups):
        raise ValueError("closest_match needs at least one distance in every group")
    nearest, gaps = [], []
    for group in groups:
        gap = np.abs(group[None, :] - reference[:, None])  # (R, C_k)
        nearest.append(np.argmin(gap, axis=1))  # argmin: the first of equal gaps
        gaps.append(gap.min(axis=1))
    worst = np.max(gaps, axis=0) if gaps else np.zeros(len(reference))
    i = int(np.argmin(worst))
    return i, [int(n[i]) for n in nearest]


def _side_view_picks(pools: list[dict[str, np.ndarray]]) -> tuple[str, list[int]]:
    """``(class, [row of each pool])``: one object per pool (of :func:`_objects`; the first is
    the real ones), of one class, at about the same distance (:func:`closest_match`): Cars when
    every pool has one, else the next class. The real object has at least
    :data:`SIDE_VIEW_POINTS` points when one has; an inserted one has points, however few (a
    sparse one shows what its preset does at that distance)."""
    for least in (SIDE_VIEW_POINTS, 1):
        for name in CLASSES:
            fewest = [least] + [1] * (len(pools) - 1)
            rows = [
                np.flatnonzero((p["names"] == name) & (p["points"] >= n))
                for p, n in zip(pools, fewest, strict=True)
            ]
            if all(len(r) for r in rows):
                distances = [p["distance"][r] for p, r in zip(pools, rows, strict=True)]
                i, js = closest_match(distances[0], distances[1:])
                return name, [int(r[k]) for r, k in zip(rows, [i, *js], strict=True)]
    raise DrcpoError(
        "no class has both a real object and one inserted by every preset with points to draw "
        "in the side view (more --augment-frames?)"
    )


def draw_side_view(originals: list[Frame], results: dict[str, list[Frame]], path: Path) -> Path:
    """``side_view.png``: a real object next to one inserted by each preset
    (:func:`_side_view_picks`)."""
    pools = [_objects(originals), *(_objects(group, originals) for group in results.values())]
    name, picks = _side_view_picks(pools)
    frames = [originals, *results.values()]
    titles = [f"real {name}", *(f"inserted, preset {label}" for label in results)]
    views = []
    for pool, group, row, title in zip(pools, frames, picks, titles, strict=True):
        frame = group[int(pool["frame"][row])]
        box = frame.boxes[int(pool["box"][row])]
        inside = points_in_boxes(frame.points, box[None])[:, 0]
        views.append(ObjectView(frame.points[inside], box, f"{title} (frame {frame.frame_id})"))
    return side_view_figure(
        views,
        path,
        # the synthetic world's sensor, which recorded the frames, at the origin
        elevations_deg=np.asarray(LidarConfig().elevations_deg),
        title=(
            f"a {name} as the sensor saw it (top; grey lines: its beams' elevations) and from "
            "the side (bottom): a real one and one each preset inserted at about the same distance"
        ),
    )


def _construction_steps(
    database: GroundTruthDatabase, index: CandidateIndex, seed: int
) -> tuple[str, int, list[ConstructionStep]]:
    """``(class, database row, steps)`` of the construction of one sparse indexed Car."""
    rows = [r for r in database.rows_of_class("Car") if len(index.candidates_of(int(r)))]
    if not rows:
        raise DrcpoError("no Car of the database has candidates in the index (more --frames?)")
    # A sparse (far or occluded) but not empty car shows the filling best.
    rows = sorted(rows, key=lambda r: database.num_points[r])
    sparse = [r for r in rows if database.num_points[r] >= 30] or rows
    row = int(sparse[len(sparse) // 4])
    name = str(database.names[row])
    max_counts = np.asarray(index.max_counts[name])
    grid = tuple(index.grids[name])

    def build(iterations: int | None):
        config = (
            ConstructionConfig()
            if iterations is None
            else ConstructionConfig(max_iterations=iterations)
        )
        rng = np.random.default_rng(seed)  # same draws each time: runs share their prefix
        return construct_object(database, row, index.candidates_of(row), rng, config, max_counts)

    total = build(None).iterations
    shown = np.unique(np.round(np.linspace(0, total, min(total + 1, MAX_CONSTRUCTION_PANELS))))
    steps, threshold, source_count = [], 0.0, 0
    for iterations in shown.astype(int).tolist():
        built = build(iterations)
        counts = partition_counts(built.points, built.dims, grid)
        fillable = max_counts[: len(counts)] > 0
        density = counts / np.where(fillable, max_counts[: len(counts)], 1)
        if iterations == 0:
            occupied = fillable & (counts > 0)
            threshold = float(density[occupied].mean()) if occupied.any() else 0.0
            source_count = len(built.points)
        above = fillable & (density > threshold)
        added = np.arange(len(built.points)) >= source_count
        steps.append(
            ConstructionStep(
                built.points,
                added,
                built.dims,
                above.reshape(grid),
                fillable.reshape(grid),
                built.coverage,
                built.iterations,
            )
        )
    return name, row, steps
