"""Command-line interface: build-db, import-openpcdet, info, index, augment, synth, demo.

Every command prints a summary at the end and exits with status 1 and a one-line message naming
the culprit on bad input (any :class:`drcpo.errors.DrcpoError`).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table
from rich.text import Text

from drcpo.errors import DrcpoError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="DR.CPO LiDAR augmentation: ground-truth database, candidate index, augmentation.",
)
console = Console(stderr=True)
VERIFY_HELP = (
    "Check the database's files against its manifest checksum (and for NaN/inf) on opening; "
    "--no-verify skips it for huge databases verified once already."
)


def fail(message: str) -> None:
    """Print an error message and exit with status 1."""
    # Not wrapped (paths stay whole for copying) and not read as markup (paths may hold "[").
    console.print(Text.assemble(("error:", "bold red"), " ", message), soft_wrap=True)
    raise typer.Exit(1)


def class_table(summary: dict[str, dict[str, int]], title: str) -> Table:
    table = Table(title=title)
    table.add_column("class")
    table.add_column("objects", justify="right")
    table.add_column("points", justify="right")
    for name, row in summary.items():
        table.add_row(name, str(row["objects"]), str(row["points"]))
    table.add_row(
        "[bold]total",
        str(sum(r["objects"] for r in summary.values())),
        str(sum(r["points"] for r in summary.values())),
    )
    return table


@contextmanager
def progress_bar(description: str) -> Iterator[Callable[[int, int], None]]:
    """A rich progress bar on stderr; yields a ``progress(done, total)`` callback."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    columns = (*Progress.get_default_columns()[:1], BarColumn(), MofNCompleteColumn())
    with Progress(*columns, TimeElapsedColumn(), console=console) as bar:
        task = bar.add_task(description, total=None)
        yield lambda done, total: bar.update(task, completed=done, total=total)


def _class_list(classes: list[str] | None, extra: list[str]) -> list[str] | str:
    """``--classes`` values: repeated, comma-separated or space-separated (``Car Pedestrian``)."""
    if extra and not classes:
        fail(f"unexpected argument(s): {' '.join(extra)}")
    if not classes:
        from drcpo.database_build import DEFAULT_CLASSES

        return list(DEFAULT_CLASSES)
    names = [name for item in [*classes, *extra] for name in item.split(",") if name]
    return "all" if names == ["all"] else names


@app.command("build-db", context_settings={"allow_extra_args": True})
def build_db(
    ctx: typer.Context,
    kitti: Annotated[Path, typer.Option("--kitti", help="KITTI root (ImageSets/, training/).")],
    out: Annotated[Path, typer.Option("--out", help="Database directory to create.")],
    split: Annotated[str, typer.Option(help="Split: frames of ImageSets/<split>.txt.")] = "train",
    classes: Annotated[
        list[str] | None,
        typer.Option(
            help="Classes to keep (e.g. --classes Car Pedestrian), or 'all' for every "
            "non-DontCare class. Default: Car Pedestrian Cyclist."
        ),
    ] = None,
    workers: Annotated[int, typer.Option(min=1, help="Processes reading frames.")] = 1,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing database.")] = False,
) -> None:
    """Build a ground-truth database from a KITTI split."""
    from drcpo.database_build import build_database

    chosen = _class_list(classes, list(ctx.args))
    try:
        with progress_bar(f"frames of {split}") as progress:
            database = build_database(
                kitti, split, out, chosen, workers=workers, overwrite=overwrite, progress=progress
            )
    except (DrcpoError, FileExistsError) as exc:
        fail(str(exc))
    Console().print(class_table(database.summary(), f"{out} ({len(database)} objects)"))


@app.command("import-openpcdet")
def import_openpcdet_command(
    dbinfos: Annotated[Path, typer.Argument(help="OpenPCDet *_dbinfos_*.pkl file.")],
    out: Annotated[Path, typer.Option("--out", help="Database directory to create.")],
    root: Annotated[
        Path | None,
        typer.Option(help="Data root the gt_database paths are relative to (default: the pkl's)."),
    ] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing database.")] = False,
) -> None:
    """Convert an OpenPCDet ground-truth database (dbinfos pickle + gt_database/) to drcpo's."""
    from drcpo.database_build import import_openpcdet

    try:
        with progress_bar("objects") as progress:
            database = import_openpcdet(
                dbinfos, out, root=root, overwrite=overwrite, progress=progress
            )
    except (DrcpoError, FileExistsError) as exc:
        fail(str(exc))
    Console().print(class_table(database.summary(), f"{out} ({len(database)} objects)"))


