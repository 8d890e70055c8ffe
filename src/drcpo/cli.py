"""Command-line interface: build-db, import-openpcdet, import-mmdet3d, info, index, augment,
synth, evaluate, demo.

Here: the ``drcpo`` app (the console script :func:`main`) and the commands that index, augment,
evaluate and run the demo; the commands that make data (build-db, import-openpcdet,
import-mmdet3d, info, synth) are in :mod:`drcpo.cli_data`.

Every command prints a summary at the end. On bad input it prints one line naming the culprit
and exits with status 1; Ctrl-C prints "interrupted" and exits with 130 (every case, and
``DRCPO_DEBUG=1`` for the traceback: :mod:`drcpo.cli_console`). Usage errors (an option out of
range) exit with 2.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.console import Console
from rich.table import Table
from typer.core import TyperGroup

from drcpo.cli_console import fail, progress_bar, safety_net
from drcpo.cli_data import (
    CLUSTER_HELP,
    VERIFY_HELP,
    build_db,
    import_mmdet3d_command,
    import_openpcdet_command,
    info,
    synth,
)

__all__ = ["app", "main"]

if TYPE_CHECKING:  # the evaluator loads its kernels: imported by its command only
    from drcpo.evaluation import KittiEvaluation


class _SafeGroup(TyperGroup):
    """The command group, every command run inside :func:`safety_net`. (The net sits here and
    not only in :func:`main`: typer itself turns Ctrl-C into a silent exit status.)"""

    def invoke(self, ctx: Any) -> Any:
        with safety_net():
            return super().invoke(ctx)


app = typer.Typer(
    cls=_SafeGroup,
    add_completion=False,
    no_args_is_help=True,
    help="DR.CPO LiDAR augmentation: ground-truth database, candidate index, augmentation.",
)


INDEX_CONFIG_HELP = (
    "YAML config file, or a preset: the index is built with its `index` section and the "
    "partition grids and mirrored classes of its drcpo.construction, so that DR.CPO with this "
    "config accepts it (default: the paper defaults). An option given explicitly wins over "
    "the config."
)


def index(
    db: Annotated[Path, typer.Argument(help="Database directory (the index goes to DB/index/).")],
    config: Annotated[str | None, typer.Option(help=INDEX_CONFIG_HELP)] = None,
    k: Annotated[
        int | None,
        typer.Option(
            "--k", min=1, help="Candidates per object (default: index.k of --config, 400)."
        ),
    ] = None,
    alpha: Annotated[
        float | None,
        typer.Option(
            min=0.0, help="Low-density partitions: below alpha x mean (default: index.alpha, 0.8)."
        ),
    ] = None,
    min_points: Annotated[
        int | None,
        typer.Option(
            min=0, help="Objects with fewer points are not indexed (default: index.min_points, 5)."
        ),
    ] = None,
    exclude_difficulty: Annotated[
        list[int] | None,
        typer.Option(
            help="Difficulty code never indexed (repeatable; -1 = unknown; "
            "default: index.exclude_difficulty, none)."
        ),
    ] = None,
    approximate_above: Annotated[
        int | None,
        typer.Option(
            help="Approximate first stage for classes with more indexed objects "
            "(default: index.approximate_above, never)."
        ),
    ] = None,
    workers: Annotated[
        int | None, typer.Option(min=1, help="With --cluster: its workers (default 2).")
    ] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing index.")] = False,
    cluster: Annotated[str | None, typer.Option(help=CLUSTER_HELP)] = None,
) -> None:
    """Index every object's K best candidates (DR.CPO pre-processing).

    With --config, the index that config's DR.CPO needs (its index section, its construction
    grids and mirrored classes); an option given explicitly wins over the config; without
    either, the paper defaults.
    """
    import dataclasses
    import time

    from drcpo.config import load_config
    from drcpo.database import GroundTruthDatabase
    from drcpo.index import INDEX_DIRNAME, INDEX_OUTPUT
    from drcpo.index_build import build_index, indexed_mask
    from drcpo.outputs import check_output

    settings = load_config(config).index
    options = {
        "k": k,
        "alpha": alpha,
        "min_points": min_points,
        "exclude_difficulty": exclude_difficulty,
        "approximate_above": approximate_above,
    }
    if workers is not None and cluster is None:
        fail("--workers needs --cluster (the index is built in one process otherwise)")
    given = {key: value for key, value in options.items() if value is not None}
    settings = dataclasses.replace(settings, **given)
    database = GroundTruthDatabase.open(db)
    check_output(db / INDEX_DIRNAME, INDEX_OUTPUT, overwrite)  # before the long build
    total = int(indexed_mask(database, settings).sum())
    done: dict[str, int] = {}
    start = time.perf_counter()
    with progress_bar("indexing objects") as bar:

        def progress(name: str, objects: int, _: int) -> None:
            done[name] = objects
            bar(sum(done.values()), total)

        if cluster is None:
            result = build_index(database, settings, progress=progress)
        else:
            from drcpo.distributed import build_index_cluster

            result = build_index_cluster(database, settings, progress, cluster, workers or 2)
        path = result.save(db, overwrite=overwrite)
    seconds = time.perf_counter() - start
    table = Table(title=f"{path} (K = {settings.k}, {seconds:.1f} s)")
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


def augment(
    kitti: Annotated[Path, typer.Option("--kitti", help="KITTI root (ImageSets/, training/).")],
    db: Annotated[Path, typer.Option("--db", help="Ground-truth database (with index/).")],
    out: Annotated[Path, typer.Option("--out", help="Output directory (KITTI layout).")],
    split: Annotated[str, typer.Option(help="Split: frames of ImageSets/<split>.txt.")] = "train",
    config: Annotated[
        str,
        typer.Option(help="YAML config file, or a preset: default, paper, nuscenes, second, ..."),
    ] = "default",
    pipeline: Annotated[
        str | None, typer.Option(help="Override the config's pipeline: drcpo or cda.")
    ] = None,
    frames: Annotated[
        int | None, typer.Option(min=0, help="Augment the first N frames (default: all).")
    ] = None,
    seed: Annotated[
        int, typer.Option(min=0, help="Random seed, >= 0 (frame i uses (seed, i)).")
    ] = 0,
    fov: Annotated[bool, typer.Option(help="Cut frames to the camera field of view first.")] = True,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing output.")] = False,
    verify: Annotated[bool, typer.Option(help=VERIFY_HELP)] = True,
    cluster: Annotated[str | None, typer.Option(help=CLUSTER_HELP)] = None,
    workers: Annotated[
        int | None,
        typer.Option(
            min=1,
            help="Processes augmenting frames, one core each (default 1); with --cluster: its "
            "workers (default 2). The output is the same bytes for any number.",
        ),
    ] = None,
) -> None:
    """Augment KITTI frames and write them in KITTI layout, with stats.jsonl per frame.

    Resumable: each frame is written atomically into a staging directory beside OUT, so the
    same command run again after an interruption augments only the frames still missing.
    """
    from drcpo.config import load_config
    from drcpo.database import GroundTruthDatabase
    from drcpo.datasets.export import augment_kitti
    from drcpo.pipeline import build_pipeline

    settings = load_config(config)
    database = GroundTruthDatabase.open(db, verify=verify)
    transform = build_pipeline(settings, database, kind=pipeline)
    run: Callable[..., dict[str, Any]] = augment_kitti
    if cluster is not None:
        from drcpo.distributed import augment_kitti_cluster, require_ray

        require_ray()
        workers = workers or 2
        run = partial(augment_kitti_cluster, cluster=cluster, workers=workers)
    elif (workers or 1) > 1:
        from drcpo.distributed.local import augment_kitti_processes

        run = partial(augment_kitti_processes, workers=workers)
    with progress_bar(f"frames of {split}") as progress:
        summary = run(
            kitti, split, transform, out, frames, seed, fov, overwrite, progress, inputs=[db]
        )
    table = Table(title=f"{out}: {summary['frames']} frames, {summary['points']} points")
    table.add_column("class")
    table.add_column("boxes", justify="right")
    for name, count in sorted(summary["boxes"].items()):
        table.add_row(name, str(count))
    table.add_row("[bold]ms per frame (median)", f"{summary['median_ms']:.1f}")
    if summary.get("resumed"):
        table.add_row("frames resumed from an earlier run", str(summary["resumed"]))
    if "cluster" in summary:
        table.add_row("cluster", f"{summary['cluster']['address']}, {workers} workers")
    elif (workers or 1) > 1:
        table.add_row("worker processes", str(workers))
    Console().print(table)


def demo(
    out: Annotated[Path, typer.Option(help="Output directory.")] = Path("drcpo_demo"),
    frames: Annotated[
        int, typer.Option(min=1, help="Synthetic frames (cached in OUT/kitti).")
    ] = 16,
    seed: Annotated[int, typer.Option(min=0, help="Random seed, >= 0.")] = 0,
    augment_frames: Annotated[int, typer.Option(min=1, help="Frames to augment.")] = 4,
) -> None:
    """Run every available stage on the built-in synthetic world; writes figures and a summary."""
    from drcpo.demo import run_demo

    run_demo(out, frames=frames, seed=seed, augment_frames=augment_frames)


def evaluate(
    gt: Annotated[Path, typer.Option("--gt", help="KITTI root (ImageSets/, training/label_2/).")],
    pred: Annotated[
        Path, typer.Option("--pred", help="Result files: one KITTI label file + score per frame.")
    ],
    split: Annotated[str, typer.Option(help="Split: frames of ImageSets/<split>.txt.")] = "val",
    classes: Annotated[
        str, typer.Option(help="Comma-separated classes (Car, Pedestrian, Cyclist, Van, ...).")
    ] = "Car,Pedestrian,Cyclist",
    loose: Annotated[
        bool, typer.Option("--loose", help="Loose BEV/3D IoU thresholds (Car 0.5, others 0.25).")
    ] = False,
    missing_empty: Annotated[
        bool,
        typer.Option("--missing-empty", help="A frame without a result file has no detections."),
    ] = False,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object on stdout.")] = False,
) -> None:
    """KITTI AP (2D, BEV, 3D; R40 and R11; easy, moderate, hard) of result files."""
    from drcpo.evaluation import evaluate_kitti_split

    names = [name.strip() for name in classes.split(",") if name.strip()]
    result = evaluate_kitti_split(
        gt, split, pred, names, "loose" if loose else "strict", missing_empty
    )
    if as_json:
        typer.echo(json.dumps(result.to_dict()))
        return
    Console().print(evaluation_table(result, f"KITTI {split}: {result.frames} frames"))


def evaluation_table(result: KittiEvaluation, title: str) -> Table:
    """One row per class and metric (2d, bev, 3d, aos): AP R40 / R11 per difficulty."""
    from drcpo.evaluation import DIFFICULTIES, METRICS

    table = Table(title=f"{title}, AP in % (R40 / R11)")
    for column in ("class", "metric", "IoU", *DIFFICULTIES):
        table.add_column(column, justify="left" if column in ("class", "metric") else "right")
    for c, name in enumerate(result.classes):
        rows = [
            (m, f"{threshold:.2f}", result.ap(m, name, "R40"), result.ap(m, name, "R11"))
            for m, threshold in zip(METRICS, result.min_overlaps[c], strict=True)
        ]
        if result.aos_r40 is not None and result.aos_r11 is not None:
            rows.append(("aos", "", result.aos_r40[c], result.aos_r11[c]))
        for i, (metric, threshold, r40, r11) in enumerate(rows):
            cells = [f"{a:.2f} / {b:.2f}" for a, b in zip(r40, r11, strict=True)]
            table.add_row(name if i == 0 else "", metric, threshold, *cells)
        table.add_section()
    return table


# The commands, in the order ``drcpo --help`` lists them.
app.command("build-db", context_settings={"allow_extra_args": True})(build_db)
app.command("import-openpcdet")(import_openpcdet_command)
app.command("import-mmdet3d")(import_mmdet3d_command)
app.command()(info)
app.command()(index)
app.command()(augment)
app.command()(synth)
app.command()(demo)
app.command()(evaluate)


def main() -> None:
    """The ``drcpo`` console script: the app, inside :func:`safety_net`."""
    with safety_net():
        app()


if __name__ == "__main__":
    main()
