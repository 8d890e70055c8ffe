"""Figures (PNG, matplotlib's Agg canvas; no display and no global pyplot state).

* :func:`bev_figure`: bird's-eye views of frames side by side, boxes coloured by class, inserted
  objects highlighted, the sensor at the origin.
* :func:`construction_figure`: one object's iterative construction, one panel per iteration,
  partitions shaded by how many of their cells are above the density threshold.
* :func:`density_figure`: points per object versus distance, real objects against inserted ones.

Every function writes its file atomically (temporary file, then rename) and returns the path.
"""

from __future__ import annotations

import io
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Polygon, Rectangle

from drcpo.geometry import bev_corners
from drcpo.outputs import atomic_write_bytes

__all__ = [
    "CLASS_COLOURS",
    "INSERTED_COLOUR",
    "OTHER_COLOUR",
    "BevPanel",
    "ConstructionStep",
    "DistanceSeries",
    "bev_figure",
    "construction_figure",
    "density_figure",
]

CLASS_COLOURS: dict[str, str] = {
    "Car": "#1f77b4",
    "Pedestrian": "#d62728",
    "Cyclist": "#2ca02c",
}
OTHER_COLOUR = "#7f7f7f"
INSERTED_COLOUR = "#ff7f0e"


@dataclass(frozen=True, eq=False)
class BevPanel:
    """One bird's-eye view: points ``(N, 3+)``, boxes ``(M, 7)``, names ``(M,)``, which boxes were
    inserted ``bool (M,)`` (default none), and a title."""

    points: np.ndarray
    boxes: np.ndarray
    names: Sequence[str]
    title: str = ""
    inserted: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class ConstructionStep:
    """One iteration of a construction in canonical pose.

    Attributes:
        points: ``(n, 3+)`` the object's points after this iteration.
        added: ``bool (n,)`` points that did not belong to the source object.
        dims: ``(3,)`` the box size.
        above: ``bool (nx, ny, nz)`` partitions above the density threshold.
        fillable: ``bool (nx, ny, nz)`` partitions that can hold points at all.
        coverage: the fraction reported by the construction.
        iteration: iteration number (0 = the source object).
    """

    points: np.ndarray
    added: np.ndarray
    dims: np.ndarray
    above: np.ndarray
    fillable: np.ndarray
    coverage: float
    iteration: int


@dataclass(frozen=True, eq=False)
class DistanceSeries:
    """Points per object against distance for one group of objects (a scatter series)."""

    label: str
    distance: np.ndarray
    points: np.ndarray
    colour: str = OTHER_COLOUR
    marker: str = "o"


def _save(fig: Figure, path: str | os.PathLike, dpi: int) -> Path:
    FigureCanvasAgg(fig)
    buffer = io.BytesIO()
    fig.savefig(buffer, dpi=dpi, format="png")
    return atomic_write_bytes(path, buffer.getvalue())


def _draw_bev(ax, panel: BevPanel, extent: tuple[float, float, float, float]) -> None:
    x_lo, x_hi, y_lo, y_hi = extent
    points = np.asarray(panel.points)
    keep = (points[:, 0] >= x_lo) & (points[:, 0] <= x_hi)
    keep &= (points[:, 1] >= y_lo) & (points[:, 1] <= y_hi)
    shown = points[keep]
    # Points well above the ground (objects, walls, poles) are drawn darker and larger than the
    # ground rings; the ground level is a low percentile of the heights shown.
    ground = np.percentile(shown[:, 2], 5) if len(shown) else 0.0
    raised = shown[:, 2] > ground + 0.35
    for mask, size, colour in ((~raised, 0.2, "#b0b0b0"), (raised, 0.9, "#303030")):
        ax.scatter(shown[mask, 1], shown[mask, 0], s=size, c=colour, linewidths=0, rasterized=True)
    boxes = np.asarray(panel.boxes, dtype=np.float64).reshape(-1, 7)
    inserted = (
        np.zeros(len(boxes), bool) if panel.inserted is None else np.asarray(panel.inserted, bool)
    )
    for corners, name, new in zip(bev_corners(boxes), panel.names, inserted, strict=True):
        colour = CLASS_COLOURS.get(str(name), OTHER_COLOUR)
        ax.add_patch(
            Polygon(
                corners[:, ::-1],
                closed=True,
                fill=False,
                edgecolor=colour,
                linewidth=1.0,
            )
        )
        if new:
            ax.add_patch(
                Polygon(corners[:, ::-1], closed=True, facecolor=INSERTED_COLOUR, alpha=0.45)
            )
    ax.plot([0], [0], marker="^", color="black", markersize=7, zorder=5)
    ax.set_xlim(y_hi, y_lo)  # y points left in the LiDAR frame, so it grows to the left
    ax.set_ylim(x_lo, x_hi)
    ax.set_aspect("equal")
    ax.set_xlabel("y (m)")
    ax.set_ylabel("x (m)")
    counts = {n: int(np.sum(np.asarray(panel.names) == n)) for n in CLASS_COLOURS}
    subtitle = ", ".join(f"{n} {c}" for n, c in counts.items() if c)
    ax.set_title(
        f"{panel.title}\n{len(points):,} points; {subtitle} ({int(inserted.sum())} inserted)",
        fontsize=9,
    )


