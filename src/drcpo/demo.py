"""``drcpo demo``: every stage that exists, end to end, on the built-in synthetic world.

Stages: synthetic KITTI data (cached under ``OUT/kitti``, reused while its parameters match) ->
ground-truth database -> candidate index -> augmentation with the conventional baseline
(ground-truth sampling) and with DR.CPO -> figures and a summary. Every stage is mandatory: one
that fails stops the demo with a :class:`DemoError` naming it (``drcpo demo``: one line, exit
status 1), and the summary's ``stages`` lists the stages that ran, in order.

Figures written under ``OUT``: ``bev.png`` (original / after ground-truth sampling / after
DR.CPO), ``construction.png`` (one object's iterative construction), ``density.png`` (points
per object against distance, real against inserted), plus ``summary.json``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from drcpo.construction import ConstructionConfig, construct_object
from drcpo.database import GroundTruthDatabase, build_database
from drcpo.datasets.kitti import KittiDataset, fov_mask
from drcpo.errors import DrcpoError
from drcpo.frame import Frame
from drcpo.geometry import points_in_boxes
from drcpo.index import CandidateIndex, build_index
from drcpo.outputs import atomic_write_bytes
from drcpo.partitions import partition_counts
from drcpo.synth.dataset import matches, synth_parameters, write_synthetic_kitti
from drcpo.synth.sensor import LidarConfig
from drcpo.synth.world import WorldConfig
from drcpo.transforms import DRCPO, GroundTruthSampling, Transform
from drcpo.viz import (
    BevPanel,
    ConstructionStep,
    DistanceSeries,
    bev_figure,
    construction_figure,
    density_figure,
)

__all__ = ["DEFAULT_AUGMENTED", "DEFAULT_FRAMES", "DemoError", "inserted_mask", "run_demo"]

DEFAULT_FRAMES = 16
DEFAULT_AUGMENTED = 4
MAX_CONSTRUCTION_PANELS = 8
CLASSES = ("Car", "Pedestrian", "Cyclist")


class DemoError(DrcpoError):
    """A stage of the demo failed; the message names the stage and the cause."""


class _Run:
    """Timings, stages run and console output of one demo run."""

    def __init__(self, console: Console) -> None:
        self.console = console
        self.ms: dict[str, float] = {}
        self.ran: list[str] = []
        self.step = 0

    @contextmanager
    def stage(self, name: str, what: str) -> Iterator[None]:
        """Time stage ``name``; any exception in it becomes a :class:`DemoError` naming it (a
        bug too: the demo is the end-to-end check, so it must not look like a success)."""
        self.step += 1
        self.console.print(f"[bold cyan][{self.step}][/] {what} ...")
        start = time.perf_counter()
        try:
            yield
        except Exception as exc:
            cause = str(exc) if isinstance(exc, DrcpoError) else f"{type(exc).__name__}: {exc}"
            raise DemoError(f"demo stage {name!r} failed: {cause}") from exc
        self.ms[name] = self.ms.get(name, 0.0) + (time.perf_counter() - start) * 1e3
        self.ran.append(name)

    def progress(self) -> Progress:
        return Progress(
            TextColumn("    {task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=self.console,
            transient=True,
        )


def run_demo(
    out: str | Path = "drcpo_demo",
    frames: int = DEFAULT_FRAMES,
    seed: int = 0,
    augment_frames: int = DEFAULT_AUGMENTED,
    console: Console | None = None,
) -> dict[str, Any]:
    """Run the demo into ``out``; returns (and writes to ``out/summary.json``) its summary."""
    out = Path(out)
    run = _Run(console or Console(stderr=True))
    start = time.perf_counter()
    root = _synthetic_data(run, out / "kitti", frames, seed)
    database = _database(run, root, out / "gt_database")
    index = _index(run, database)
    dataset = KittiDataset(root, "train")
    originals = [_fov_frame(dataset, i) for i in range(min(augment_frames, len(dataset)))]
    results = _augment(run, database, index, originals, seed)
    figures = _figures(run, out, database, index, originals, results, seed)
    summary = {
        "out": str(out),
        "frames": frames,
        "seed": seed,
        "augmented_frames": len(originals),
        "ms": run.ms,
        "stages": run.ran,
        "figures": {k: str(v) for k, v in figures.items()},
        "database": database.summary(),
        "points_per_frame": {
            label: float(np.mean([len(f) for f in group]))
            for label, group in {"original": originals, **results}.items()
        },
        "objects_per_frame": {
            label: {c: float(np.mean([np.sum(f.names == c) for f in group])) for c in CLASSES}
            for label, group in {"original": originals, **results}.items()
        },
    }
    summary["total_s"] = time.perf_counter() - start
    atomic_write_bytes(out / "summary.json", (json.dumps(summary, indent=2) + "\n").encode())
    _print_summary(run.console, summary, results)
    return summary


# Stages ---------------------------------------------------------------------------------------
def _synthetic_data(run: _Run, root: Path, frames: int, seed: int) -> Path:
    parameters = synth_parameters(frames, seed, WorldConfig(), LidarConfig(), 0.0)
    if matches(root, parameters):
        run.step += 1
        run.console.print(f"[bold cyan][{run.step}][/] reusing synthetic frames in {root}")
        run.ran.append("synthetic world")
        return root
    with run.stage("synthetic world", f"ray-casting {frames} synthetic frames into {root}"):
        with run.progress() as bar:
            task = bar.add_task("frames", total=frames)
            report = write_synthetic_kitti(
                root,
                frames,
                seed,
                val_fraction=0.0,
                overwrite=True,
                progress=lambda done, total: bar.update(task, completed=done),
            )
    run.ms["synthetic world per frame"] = report["ms_per_frame"]
    return root


def _database(run: _Run, root: Path, path: Path) -> GroundTruthDatabase:
    with run.stage("database", f"building the ground-truth database {path}"):
        return build_database(root, "train", path, overwrite=True)


def _index(run: _Run, database: GroundTruthDatabase) -> CandidateIndex:
    with run.stage("candidate index", "indexing candidates (DR.CPO pre-processing)"):
        index = build_index(database)
        index.save(database.path, overwrite=True)
    return index


def _fov_frame(dataset: KittiDataset, i: int) -> Frame:
    """Frame i cut to the camera's field of view, as OpenPCDet trains on KITTI."""
    frame = dataset[i]
    keep = fov_mask(frame.points, frame.metadata["calib"], dataset.image_shape(frame.frame_id))
    return frame.replace(points=frame.points[keep], metadata={**frame.metadata, "fov_only": True})


