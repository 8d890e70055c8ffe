"""Command-line interface: build-db, import-openpcdet, import-mmdet3d, info, index, augment,
synth, evaluate, demo.

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

__all__ = ["app", "main"]

if TYPE_CHECKING:  # the evaluator loads its kernels: imported by its command only
    from drcpo.evaluation import KittiEvaluation

VERIFY_HELP = (
    "Check the database's files against its manifest checksum (and for NaN/inf) on opening; "
    "--no-verify skips it for huge databases verified once already."
)
CLUSTER_HELP = (
    "Spread the work over a Ray cluster (pip install drcpo[ray]): 'local' starts one on this "
    "machine, else a running cluster's address (every node sees the same paths). The output is "
    "the same as without it."
)


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


def _class_list(classes: list[str] | None, extra: list[str]) -> list[str] | str:
    """``--classes`` values: repeated, comma-separated or space-separated (``Car Pedestrian``)."""
    if extra and not classes:
        fail(f"unexpected argument(s): {' '.join(extra)}")
    if not classes:
        from drcpo.database.build import DEFAULT_CLASSES

        return list(DEFAULT_CLASSES)
    names = [name for item in [*classes, *extra] for name in item.split(",") if name]
    return "all" if names == ["all"] else names


@app.command("build-db", context_settings={"allow_extra_args": True})
def build_db(
    ctx: typer.Context,
    out: Annotated[Path, typer.Option("--out", help="Database directory to create.")],
    kitti: Annotated[
        Path | None, typer.Option("--kitti", help="KITTI root (ImageSets/, training/).")
    ] = None,
    nuscenes: Annotated[
        Path | None,
        typer.Option("--nuscenes", help="nuScenes-style root (v1.0-*/ tables, samples/, sweeps/)."),
    ] = None,
    split: Annotated[str, typer.Option(help="KITTI: frames of ImageSets/<split>.txt.")] = "train",
    version: Annotated[str, typer.Option(help="nuScenes: the tables' version.")] = "v1.0-trainval",
    scenes: Annotated[
        Path | None,
        typer.Option(help="nuScenes: a file of scene names, one per line (default: all scenes)."),
    ] = None,
    sweeps: Annotated[
        int, typer.Option(min=0, help="nuScenes: earlier sweeps joined to each key sweep.")
    ] = 0,
    classes: Annotated[
        list[str] | None,
        typer.Option(
            help="Classes to keep (e.g. --classes Car Pedestrian), or 'all' for every "
            "non-DontCare class. Default: Car Pedestrian Cyclist (KITTI), the ten detection "
            "classes (nuScenes)."
        ),
    ] = None,
    workers: Annotated[
        int, typer.Option(min=1, help="Processes reading frames (with --cluster: its workers).")
    ] = 1,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing database.")] = False,
    cluster: Annotated[str | None, typer.Option(help=CLUSTER_HELP)] = None,
) -> None:
    """Build a ground-truth database from a KITTI split or a nuScenes-style data set."""
    if (kitti is None) == (nuscenes is None):
        fail("build-db: give exactly one of --kitti ROOT or --nuscenes ROOT")
    if nuscenes is not None:
        _build_db_nuscenes(
            ctx, nuscenes, out, version, scenes, sweeps, classes, workers, overwrite, cluster
        )
        return
    from drcpo.database.build import build_database

    chosen = _class_list(classes, list(ctx.args))
    with progress_bar(f"frames of {split}") as progress:
        if cluster is None:
            database = build_database(
                kitti, split, out, chosen, workers=workers, overwrite=overwrite, progress=progress
            )
        else:
            from drcpo.distributed import build_database_cluster

            database = build_database_cluster(
                kitti, split, out, chosen, overwrite, progress, cluster, workers
            )
    Console().print(class_table(database.summary(), f"{out} ({len(database)} objects)"))


def _build_db_nuscenes(
    ctx: typer.Context,
    root: Path,
    out: Path,
    version: str,
    scenes: Path | None,
    sweeps: int,
    classes: list[str] | None,
    workers: int,
    overwrite: bool,
    cluster: str | None,
) -> None:
    """``build-db --nuscenes``: the key samples of the chosen scenes, ``sweeps`` joined."""
    from drcpo.database.build import build_database_from
    from drcpo.datasets.nuscenes import NUSCENES_CLASSES, NuScenesDataset

    chosen = list(NUSCENES_CLASSES) if not classes else _class_list(classes, list(ctx.args))
    dataset = NuScenesDataset(root, version, scenes=scenes, sweeps=sweeps)
    parameters = {
        "source": "nuscenes",
        "root": str(root.resolve()),
        "version": version,
        "scenes": None if scenes is None else str(scenes),
        "sweeps": sweeps,
    }
    with progress_bar(f"samples of {version}") as progress:
        if cluster is None:
            database = build_database_from(
                dataset, out, chosen, workers, overwrite, progress, parameters=parameters
            )
        else:
            from drcpo.distributed import build_dataset_cluster

            database = build_dataset_cluster(
                dataset, out, chosen, overwrite, progress, cluster, workers, parameters
            )
    Console().print(class_table(database.summary(), f"{out} ({len(database)} objects)"))


def _import_database(
    importer: Callable[..., Any], dbinfos: Path, out: Path, root: Path | None, overwrite: bool
) -> None:
    """Run a framework database importer with a progress bar and print what it made."""
    with progress_bar("objects") as progress:
        database = importer(dbinfos, out, root=root, overwrite=overwrite, progress=progress)
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
    from drcpo.database.build import import_openpcdet

    _import_database(import_openpcdet, dbinfos, out, root, overwrite)


@app.command("import-mmdet3d")
def import_mmdet3d_command(
    dbinfos: Annotated[Path, typer.Argument(help="MMDetection3D *_dbinfos_*.pkl file.")],
    out: Annotated[Path, typer.Option("--out", help="Database directory to create.")],
    root: Annotated[
        Path | None,
        typer.Option(help="Data root the gt_database paths are relative to (default: the pkl's)."),
    ] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing database.")] = False,
) -> None:
    """Convert an MMDetection3D ground-truth database (dbinfos pickle + *_gt_database/; boxes and
    points relative to the bottom centre) to drcpo's."""
    from drcpo.database.build import import_mmdet3d

    _import_database(import_mmdet3d, dbinfos, out, root, overwrite)


