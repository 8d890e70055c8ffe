"""Figures: files exist, are PNGs with content, and bad input is refused."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.image import imread

from drcpo.viz import (
    BevPanel,
    ConstructionStep,
    DistanceSeries,
    ObjectView,
    bev_figure,
    construction_figure,
    density_figure,
    density_plot,
    side_view_figure,
    side_view_plot,
)


def _assert_picture(path, min_side=200):
    image = imread(path)
    assert image.shape[0] >= min_side and image.shape[1] >= min_side
    grey = image[..., :3].mean(axis=2)
    assert grey.std() > 0.02  # not blank
    assert (grey < 0.5).mean() > 0.001  # something dark was drawn
    assert not list(path.parent.glob(".*"))  # no temporary file left


def _panel(rng, inserted=False):
    points = np.column_stack(
        [rng.uniform(0, 70, 5000), rng.uniform(-40, 40, 5000), rng.uniform(-2, 1, 5000)]
    )
    boxes = np.array([[10, 2, -1, 4, 1.6, 1.5, 0.3], [20, -5, -1, 0.8, 0.6, 1.7, 1.0]])
    return BevPanel(points, boxes, ["Car", "Pedestrian"], "frame", np.array([False, inserted]))


def test_bev_figure_draws_panels_side_by_side(tmp_path, rng):
    one = bev_figure([_panel(rng)], tmp_path / "one.png")
    two = bev_figure([_panel(rng), _panel(rng, inserted=True)], tmp_path / "two.png")
    _assert_picture(one)
    _assert_picture(two)
    assert imread(two).shape[1] > 1.6 * imread(one).shape[1]


def test_bev_figure_needs_a_panel(tmp_path):
    with pytest.raises(ValueError, match="panel"):
        bev_figure([], tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def test_construction_figure_has_one_panel_per_step(tmp_path, rng):
    dims = np.array([4.0, 1.6, 1.5])
    steps = []
    for iteration in range(3):
        points = rng.uniform(-0.5, 0.5, (200 * (iteration + 1), 3)) * dims
        added = np.arange(len(points)) >= 200
        above = rng.random((10, 4, 3)) < 0.3 * (iteration + 1)
        steps.append(
            ConstructionStep(points, added, dims, above, np.ones((10, 4, 3), bool), 0.5, iteration)
        )
    path = construction_figure(steps, tmp_path / "construction.png", "a car")
    _assert_picture(path)
    single = construction_figure(steps[:1], tmp_path / "single.png")
    assert imread(path).shape[1] > 2 * imread(single).shape[1]


def test_density_figure(tmp_path, rng):
    distance = rng.uniform(5, 70, 50)
    series = [
        DistanceSeries("real", distance, 1e5 / distance**2, "#1f77b4"),
        DistanceSeries("inserted", distance, np.zeros(50), "#ff7f0e", "D"),  # zero counts plot
    ]
    _assert_picture(density_figure(series, tmp_path / "density.png"))


def _scatter_points(ax) -> list[int]:
    """Number of points of each scatter series drawn in ``ax``, in drawing order."""
    return [len(c.get_offsets()) for c in ax.collections]


def _median_lines(ax) -> list[np.ndarray]:
    """``(k, 2)`` vertices of each line drawn in ``ax`` (the medians), in drawing order."""
    return [np.asarray(line.get_xydata()) for line in ax.get_lines()]


def test_density_plot_has_a_panel_per_class_with_each_series_objects(tmp_path, rng):
    names = np.array(["Car"] * 6 + ["Pedestrian"] * 3 + ["Truck"])
    distance = np.array([5.0, 7.0, 12.0, 14.0, 16.0, 33.0, 5.0, 6.0, 40.0, 20.0])
    points = np.array([800, 600, 300, 200, 100, 50, 40, 30, 5, 70])
    series = [
        DistanceSeries("real", distance, points, "#1f77b4", "o", names),
        DistanceSeries("inserted", distance[:7] + 1.0, points[:7] // 2, "#ff7f0e", "D", names[:7]),
    ]
    fig = density_plot(series, classes=("Car", "Pedestrian", "Cyclist"))
    axes = fig.axes
    assert [ax.get_title() for ax in axes] == ["Car", "Pedestrian", "Cyclist"]
    assert _scatter_points(axes[0]) == [6, 6]
    assert _scatter_points(axes[1]) == [3, 1]
    assert _scatter_points(axes[2]) == [0, 0]  # no Cyclist: an empty panel, not an error
    assert [t.get_text() for t in axes[1].get_legend().get_texts()] == ["real (3)", "inserted (1)"]
    # medians per 10 m bin with >= 2 objects: Cars of "real" at 0-10 (5, 7) and 10-20 m
    real, inserted = _median_lines(axes[0])
    np.testing.assert_allclose(real, [[5.0, 700.0], [15.0, 200.0]])
    # "inserted" Cars at 6, 8 | 13, 15, 17 | 34 (one: no median)
    np.testing.assert_allclose(inserted, [[5.0, 350.0], [15.0, 100.0]])
    assert _median_lines(axes[1])[0].tolist() == [[5.0, 35.0]]  # 40 m: alone in its bin
    assert _median_lines(axes[2]) == []
    # without classes: one panel of everything (the Truck too)
    single = density_plot(series)
    assert len(single.axes) == 1 and _scatter_points(single.axes[0]) == [10, 7]
    path = density_figure(series, tmp_path / "density.png", classes=("Car", "Pedestrian"))
    _assert_picture(path)
    assert (
        imread(path).shape[1] > 1.6 * imread(density_figure(series, tmp_path / "one.png")).shape[1]
    )


def test_density_plot_refuses_per_class_panels_without_names(tmp_path):
    series = [DistanceSeries("unnamed", np.array([5.0]), np.array([10]))]
    with pytest.raises(ValueError, match="unnamed"):
        density_figure(series, tmp_path / "x.png", classes=("Car",))
    with pytest.raises(ValueError, match="bin_width"):
        density_plot(series, bin_width=0.0)
    assert not (tmp_path / "x.png").exists()


def _scan_lines(box, elevations_deg, columns_deg, intensity=True):
    """Points on a box's face towards the origin where the rays at the given elevations and
    azimuths (degrees) meet it: a hand-made scanned object."""
    elevation, azimuth = np.meshgrid(np.radians(elevations_deg), np.radians(columns_deg))
    face = box[0] - box[3] / 2  # the box is axis-aligned, on the x axis
    distance = face / np.cos(azimuth)
    x = face * np.ones_like(distance)
    y = face * np.tan(azimuth)
    z = distance * np.tan(elevation)
    points = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    inside = (np.abs(points[:, 1] - box[1]) <= box[4] / 2) & (
        np.abs(points[:, 2] - box[2]) <= box[5] / 2
    )
    points = points[inside]
    if intensity:
        points = np.column_stack([points, np.linspace(0, 1, len(points))])
    return points


def test_side_view_plot_draws_two_views_per_object_with_the_beams(tmp_path):
    beams = np.linspace(2.0, -24.9, 64)
    near = np.array([10.0, 0.0, -1.0, 4.0, 1.8, 1.5, 0.0])
    far = np.array([25.0, 0.0, -1.0, 4.0, 1.8, 1.5, 0.0])
    columns = np.arange(-10.0, 10.0, 0.17)
    views = [
        ObjectView(_scan_lines(near, beams, columns), near, "real"),
        ObjectView(_scan_lines(far, beams, columns, intensity=False), far, "inserted"),
        ObjectView(np.zeros((0, 4)), far, "empty"),
    ]
    fig = side_view_plot(views, beams, title="a car")
    # 2 rows x 3 columns of views and the intensity colour bar
    assert len(fig.axes) == 7
    tops, sides = fig.axes[0:3], fig.axes[3:6]  # row by row
    for top, side, view in zip(tops, sides, views, strict=True):
        assert _scatter_points(top) == _scatter_points(side) == [len(view.points)]
        assert top.get_title().startswith(view.title)
    assert tops[0].get_title().endswith(f"{len(views[0].points)} points at 10.0 m")
    # every point lies on a drawn beam line; only the beams within the box's rows are drawn
    for top, view in zip(tops[:2], views[:2], strict=True):
        lines = np.array([line.get_ydata()[0] for line in top.get_lines()])
        elevation = np.degrees(np.arctan2(view.points[:, 2], np.hypot(*view.points[:, :2].T)))
        assert np.abs(elevation[:, None] - lines[None]).min(axis=1).max() < 1e-9
        low, high = top.get_ylim()
        assert np.all((lines >= low) & (lines <= high))
        assert len(lines) == np.sum((beams >= low) & (beams <= high))
        assert len(np.unique(np.round(elevation, 6))) <= len(lines)
    assert len(tops[0].get_lines()) > len(tops[1].get_lines())  # the far box spans fewer beams
    # the side view: heights above the box bottom, the range across the box
    heights = sides[0].collections[0].get_offsets()[:, 1]
    assert heights.min() >= 0.0 and heights.max() <= near[5]
    path = side_view_figure(views, tmp_path / "side.png", beams, title="a car")
    _assert_picture(path)
    without = side_view_plot(views[1:2])  # no intensity, no beams: no colour bar, no lines
    assert len(without.axes) == 2 and without.axes[0].get_lines() == []


def test_side_view_plot_refuses_bad_input(tmp_path):
    with pytest.raises(ValueError, match="at least one"):
        side_view_figure([], tmp_path / "x.png")
    box = np.array([10.0, 0.0, -1.0, 4.0, 1.8, 1.5, 0.0])
    with pytest.raises(ValueError, match="'flat'.*\\(n, 3\\+\\)"):
        side_view_plot([ObjectView(np.zeros((5, 2)), box, "flat")])
    assert not (tmp_path / "x.png").exists()
