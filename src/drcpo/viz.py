"""Figures (PNG, matplotlib's Agg canvas; no display and no global pyplot state).

* :func:`bev_figure`: bird's-eye views of frames side by side, boxes coloured by class, inserted
  objects highlighted, the sensor at the origin.
* :func:`construction_figure`: one object's iterative construction, one panel per iteration,
  partitions shaded by how many of their cells are above the density threshold.
* :func:`density_figure`: points per object versus distance, real objects against inserted ones,
  in one panel or one panel per class, with each group's median per distance bin.
* :func:`side_view_figure`: objects' points as the sensor saw them (azimuth against elevation,
  with the beams' elevations drawn, so scan lines show) and from the side (range against height).

Every ``*_figure`` function writes its file atomically (temporary file, then rename) and returns
the path; :func:`density_plot` and :func:`side_view_plot` return the figure they draw.
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

from drcpo.geometry import bev_corners, box_corners
from drcpo.outputs import atomic_write_bytes

__all__ = [
    "CLASS_COLOURS",
    "INSERTED_COLOUR",
    "OTHER_COLOUR",
    "BevPanel",
    "ConstructionStep",
    "DistanceSeries",
    "ObjectView",
    "bev_figure",
    "construction_figure",
    "density_figure",
    "density_plot",
    "side_view_figure",
    "side_view_plot",
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
    """Points per object against distance for one group of objects (a scatter series).

    Attributes:
        label: the group's name in the legend.
        distance: ``(n,)`` each object's distance from the sensor, metres.
        points: ``(n,)`` each object's number of points.
        colour, marker: matplotlib colour and marker of the series.
        names: ``(n,)`` each object's class (needed when the figure has a panel per class).
    """

    label: str
    distance: np.ndarray
    points: np.ndarray
    colour: str = OTHER_COLOUR
    marker: str = "o"
    names: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class ObjectView:
    """One object for :func:`side_view_figure`: its points ``(n, 3+)`` in the LiDAR frame
    (column 3, when present, is the intensity, 0 to 1), its box ``(7,)`` and a title."""

    points: np.ndarray
    box: np.ndarray
    title: str = ""


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


def density_plot(
    series: Sequence[DistanceSeries],
    classes: Sequence[str] | None = None,
    bin_width: float = 10.0,
) -> Figure:
    """Points per object (log scale) against distance from the sensor, one scatter series per
    group and, as a line, each group's median per ``bin_width`` metre bin (bins holding at
    least two of its objects). One panel of every object when ``classes`` is ``None``, else one
    panel per class of ``classes`` (each series' objects of that class, by its ``names``)."""
    if bin_width <= 0:
        raise ValueError(f"density_plot: bin_width must be positive, got {bin_width}")
    if classes is not None and any(s.names is None for s in series):
        missing = [s.label for s in series if s.names is None]
        raise ValueError(f"density_plot: per-class panels need names for series {missing}")
    panels = [None] if classes is None else list(classes)
    if not panels:
        raise ValueError("density_plot needs at least one class")
    fig = Figure(figsize=(1.0 + 4.6 * len(panels), 4.4), layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False, sharey=True)[0]
    for ax, name in zip(axes, panels, strict=True):
        for s in series:
            distance = np.asarray(s.distance, dtype=np.float64).reshape(-1)
            points = np.asarray(s.points, dtype=np.float64).reshape(-1)
            if name is not None:
                chosen = np.asarray(s.names).reshape(-1) == name
                distance, points = distance[chosen], points[chosen]
            _draw_density(ax, s, distance, points, bin_width)
        ax.set_yscale("log")
        ax.set_xlabel("distance from the sensor (m)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
        if name is not None:
            ax.set_title(name, fontsize=10)
    axes[0].set_ylabel("points in the box")
    return fig


def _draw_density(ax, s: DistanceSeries, distance, points, bin_width: float) -> None:
    shown = np.maximum(points, 0.8)  # an empty box still shows, at the foot of the log axis
    ax.scatter(
        distance,
        shown,
        s=14,
        c=s.colour,
        marker=s.marker,
        alpha=0.6,
        linewidths=0,
        label=f"{s.label} ({len(points)})",
    )
    bins = np.floor(distance / bin_width).astype(np.int64)
    centres, medians = [], []
    for b in np.unique(bins):
        inside = bins == b
        if inside.sum() >= 2:
            centres.append((b + 0.5) * bin_width)
            medians.append(np.median(shown[inside]))
    if centres:
        ax.plot(centres, medians, color=s.colour, linewidth=1.6, alpha=0.9)


def density_figure(
    series: Sequence[DistanceSeries],
    path: str | os.PathLike,
    dpi: int = 110,
    classes: Sequence[str] | None = None,
    bin_width: float = 10.0,
) -> Path:
    """:func:`density_plot` written to ``path`` (PNG)."""
    return _save(density_plot(series, classes, bin_width), path, dpi)


def side_view_plot(
    views: Sequence[ObjectView],
    elevations_deg: np.ndarray | None = None,
    mount: Sequence[float] = (0.0, 0.0, 0.0),
    title: str = "",
) -> Figure:
    """Each object in a column, two views of its points, both seen across the line of sight
    from ``mount`` (the sensor, metres in the LiDAR frame) to its box centre:

    * top, as the sensor saw it: azimuth (degrees, from the box centre's; left is left as seen
      from the sensor) against elevation (degrees above the horizontal at ``mount``); the beams'
      ``elevations_deg`` are drawn as faint lines, so points on scan lines lie on them;
    * bottom, from the side: range along the line of sight (metres) against height above the
      box's bottom (metres).

    Points are coloured by intensity (column 3) when they have one; the box outline is drawn.
    """
    if not views:
        raise ValueError("side_view_plot needs at least one object")
    mount = np.asarray(mount, dtype=np.float64).reshape(3)
    fig = Figure(figsize=(3.8 * len(views), 6.4), layout="constrained")
    axes = fig.subplots(2, len(views), squeeze=False)
    shown = None
    for column, view in enumerate(views):
        top, side = axes[0, column], axes[1, column]
        shown = _draw_side_view(top, side, view, mount, elevations_deg) or shown
    if shown is not None:
        fig.colorbar(shown, ax=axes[:, -1].tolist(), label="intensity", shrink=0.6)
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def _draw_side_view(top, side, view: ObjectView, mount, elevations_deg):
    """Draws one object's two views; returns the intensity-coloured scatter, if any."""
    box = np.asarray(view.box, dtype=np.float64).reshape(7)
    points = np.asarray(view.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(
            f"side_view_plot: {view.title!r} points must be (n, 3+), got {points.shape}"
        )
    # Angles about the line of sight to the box centre, so every object is seen head-on.
    centre = box[:2] - mount[:2]
    heading = np.arctan2(centre[1], centre[0])
    cos, sin = np.cos(heading), np.sin(heading)
    bottom = box[2] - box[5] / 2

    def project(xyz: np.ndarray) -> tuple[np.ndarray, ...]:
        dx, dy, dz = (xyz[:, k] - mount[k] for k in range(3))
        along, across = dx * cos + dy * sin, -dx * sin + dy * cos
        azimuth = np.degrees(np.arctan2(across, along))
        elevation = np.degrees(np.arctan2(dz, np.hypot(dx, dy)))
        return azimuth, elevation, along, xyz[:, 2] - bottom

    corners = box_corners(box[None])[0]
    c_az, c_el, c_along, _ = project(corners)
    p_az, p_el, p_along, p_up = project(points[:, :3])
    colour: dict = {"c": "#303030"}
    if points.shape[1] > 3:
        colour = {"c": points[:, 3], "cmap": "viridis", "vmin": 0.0, "vmax": 1.0}
    scatter = top.scatter(p_az, p_el, s=3, linewidths=0, **colour)
    side.scatter(p_along, p_up, s=3, linewidths=0, **colour)
    az_pad = 0.08 * max(np.ptp(c_az), 0.5)
    el_pad = 0.08 * max(np.ptp(c_el), 0.5)
    el_lo, el_hi = c_el.min() - el_pad, c_el.max() + el_pad
    if elevations_deg is not None:
        beams = np.asarray(elevations_deg, dtype=np.float64).reshape(-1)
        for elevation in beams[(beams >= el_lo) & (beams <= el_hi)]:
            top.axhline(elevation, color="#c8c8c8", linewidth=0.5, zorder=0)
    top.add_patch(
        Rectangle(
            (c_az.min(), c_el.min()), np.ptp(c_az), np.ptp(c_el), fill=False, edgecolor="#d62728"
        )
    )
    top.set_xlim(c_az.max() + az_pad, c_az.min() - az_pad)  # azimuth grows to the left
    top.set_ylim(el_lo, el_hi)
    top.set_xlabel("azimuth from the box centre (deg)")
    top.set_ylabel("elevation (deg)")
    side.add_patch(
        Rectangle((c_along.min(), 0.0), np.ptp(c_along), box[5], fill=False, edgecolor="#d62728")
    )
    side.set_aspect("equal")
    side.set_xlim(c_along.min() - 0.3, c_along.max() + 0.3)
    side.set_ylim(-0.3, box[5] + 0.3)
    side.set_xlabel("range along the line of sight (m)")
    side.set_ylabel("height above the box bottom (m)")
    distance = float(np.hypot(*centre))
    top.set_title(f"{view.title}\n{len(points)} points at {distance:.1f} m", fontsize=9)
    return scatter if points.shape[1] > 3 else None


def side_view_figure(
    views: Sequence[ObjectView],
    path: str | os.PathLike,
    elevations_deg: np.ndarray | None = None,
    mount: Sequence[float] = (0.0, 0.0, 0.0),
    title: str = "",
    dpi: int = 110,
) -> Path:
    """:func:`side_view_plot` written to ``path`` (PNG)."""
    return _save(side_view_plot(views, elevations_deg, mount, title), path, dpi)