@app.command()
def info(
    db: Annotated[Path, typer.Argument(help="Database directory.")],
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object on stdout.")] = False,
    verify: Annotated[bool, typer.Option(help=VERIFY_HELP)] = True,
) -> None:
    """Describe a ground-truth database: objects and points per class."""
    from drcpo.database import GroundTruthDatabase

    database = GroundTruthDatabase.open(db, verify=verify)
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


INDEX_CONFIG_HELP = (
    "YAML config file, or a preset: the index is built with its `index` section and the "
    "partition grids and mirrored classes of its drcpo.construction, so that DR.CPO with this "
    "config accepts it (default: the paper defaults). An option given explicitly wins over "
    "the config."
)


@app.command()
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


@app.command()
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


SYNTH_LAYOUTS = ("kitti", "nuscenes")


@app.command()
def synth(
    out: Annotated[Path, typer.Option("--out", help="Data root to create.")],
    frames: Annotated[
        int,
        typer.Option(min=1, help="Frames to generate (nuscenes: key samples, in whole scenes)."),
    ] = 10,
    seed: Annotated[
        int, typer.Option(min=0, help="Random seed, >= 0 (frame or scene i uses (seed, i)).")
    ] = 0,
    val_fraction: Annotated[
        float, typer.Option(min=0.0, max=0.99, help="kitti: share of frames listed in val.txt.")
    ] = 0.5,
    azimuth_step: Annotated[
        float | None,
        typer.Option(
            min=0.01, max=10.0, help="kitti: LiDAR azimuth step, degrees (default: the sensor's)."
        ),
    ] = None,
    street_angle: Annotated[
        float | None,
        typer.Option(
            min=0.0,
            max=90.0,
            help="Largest absolute yaw of the street from the sensor's x axis, degrees "
            "(default: 0.1 rad, about 5.7).",
        ),
    ] = None,
    layout: Annotated[
        str, typer.Option(help="kitti (KITTI object layout) or nuscenes (tables and sweeps).")
    ] = "kitti",
    sensor: Annotated[
        str | None,
        typer.Option(help="hdl64e or hdl32e (default: hdl64e for kitti, hdl32e for nuscenes)."),
    ] = None,
    scene_samples: Annotated[
        int, typer.Option(min=1, max=100, help="nuscenes: key samples (2 Hz) per scene.")
    ] = 5,
    version: Annotated[
        str, typer.Option(help="nuscenes: the table directory's name.")
    ] = "v1.0-trainval",
    overwrite: Annotated[bool, typer.Option(help="Replace an existing output.")] = False,
) -> None:
    """Generate a synthetic data set: a ray-cast LiDAR (HDL-64E or 32-beam HDL-32E) in
    procedural streets, in KITTI or nuScenes layout."""
    from drcpo.synth import WorldConfig, lidar_preset

    if layout not in SYNTH_LAYOUTS:
        fail(f"--layout {layout!r} is not one of {', '.join(SYNTH_LAYOUTS)}")
    sensor = sensor or ("hdl64e" if layout == "kitti" else "hdl32e")
    lidar = lidar_preset(sensor)
    world = WorldConfig() if street_angle is None else WorldConfig().with_street_angle(street_angle)
    if layout == "nuscenes":
        if azimuth_step is not None:
            fail("--azimuth-step is for --layout kitti; nuscenes uses the sensor's own")
        _synth_nuscenes(out, frames, seed, sensor, world, scene_samples, version, overwrite)
        return
    from dataclasses import replace

    from drcpo.synth import write_synthetic_kitti

    if azimuth_step is not None:
        lidar = replace(lidar, azimuth_step_deg=azimuth_step)
    with progress_bar("synthetic frames") as progress:
        summary = write_synthetic_kitti(
            out, frames, seed, world, lidar, val_fraction, overwrite, progress
        )
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


