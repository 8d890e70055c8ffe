"""``drcpo demo``: every stage that exists, end to end, on the built-in synthetic world.

Stages: the DR.CPO presets' configs -> synthetic KITTI data (cached under ``OUT/kitti``, reused
while its parameters match) -> ground-truth database -> candidate index -> augmentation with the
conventional baseline (ground-truth sampling) and with DR.CPO under each preset (``paper``: the
paper's method, the default) -> figures and a summary.
Every stage is mandatory: one that fails stops the demo with a :class:`DemoError` naming it
(``drcpo demo``: one line, exit status 1), and the summary's ``stages`` lists the stages that
ran, in order.

Written under ``OUT``: the figures ``bev.png``, ``construction.png``, ``density.png`` and
``side_view.png`` (:mod:`drcpo.demo_figures` draws them, and says what each shows), plus
``summary.json``.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from drcpo.config import DRCPOConfig, load_config
from drcpo.database import GroundTruthDatabase, build_database
from drcpo.datasets.kitti import KittiDataset
from drcpo.datasets.kitti_coordinates import fov_mask
from drcpo.demo_figures import (
    CLASSES,
    draw_bev,
    draw_construction,
    draw_density,
    draw_side_view,
    inserted_mask,
)
from drcpo.errors import DrcpoError
from drcpo.frame import Frame
from drcpo.index import CandidateIndex
from drcpo.index_build import build_index
from drcpo.outputs import OutputKind, atomic_write_bytes, check_output
from drcpo.synth.dataset import matches, synth_parameters, write_synthetic_kitti
from drcpo.synth.sensor import LidarConfig
from drcpo.synth.world import WorldConfig
from drcpo.transforms import DRCPO, GroundTruthSampling, Transform

__all__ = [
    "DEFAULT_AUGMENTED",
    "DEFAULT_FRAMES",
    "DEFAULT_PRESETS",
    "DemoError",
    "run_demo",
]

DEFAULT_FRAMES = 16
DEFAULT_AUGMENTED = 4
#: The DR.CPO presets the demo compares (names of packaged configs, or YAML paths).
DEFAULT_PRESETS: tuple[str, ...] = ("paper",)


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


#: What the demo writes into its directory: its marker ``demo.json`` (written first, so that a
#: demo stopped half-way may be run again there), the cached synthetic frames, their database
#: and index, the figures and the summary.
DEMO_OUTPUT = OutputKind(
    "drcpo demo output",
    "demo.json",
    "drcpo-demo",
    ("kitti", "gt_database", "*.png", "summary.json"),
)


def run_demo(
    out: str | Path = "drcpo_demo",
    frames: int = DEFAULT_FRAMES,
    seed: int = 0,
    augment_frames: int = DEFAULT_AUGMENTED,
    console: Console | None = None,
    presets: Sequence[str | os.PathLike] = DEFAULT_PRESETS,
) -> dict[str, Any]:
    """Run the demo into ``out``; returns (and writes to ``out/summary.json``) its summary.

    ``presets``: the DR.CPO configurations compared, each a packaged preset's name or a YAML
    path (anything :func:`drcpo.config.load_config` reads; its ``drcpo`` section is used), named
    in the figures and the summary by the name or the file's stem.
    """
    out = Path(out)
    # Its files go straight into ``out``, so ``out`` must be new, empty or an earlier demo's:
    # never a directory of the user's (check_output names what is in the way).
    check_output(out, DEMO_OUTPUT, overwrite=True)
    run = _Run(console or Console(stderr=True))
    start = time.perf_counter()
    configs = _presets(run, presets)  # a bad one stops the demo before anything is written
    marker = json.dumps({"format": DEMO_OUTPUT.format}) + "\n"
    atomic_write_bytes(out / DEMO_OUTPUT.marker, marker.encode())
    root = _synthetic_data(run, out / "kitti", frames, seed)
    database = _database(run, root, out / "gt_database")
    index = _index(run, database)
    dataset = KittiDataset(root, "train")
    originals = [_fov_frame(dataset, i) for i in range(min(augment_frames, len(dataset)))]
    results = _augment(run, database, index, originals, seed, configs)
    figures = _figures(run, out, database, index, originals, results, list(configs), seed)
    groups = {"original": originals, **results}
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
            label: float(np.mean([len(f) for f in group])) for label, group in groups.items()
        },
        "objects_per_frame": {
            label: {c: float(np.mean([np.sum(f.names == c) for f in group])) for c in CLASSES}
            for label, group in groups.items()
        },
        "inserted_per_frame": {
            label: _inserted_per_frame(originals, group) for label, group in results.items()
        },
    }
    summary["presets"] = {
        label: {
            "config": str(source),
            "points_per_frame": summary["points_per_frame"][label],
            "objects_per_frame": summary["objects_per_frame"][label],
            "inserted_per_frame": summary["inserted_per_frame"][label],
            "ms_per_frame": run.ms[f"DR.CPO {label} per frame"],
            "first_call_ms": run.ms[f"DR.CPO {label} first call"],
        }
        for label, (source, _) in configs.items()
    }
    summary["total_s"] = time.perf_counter() - start
    atomic_write_bytes(out / "summary.json", (json.dumps(summary, indent=2) + "\n").encode())
    _print_summary(run.console, summary, results)
    return summary


# Stages ---------------------------------------------------------------------------------------
def _presets(
    run: _Run, presets: Sequence[str | os.PathLike]
) -> dict[str, tuple[str | os.PathLike, DRCPOConfig]]:
    """``{label: (source, its drcpo section)}``, read before any work so a bad one stops the
    demo at once."""
    configs: dict[str, tuple[str | os.PathLike, DRCPOConfig]] = {}
    labels = [_preset_label(source) for source in presets]
    with run.stage("presets", f"reading the DR.CPO presets {', '.join(labels)}"):
        if not labels:
            raise DemoError("no DR.CPO preset given")
        for label, source in zip(labels, presets, strict=True):
            if label in configs or label in ("original", "gt sampling"):
                raise DemoError(
                    f"preset {source!s}: its name {label!r} is already taken (by another "
                    "preset or a column of the summary: original, gt sampling)"
                )
            configs[label] = (source, load_config(source).drcpo)
    return configs


def _preset_label(source: str | os.PathLike) -> str:
    """A preset's name in figures and the summary: the name itself, or a YAML file's stem."""
    text = os.fspath(source)
    return Path(text).stem if text.endswith((".yaml", ".yml")) else text


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
    run: _Run,
    database: GroundTruthDatabase,
    index: CandidateIndex,
    frames: list[Frame],
    seed: int,
    configs: dict[str, tuple[str | os.PathLike, DRCPOConfig]],
) -> dict[str, list[Frame]]:
    results = {
        "gt sampling": _apply(
            run, "ground-truth sampling", lambda: GroundTruthSampling(database), frames, seed, 1
        )
    }
    for label, (_, config) in configs.items():
        # One random stream for every preset: each frame's draws are the same, so the presets
        # differ only by what they do with them (and the paper's matches earlier demos).
        results[label] = _apply(
            run, f"DR.CPO {label}", lambda c=config: DRCPO(database, index, c), frames, seed, 2
        )
    return results


def _apply(
    run: _Run,
    name: str,
    make: Callable[[], Transform],
    frames: list[Frame],
    seed: int,
    stream: int,
) -> list[Frame]:
    augmented = []
    # Loads (or compiles) the kernels and touches the database: timed on its own. (The demo
    # always has a frame: KittiDataset refuses an empty split and --augment-frames is >= 1.)
    with run.stage(f"{name} first call", f"warming up {name} (its compiled kernels)"):
        transform = make()
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
        run.ms[f"  {name}: {key} per frame"] = value
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
def _figures(
    run: _Run,
    out: Path,
    database: GroundTruthDatabase,
    index: CandidateIndex,
    originals: list[Frame],
    results: dict[str, list[Frame]],
    presets: list[str],
    seed: int,
) -> dict[str, Path]:
    figures: dict[str, Path] = {}
    with run.stage("figures", f"drawing figures into {out}"):
        figures["bev"] = draw_bev(originals, results, out / "bev.png")
        preset_results = {label: results[label] for label in presets}
        figures["density"] = draw_density(originals, preset_results, out / "density.png")
        figures["side_view"] = draw_side_view(originals, preset_results, out / "side_view.png")
    with run.stage("construction figure", "drawing one object's iterative construction"):
        figures["construction"] = draw_construction(database, index, seed, out / "construction.png")
    for path in figures.values():
        run.console.print(f"    wrote {path}")
    return figures


# Summary --------------------------------------------------------------------------------------
def _inserted_per_frame(originals: list[Frame], group: list[Frame]) -> dict[str, float]:
    """Mean objects per frame of each class that the transform added."""
    counts = {c: 0 for c in CLASSES}
    for original, frame in zip(originals, group, strict=True):
        names = frame.names[inserted_mask(original, frame)]
        for c in CLASSES:
            counts[c] += int(np.sum(names == c))
    return {c: counts[c] / max(len(group), 1) for c in CLASSES}


def _print_summary(console: Console, summary: dict[str, Any], results: dict) -> None:
    groups = ["original", *results]
    table = Table(
        title=f"drcpo demo: {summary['augmented_frames']} augmented frames (means per frame)",
        caption="objects per class; (+n): those the transform added",
    )
    table.add_column("")
    for group in groups:
        heading = group if group in ("original", "gt sampling") else f"dr.cpo {group}"
        table.add_column(heading, justify="right")
    table.add_row("points per frame", *(f"{summary['points_per_frame'][g]:,.0f}" for g in groups))
    for name in CLASSES:
        cells = []
        for g in groups:
            cell = f"{summary['objects_per_frame'][g][name]:.1f}"
            if g in summary["inserted_per_frame"]:
                cell += f" (+{summary['inserted_per_frame'][g][name]:.1f})"
            cells.append(cell)
        table.add_row(f"{name}s", *cells)
    stages = {p: f"DR.CPO {p}" for p in results} | {"gt sampling": "ground-truth sampling"}
    ms = ["", *(f"{summary['ms'][f'{stages[g]} per frame']:,.1f}" for g in groups[1:])]
    table.add_row("ms per frame", *ms)
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
