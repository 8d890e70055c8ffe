"""``drcpo demo``: every stage that exists, end to end, on the built-in synthetic world.

Stages: synthetic KITTI data (cached under ``OUT/kitti``, reused while its parameters match) ->
ground-truth database -> candidate index -> augmentation with the conventional baseline
(ground-truth sampling) and with DR.CPO -> figures and a summary. A stage whose code is not in
this installation is skipped with a line saying so; nothing else is ever skipped silently.

Figures written under ``OUT``: ``bev.png`` (original / after ground-truth sampling / after
DR.CPO), ``construction.png`` (one object's iterative construction), ``density.png`` (points
per object against distance, real against inserted), plus ``summary.json``.
"""

from __future__ import annotations

import importlib
import json
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from drcpo.database import GroundTruthDatabase, ObjectRecord
from drcpo.datasets.kitti import KittiDataset, fov_mask
from drcpo.frame import Frame
from drcpo.geometry import points_in_boxes, to_canonical
from drcpo.outputs import atomic_write_bytes
from drcpo.partitions import partition_counts
from drcpo.synth.dataset import matches, synth_parameters, write_synthetic_kitti
from drcpo.synth.sensor import LidarConfig
from drcpo.synth.world import WorldConfig
from drcpo.viz import (
    BevPanel,
    ConstructionStep,
    DistanceSeries,
    bev_figure,
    construction_figure,
    density_figure,
)

DEFAULT_FRAMES = 16
DEFAULT_AUGMENTED = 4
MAX_CONSTRUCTION_PANELS = 8
CLASSES = ("Car", "Pedestrian", "Cyclist")


def optional(module: str, attribute: str) -> tuple[Any, str | None]:
    """``(module.attribute, None)`` when this installation has it, else ``(None, reason)``."""
    try:
        return getattr(importlib.import_module(module), attribute), None
    except ImportError as exc:
        return None, f"{module} is not available ({exc})"
    except AttributeError:
        return None, f"{module}.{attribute} is not available yet"


class _Run:
    """Timings, skipped stages and console output of one demo run."""

    def __init__(self, console: Console) -> None:
        self.console = console
        self.ms: dict[str, float] = {}
        self.skipped: dict[str, str] = {}
        self.step = 0

    @contextmanager
    def stage(self, name: str, what: str) -> Iterator[None]:
        self.step += 1
        self.console.print(f"[bold cyan][{self.step}][/] {what} ...")
        start = time.perf_counter()
        yield
        self.ms[name] = self.ms.get(name, 0.0) + (time.perf_counter() - start) * 1e3

    def skip(self, name: str, reason: str) -> None:
        self.skipped[name] = reason
        self.console.print(f"[yellow]skipped {name}[/]: {reason}")

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
        "skipped": run.skipped,
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
        run.console.print(f"[bold cyan][{run.step + 1}][/] reusing synthetic frames in {root}")
        run.step += 1
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
    build, reason = optional("drcpo.database.build", "build_database")
    with run.stage("database", f"building the ground-truth database {path}"):
        if build is not None:
            return build(root, "train", path, overwrite=True)
        run.console.print(f"    ({reason}; cutting objects with points_in_boxes instead)")
        records = []
        for frame in KittiDataset(root, "train"):
            inside = points_in_boxes(frame.points, frame.boxes)
            for i, (box, name) in enumerate(zip(frame.boxes, frame.names, strict=True)):
                records.append(
                    ObjectRecord(
                        to_canonical(frame.points[inside[:, i]], box),
                        str(name),
                        box,
                        frame.frame_id or "",
                        i,
                        int(frame.metadata["difficulty"][i]),
                        int(frame.metadata["occlusion"][i]),
                        float(frame.metadata["truncation"][i]),
                    )
                )
        GroundTruthDatabase.from_records(records).save(
            path, parameters={"source": "drcpo demo (synthetic)"}, overwrite=True
        )
        return GroundTruthDatabase.open(path)