@app.command()
def info(
    db: Annotated[Path, typer.Argument(help="Database directory.")],
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object on stdout.")] = False,
    verify: Annotated[bool, typer.Option(help=VERIFY_HELP)] = True,
) -> None:
    """Describe a ground-truth database: objects and points per class."""
    from drcpo.database import GroundTruthDatabase

    try:
        database = GroundTruthDatabase.open(db, verify=verify)
    except DrcpoError as exc:
        fail(str(exc))
    summary = database.summary()
    if as_json:
        payload = {
            "classes": summary,
            "format_version": database.manifest.get("format_version"),
            "objects": len(database),
            "points": len(database.points),
            "checksum": database.checksum,
            "verified": database.verified,
        }
        typer.echo(json.dumps(payload))
        return
    Console().print(class_table(summary, f"{db} ({len(database)} objects)"))


@app.command()
def index(
    db: Annotated[Path, typer.Argument(help="Database directory (the index goes to DB/index/).")],
    k: Annotated[int, typer.Option("--k", min=1, help="Candidates per object.")] = 400,
    alpha: Annotated[
        float, typer.Option(min=0.0, help="Low-density partitions: below alpha x mean.")
    ] = 0.8,
    min_points: Annotated[
        int, typer.Option(min=0, help="Objects with fewer points are not indexed.")
    ] = 5,
    exclude_difficulty: Annotated[
        list[int] | None,
        typer.Option(help="Difficulty code never indexed (repeatable; -1 = unknown)."),
    ] = None,
    approximate_above: Annotated[
        int | None,
        typer.Option(help="Approximate first stage for classes with more indexed objects."),
    ] = None,
    workers: Annotated[
        int | None, typer.Option(min=1, help="Threads (default: all cores).")
    ] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing index.")] = False,
) -> None:
    """Index every object's K best candidates (DR.CPO pre-processing)."""
    import time

    from drcpo.database import GroundTruthDatabase
    from drcpo.index import INDEX_DIRNAME, IndexConfig, build_index, indexed_mask

    try:
        database = GroundTruthDatabase.open(db)
        if (db / INDEX_DIRNAME).exists() and not overwrite:
            fail(f"{db / INDEX_DIRNAME} already exists (pass --overwrite to rebuild it)")
        config = IndexConfig(
            k=k,
            alpha=alpha,
            min_points=min_points,
            exclude_difficulties=tuple(exclude_difficulty or ()),
            approximate_above=approximate_above,
            workers=workers,
        )
        total = int(indexed_mask(database, config).sum())
        done: dict[str, int] = {}
        start = time.perf_counter()
        with progress_bar("indexing objects") as bar:

            def progress(name: str, objects: int, _: int) -> None:
                done[name] = objects
                bar(sum(done.values()), total)

            result = build_index(database, config, progress=progress)
            path = result.save(db, overwrite=overwrite)
        seconds = time.perf_counter() - start
    except (DrcpoError, FileExistsError) as exc:
        fail(str(exc))
    table = Table(title=f"{path} (K = {k}, {seconds:.1f} s)")
    for column in ("class", "objects", "indexed", "mean candidates", "first stage"):
        table.add_column(column, justify="left" if column == "class" else "right")
    for name, stats in result.classes.items():
        table.add_row(
            name,
            str(stats["objects"]),
            str(stats["indexed"]),
            f"{stats['mean_candidates']:.1f}",
            stats["mode"],
        )
    Console().print(table)