def _augment(
    run: _Run, database: GroundTruthDatabase, index: CandidateIndex, frames: list[Frame], seed: int
) -> dict[str, list[Frame]]:
    return {
        "gt sampling": _apply(
            run, "ground-truth sampling", GroundTruthSampling(database), frames, seed, 1
        ),
        "dr.cpo": _apply(run, "DR.CPO", DRCPO(database, index), frames, seed, 2),
    }


def _apply(
    run: _Run, name: str, transform: Transform, frames: list[Frame], seed: int, stream: int
) -> list[Frame]:
    augmented = []
    # Loads (or compiles) the kernels and touches the database: timed on its own. (The demo
    # always has a frame: KittiDataset refuses an empty split and --augment-frames is >= 1.)
    with run.stage(f"{name} first call", f"warming up {name} (its compiled kernels)"):
        transform(frames[0], np.random.default_rng(np.random.SeedSequence([seed, stream, 1, 0])))
    with run.stage(name, f"augmenting {len(frames)} frames with {name}"):
        with run.progress() as bar:
            task = bar.add_task("frames", total=len(frames))
            for i, frame in enumerate(frames):
                rng = np.random.default_rng(np.random.SeedSequence([seed, stream, i]))
                augmented.append(transform(frame, rng))
                bar.update(task, completed=i + 1)
    run.ms[f"{name} per frame"] = run.ms[name] / max(len(frames), 1)
    for key, value in _stage_ms(augmented).items():
        run.ms[f"  {key} per frame"] = value
    return augmented


def _stage_ms(frames: list[Frame]) -> dict[str, float]:
    """Mean ms per frame of each stage the transform recorded in its statistics."""
    totals: dict[str, float] = {}
    for frame in frames:
        stages = frame.metadata.get("augment_stats", {}).get("stages", {})
        for stage, record in stages.items():
            totals[stage] = totals.get(stage, 0.0) + float(record.get("ms", 0.0))
    return {k: v / max(len(frames), 1) for k, v in totals.items()}


# Figures --------------------------------------------------------------------------------------
def inserted_mask(original: Frame, augmented: Frame) -> np.ndarray:
    """``bool (M,)``: boxes of ``augmented`` that are not boxes of ``original``."""
    if len(original.boxes) == 0:
        return np.ones(len(augmented.boxes), dtype=bool)
    delta = np.abs(augmented.boxes[:, None, :] - original.boxes[None, :, :]).max(axis=2)
    return ~(delta < 1e-6).any(axis=1)


