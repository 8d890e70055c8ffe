"""The ``drcpo`` commands that make data: ground-truth databases (``build-db`` from KITTI or a
nuScenes-style data set, ``import-openpcdet``, ``import-mmdet3d``; ``info`` describes one) and
synthetic data sets (``synth``, in KITTI or nuScenes layout).

Plain functions whose parameters are their options; :mod:`drcpo.cli` registers them on its
``app``, in the order ``drcpo --help`` lists them.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.table import Table

from drcpo.cli_console import fail, progress_bar

__all__ = [
    "CLUSTER_HELP",
    "VERIFY_HELP",
    "build_db",
    "class_table",
    "import_mmdet3d_command",
    "import_openpcdet_command",
    "info",
    "synth",
]

#: Help of the options --verify and --cluster, which cli.py's augment and index take too.
VERIFY_HELP = (
    "Check the database's files against its manifest checksum (and for NaN/inf) on opening; "
    "--no-verify skips it for huge databases verified once already."
)
CLUSTER_HELP = (
    "Spread the work over a Ray cluster (pip install drcpo[ray]): 'local' starts one on this "
    "machine, else a running cluster's address (every node sees the same paths). The output is "
    "the same as without it."
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
    from drcpo.database.dbinfos import import_openpcdet

    _import_database(import_openpcdet, dbinfos, out, root, overwrite)


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
    from drcpo.database.dbinfos import import_mmdet3d

    _import_database(import_mmdet3d, dbinfos, out, root, overwrite)


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


SYNTH_LAYOUTS = ("kitti", "nuscenes")


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