def _index(run: _Run, database: GroundTruthDatabase) -> Any:
    build, reason = optional("drcpo.index", "build_index")
    if build is None:
        run.skip("candidate index", reason or "")
        return None
    with run.stage("candidate index", "indexing candidates (DR.CPO pre-processing)"):
        index = build(database)
        if database.path is not None and hasattr(index, "save"):
            index.save(database.path, overwrite=True)
    return index


def _fov_frame(dataset: KittiDataset, i: int) -> Frame:
    """Frame i cut to the camera's field of view, as OpenPCDet trains on KITTI."""
    frame = dataset[i]
    keep = fov_mask(frame.points, frame.metadata["calib"], dataset.image_shape(frame.frame_id))
    return frame.replace(points=frame.points[keep], metadata={**frame.metadata, "fov_only": True})


def _augment(
    run: _Run, database: GroundTruthDatabase, index: Any, frames: list[Frame], seed: int
) -> dict[str, list[Frame]]:
    results: dict[str, list[Frame]] = {}
    sampling, reason = optional("drcpo.pipeline", "GroundTruthSampling")
    if sampling is None:
        run.skip("ground-truth sampling", reason or "")
    else:
        _try_apply(
            run,
            results,
            "gt sampling",
            "ground-truth sampling",
            sampling(database),
            frames,
            seed,
            1,
        )
    drcpo, reason = optional("drcpo.pipeline", "DRCPO")
    if drcpo is None:
        run.skip("DR.CPO", reason or "")
    elif index is None:
        run.skip("DR.CPO", "needs the candidate index, which was skipped")
    else:
        _try_apply(run, results, "dr.cpo", "DR.CPO", drcpo(database, index), frames, seed, 2)
    return results


def _try_apply(run: _Run, results: dict, key: str, name: str, transform, frames, seed, stream):
    """Apply a transform; a module it needs that is not in this installation skips it."""
    try:
        results[key] = _apply(run, name, transform, frames, seed, stream)
    except ImportError as exc:
        run.ms.pop(name, None)
        run.skip(name, f"a module it needs is not available yet ({exc})")


def _apply(
    run: _Run, name: str, transform: Callable, frames: list[Frame], seed: int, stream: int
) -> list[Frame]:
    augmented = []
    if frames:  # loads (or compiles) the kernels and touches the database: timed on its own
        with run.stage(f"{name} first call", f"warming up {name} (its compiled kernels)"):
            transform(
                frames[0], np.random.default_rng(np.random.SeedSequence([seed, stream, 1, 0]))
            )
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
    index: Any,
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
        try:
            steps = _construction_steps(run, database, index, seed)
        except ImportError as exc:
            run.skip("construction figure", f"a module it needs is not available yet ({exc})")
            steps = None
        if steps:
            name, row, steps = steps
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


def _construction_steps(run: _Run, database: GroundTruthDatabase, index: Any, seed: int):
    construct, reason = optional("drcpo.construction", "construct_object")
    if construct is None or index is None:
        run.skip("construction figure", reason or "needs the candidate index, which was skipped")
        return None
    config_cls, _ = optional("drcpo.construction", "ConstructionConfig")
    rows = [r for r in database.rows_of_class("Car") if len(index.candidates_of(int(r)))]
    if not rows or config_cls is None:
        run.skip("construction figure", "no indexed Car with candidates")
        return None
    # A sparse (far or occluded) but not empty car shows the filling best.
    rows = sorted(rows, key=lambda r: database.num_points[r])
    sparse = [r for r in rows if database.num_points[r] >= 30] or rows
    row = int(sparse[len(sparse) // 4])
    name = str(database.names[row])
    max_counts = np.asarray(index.max_counts[name])
    grid = tuple(index.grids[name])

    def build(iterations: int | None):
        config = config_cls() if iterations is None else config_cls(max_iterations=iterations)
        rng = np.random.default_rng(seed)  # same draws each time: runs share their prefix
        return construct(database, row, index.candidates_of(row), rng, config, max_counts)

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
    for stage, reason in summary["skipped"].items():
        out.print(f"[yellow]skipped[/] {stage}: {reason}")
    out.print(f"figures: {', '.join(summary['figures'].values())}")