def bev_figure(
    panels: Sequence[BevPanel],
    path: str | os.PathLike,
    extent: tuple[float, float, float, float] = (-5.0, 72.0, -40.0, 40.0),
    dpi: int = 110,
) -> Path:
    """Bird's-eye views side by side; ``extent`` is ``(x_min, x_max, y_min, y_max)`` metres."""
    if not panels:
        raise ValueError("bev_figure needs at least one panel")
    fig = Figure(figsize=(4.6 * len(panels), 5.6), layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, panel in zip(axes, panels, strict=True):
        _draw_bev(ax, panel, extent)
    handles = [
        Rectangle((0, 0), 1, 1, fill=False, edgecolor=c, label=n) for n, c in CLASS_COLOURS.items()
    ]
    handles.append(Rectangle((0, 0), 1, 1, facecolor=INSERTED_COLOUR, alpha=0.45, label="inserted"))
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=8)
    return _save(fig, path, dpi)


def construction_figure(
    steps: Sequence[ConstructionStep], path: str | os.PathLike, title: str = "", dpi: int = 110
) -> Path:
    """One panel per construction iteration: the object from above, partitions shaded by the
    fraction of their cells (over height) above the density threshold."""
    if not steps:
        raise ValueError("construction_figure needs at least one step")
    columns = min(len(steps), 4)
    rows = int(np.ceil(len(steps) / columns))
    dims = np.asarray(steps[0].dims, dtype=np.float64)
    aspect = dims[1] / dims[0]
    fig = Figure(figsize=(3.6 * columns, 3.6 * aspect * rows + 1.0), layout="constrained")
    axes = fig.subplots(rows, columns, squeeze=False).ravel()
    for ax in axes[len(steps) :]:
        ax.set_axis_off()
    for ax, step in zip(axes, steps, strict=False):
        _draw_construction(ax, step)
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path, dpi)


def _draw_construction(ax, step: ConstructionStep) -> None:
    dims = np.asarray(step.dims, dtype=np.float64)
    nx, ny, _ = step.above.shape
    share = step.above.sum(axis=2) / np.maximum(step.fillable.sum(axis=2), 1)
    x_edges = np.linspace(-dims[0] / 2, dims[0] / 2, nx + 1)
    y_edges = np.linspace(-dims[1] / 2, dims[1] / 2, ny + 1)
    ax.pcolormesh(x_edges, y_edges, share.T, cmap="Greens", vmin=0, vmax=1.4, alpha=0.8)
    points = np.asarray(step.points)
    added = np.asarray(step.added, bool)
    ax.scatter(points[~added, 0], points[~added, 1], s=1.5, c="#1f77b4", linewidths=0)
    ax.scatter(points[added, 0], points[added, 1], s=1.5, c=INSERTED_COLOUR, linewidths=0)
    for x in x_edges:
        ax.axvline(x, color="white", linewidth=0.5)
    for y in y_edges:
        ax.axhline(y, color="white", linewidth=0.5)
    pad = 0.15
    ax.set_xlim(-dims[0] / 2 - pad, dims[0] / 2 + pad)
    ax.set_ylim(-dims[1] / 2 - pad, dims[1] / 2 + pad)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    label = "source (mirrored)" if step.iteration == 0 else f"iteration {step.iteration}"
    ax.set_title(
        f"{label}: {len(points)} pts ({int(added.sum())} added)\n"
        f"partitions above threshold {step.coverage:.0%}",
        fontsize=8,
    )


def density_figure(
    series: Sequence[DistanceSeries], path: str | os.PathLike, dpi: int = 110
) -> Path:
    """Points per object (log scale) against distance from the sensor, one series per group."""
    fig = Figure(figsize=(6.4, 4.2), layout="constrained")
    ax = fig.subplots()
    for s in series:
        points = np.asarray(s.points, dtype=np.float64)
        ax.scatter(
            np.asarray(s.distance),
            np.maximum(points, 0.8),
            s=14,
            c=s.colour,
            marker=s.marker,
            alpha=0.75,
            linewidths=0,
            label=f"{s.label} ({len(points)})",
        )
    ax.set_yscale("log")
    ax.set_xlabel("distance from the sensor (m)")
    ax.set_ylabel("points in the box")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path, dpi)