def _figures(
    run: _Run,
    out: Path,
    database: GroundTruthDatabase,
    index: CandidateIndex,
    originals: list[Frame],
    results: dict[str, list[Frame]],
    seed: int,
) -> dict[str, Path]:
    figures: dict[str, Path] = {}
    with run.stage("figures", f"drawing figures into {out}"):
        titles = {"gt sampling": "after ground-truth sampling", "dr.cpo": "after DR.CPO"}
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
                    titles.get(label, label),
                    inserted_mask(first, frame),
                )
            )
        figures["bev"] = bev_figure(panels, out / "bev.png")
        figures["density"] = density_figure(
            _density_series(database, originals, results), out / "density.png"
        )
    with run.stage("construction figure", "drawing one object's iterative construction"):
        name, row, steps = _construction_steps(database, index, seed)
        title = (
            f"iterative construction of database object {row} ({name}), seen from above\n"
            "blue: its own points (mirrored); orange: points added from candidates; "
            "green: share of each column's partitions above the density threshold"
        )
        figures["construction"] = construction_figure(steps, out / "construction.png", title)
    for path in figures.values():
        run.console.print(f"    wrote {path}")
    return figures


def _most_inserted(originals: list[Frame], results: dict[str, list[Frame]]) -> int:
    """The augmented frame into which the last transform (DR.CPO when it ran) inserted most."""
    if not results:
        return 0
    group = list(results.values())[-1]
    counts = [int(inserted_mask(o, a).sum()) for o, a in zip(originals, group, strict=True)]
    return int(np.argmax(counts))


def _density_series(
    database: GroundTruthDatabase, originals: list[Frame], results: dict[str, list[Frame]]
) -> list[DistanceSeries]:
    boxes = database.boxes
    series = [
        DistanceSeries(
            "real objects (database)",
            np.hypot(boxes[:, 0], boxes[:, 1]),
            database.num_points,
            "#1f77b4",
            "o",
        )
    ]
    styles = {
        "gt sampling": ("inserted by GT sampling", "#9467bd", "s"),
        "dr.cpo": ("inserted by DR.CPO", "#ff7f0e", "D"),
    }
    for label, group in results.items():
        distance, points = [], []
        for original, frame in zip(originals, group, strict=True):
            new = inserted_mask(original, frame)
            counts = points_in_boxes(frame.points, frame.boxes[new]).sum(axis=0)
            distance += np.hypot(frame.boxes[new, 0], frame.boxes[new, 1]).tolist()
            points += counts.tolist()
        text, colour, marker = styles.get(label, (label, "#7f7f7f", "^"))
        series.append(DistanceSeries(text, np.array(distance), np.array(points), colour, marker))
    return series


def _construction_steps(
    database: GroundTruthDatabase, index: CandidateIndex, seed: int
) -> tuple[str, int, list[ConstructionStep]]:
    """``(class, database row, steps)`` of the construction of one sparse indexed Car."""
    rows = [r for r in database.rows_of_class("Car") if len(index.candidates_of(int(r)))]
    if not rows:
        raise DemoError("no Car of the database has candidates in the index (more --frames?)")
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


# Summary --------------------------------------------------------------------------------------
def _print_summary(console: Console, summary: dict[str, Any], results: dict) -> None:
    groups = ["original", *results]
    table = Table(title=f"drcpo demo: {summary['augmented_frames']} augmented frames (means)")
    table.add_column("")
    for group in groups:
        table.add_column(group, justify="right")
    table.add_row("points per frame", *(f"{summary['points_per_frame'][g]:,.0f}" for g in groups))
    for name in CLASSES:
        table.add_row(
            f"{name} per frame", *(f"{summary['objects_per_frame'][g][name]:.1f}" for g in groups)
        )
    out = Console()
    out.print(table)
    timing = Table(title="milliseconds per stage")
    timing.add_column("stage")
    timing.add_column("ms", justify="right")
    for stage, ms in summary["ms"].items():
        timing.add_row(stage, f"{ms:,.1f}")
    timing.add_row("[bold]total", f"{summary['total_s'] * 1e3:,.0f}")
    out.print(timing)
    database = Table(title="ground-truth database")
    database.add_column("class")
    database.add_column("objects", justify="right")
    database.add_column("points", justify="right")
    for name, row in summary["database"].items():
        database.add_row(name, str(row["objects"]), str(row["points"]))
    out.print(database)
    out.print(f"figures: {', '.join(summary['figures'].values())}")