@app.command()
def augment(
    kitti: Annotated[Path, typer.Option("--kitti", help="KITTI root (ImageSets/, training/).")],
    db: Annotated[Path, typer.Option("--db", help="Ground-truth database (with index/).")],
    out: Annotated[Path, typer.Option("--out", help="Output directory (KITTI layout).")],
    split: Annotated[str, typer.Option(help="Split: frames of ImageSets/<split>.txt.")] = "train",
    config: Annotated[
        str,
        typer.Option(help="YAML config file, or a preset: default, second, pointrcnn, ..."),
    ] = "default",
    pipeline: Annotated[
        str | None, typer.Option(help="Override the config's pipeline: drcpo or cda.")
    ] = None,
    frames: Annotated[
        int | None, typer.Option(min=0, help="Augment the first N frames (default: all).")
    ] = None,
    seed: Annotated[int, typer.Option(help="Random seed (frame i uses (seed, i)).")] = 0,
    fov: Annotated[bool, typer.Option(help="Cut frames to the camera field of view first.")] = True,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing output.")] = False,
    verify: Annotated[bool, typer.Option(help=VERIFY_HELP)] = True,
) -> None:
    """Augment KITTI frames and write them in KITTI layout, with stats.jsonl per frame."""
    from drcpo.config import load_config
    from drcpo.database import GroundTruthDatabase
    from drcpo.pipeline import augment_kitti, build_pipeline

    try:
        settings = load_config(config)
        database = GroundTruthDatabase.open(db, verify=verify)
        transform = build_pipeline(settings, database, kind=pipeline)
        with progress_bar(f"frames of {split}") as progress:
            summary = augment_kitti(
                kitti, split, transform, out, frames, seed, fov, overwrite, progress
            )
    except (DrcpoError, FileExistsError) as exc:
        fail(str(exc))
    table = Table(title=f"{out}: {summary['frames']} frames, {summary['points']} points")
    table.add_column("class")
    table.add_column("boxes", justify="right")
    for name, count in sorted(summary["boxes"].items()):
        table.add_row(name, str(count))
    table.add_row("[bold]ms per frame (median)", f"{summary['median_ms']:.1f}")
    Console().print(table)


@app.command()
def synth(
    out: Annotated[Path, typer.Option("--out", help="KITTI root to create.")],
    frames: Annotated[int, typer.Option(min=1, help="Frames to generate.")] = 10,
    seed: Annotated[int, typer.Option(help="Random seed (frame i uses (seed, i)).")] = 0,
    val_fraction: Annotated[
        float, typer.Option(min=0.0, max=0.99, help="Share of frames listed in val.txt.")
    ] = 0.5,
    azimuth_step: Annotated[
        float, typer.Option(min=0.01, max=10.0, help="LiDAR azimuth step, degrees.")
    ] = 0.17,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing output.")] = False,
) -> None:
    """Generate a synthetic KITTI data set: a ray-cast HDL-64E in procedural streets."""
    from drcpo.synth import LidarConfig, write_synthetic_kitti

    try:
        lidar = LidarConfig(azimuth_step_deg=azimuth_step)
        with progress_bar("synthetic frames") as progress:
            summary = write_synthetic_kitti(
                out, frames, seed, None, lidar, val_fraction, overwrite, progress
            )
    except (DrcpoError, FileExistsError) as exc:
        fail(str(exc))
    points = summary["points"]
    table = Table(title=f"{out}: {frames} frames")
    table.add_column("")
    table.add_column("value", justify="right")
    spread = f"{min(points):,} / {sum(points) / len(points):,.0f} / {max(points):,}"
    table.add_row("points per frame (min / mean / max)", spread)
    for name, count in sorted(summary["objects"].items()):
        table.add_row(f"labelled {name}", str(count))
    for level, count in sorted(summary["occlusion"].items()):
        table.add_row(f"occlusion level {level}", str(count))
    table.add_row("ms per frame", f"{summary['ms_per_frame']:.0f}")
    Console().print(table)


@app.command()
def demo(
    out: Annotated[Path, typer.Option(help="Output directory.")] = Path("drcpo_demo"),
    frames: Annotated[
        int, typer.Option(min=1, help="Synthetic frames (cached in OUT/kitti).")
    ] = 16,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    augment_frames: Annotated[int, typer.Option(min=1, help="Frames to augment.")] = 4,
) -> None:
    """Run every available stage on the built-in synthetic world; writes figures and a summary."""
    from drcpo.demo import run_demo

    try:
        run_demo(out, frames=frames, seed=seed, augment_frames=augment_frames)
    except (DrcpoError, FileExistsError) as exc:
        fail(str(exc))


def main() -> None:
    app()


if __name__ == "__main__":
    main()
