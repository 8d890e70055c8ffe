"""Figures: files exist, are PNGs with content, and bad input is refused."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.image import imread

from drcpo.viz import (
    BevPanel,
    ConstructionStep,
    DistanceSeries,
    bev_figure,
    construction_figure,
    density_figure,
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