def _synth_nuscenes(
    out: Path,
    samples: int,
    seed: int,
    sensor: str,
    world: Any,
    scene_samples: int,
    version: str,
    overwrite: bool,
) -> None:
    """``drcpo synth --layout nuscenes``: ``samples`` key samples in scenes of
    ``scene_samples`` each (rounded up to whole scenes)."""
    from drcpo.synth.nuscenes import NuScenesSynthConfig, write_synthetic_nuscenes

    scenes = -(-samples // scene_samples)
    config = NuScenesSynthConfig(samples=min(samples, scene_samples), sensor=sensor, world=world)
    with progress_bar("synthetic scenes") as progress:
        summary = write_synthetic_nuscenes(out, scenes, seed, config, version, overwrite, progress)
    points = summary["points"]
    table = Table(title=f"{out}: {scenes} scenes, {summary['samples']} samples")
    table.add_column("")
    table.add_column("value", justify="right")
    table.add_row("sweeps (20 Hz)", str(summary["sweeps"]))
    spread = f"{min(points):,} / {sum(points) / len(points):,.0f} / {max(points):,}"
    table.add_row("points per key sweep (min / mean / max)", spread)
    for name, count in sorted(summary["objects"].items()):
        table.add_row(f"boxes {name} (with points)", str(count))
    table.add_row("moving objects", str(summary["moving"]))
    table.add_row("ms per sweep", f"{summary['ms_per_sweep']:.0f}")
    Console().print(table)


@app.command()
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


@app.command()
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


def main() -> None:
    """The ``drcpo`` console script: the app, inside :func:`safety_net`."""
    with safety_net():
        app()


if __name__ == "__main__":
    main()
