"""Command-line interface: build-db, import-openpcdet, info, index, augment, synth, demo.

Every command prints a summary at the end and exits with status 1 and a one-line message naming
the culprit on bad input (any :class:`drcpo.errors.DrcpoError`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from drcpo.errors import DrcpoError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="DR.CPO LiDAR augmentation: ground-truth database, candidate index, augmentation.",
)
console = Console(stderr=True)


def fail(message: str) -> None:
    """Print an error message and exit with status 1."""
    console.print(f"[bold red]error:[/] {message}")
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


@app.command()
def info(
    db: Annotated[Path, typer.Argument(help="Database directory.")],
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object on stdout.")] = False,
) -> None:
    """Describe a ground-truth database: objects and points per class."""
    from drcpo.database import GroundTruthDatabase

    try:
        database = GroundTruthDatabase.open(db)
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
        }
        typer.echo(json.dumps(payload))
        return
    Console().print(class_table(summary, f"{db} ({len(database)} objects)"))


@app.command()
def demo(
    out: Annotated[Path, typer.Option(help="Output directory.")] = Path("drcpo_demo"),
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
) -> None:
    """Run every available stage on built-in data and print what it made."""
    from drcpo.demo import run_demo

    database = run_demo(out, seed=seed)
    Console().print(class_table(database.summary(), f"demo database {database.path}"))


def main() -> None:
    app()


if __name__ == "__main__":
    main()
