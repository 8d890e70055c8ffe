"""``sensor: auto``'s beam origin heights: the per-ring line fit against a least-squares
reference with the prior written out, a hand-made camera-view sweep whose beams sit in two
blocks of origin heights, and KITTI frames cut to the camera's view against their whole sweep
(what ``bench_realism.py --kitti`` scores the rendered points against)."""

from __future__ import annotations

import math

import numpy as np
import pytest

import drcpo.sensor_config as sensor_config
from drcpo.sensor import Sensor, hdl64e_elevations_deg
from drcpo.sensor_config import estimate_sensor

DEG = math.pi / 180.0


# --------------------------------------------------------------------------------------------
# The per-ring fit
# --------------------------------------------------------------------------------------------
def _reference_line(x: np.ndarray, y: np.ndarray, prior: float) -> tuple[float, float]:
    """``(t, h)`` of ``y = t + h x`` by plain weighted least squares over the returns (each
    weighted by one over the scatter about their own unregularised line) and one extra row,
    the prior ``h = prior`` weighted by one over ``_HEIGHT_SPREAD``."""
    design = np.stack([np.ones_like(x), x], axis=1)
    own, *_ = np.linalg.lstsq(design, y, rcond=None)
    scatter = max(float(np.mean((y - design @ own) ** 2)), sensor_config._MIN_SCATTER**2)
    rows = np.vstack([design / math.sqrt(scatter), [0.0, 1.0 / sensor_config._HEIGHT_SPREAD]])
    target = np.concatenate([y / math.sqrt(scatter), [prior / sensor_config._HEIGHT_SPREAD]])
    (t, h), *_ = np.linalg.lstsq(rows, target, rcond=None)
    return float(t), float(h)


def test_line_fit_matches_the_least_squares_reference_with_its_prior(rng):
    # Rings of (distances, angular scatter): spanning distances tightly on their line (as
    # KITTI's do), spanning a few metres, at one distance, and scattered over a narrow span.
    rings = [((5.0, 40.0), 3e-5), ((12.0, 14.0), 3e-5), ((6.0, 6.0), 3e-5), ((15.0, 18.0), 3e-3)]
    x, y, ring = [], [], []
    for r, ((near, far), noise) in enumerate(rings):
        d = rng.uniform(near, far, 300)
        x.append(1.0 / d)
        y.append(math.tan(math.radians(-3.0 * r)) + 0.2 / d + rng.normal(0.0, noise, 300))
        ring.append(np.full(300, r))
    x, y, ring = (np.concatenate(v) for v in (x, y, ring))
    inlier = rng.random(len(x)) > 0.1
    first = np.searchsorted(ring, np.arange(len(rings)))
    prior = 0.13
    t, h, determined = sensor_config._line_fit(x, y, first, inlier, prior)
    for r in range(len(rings)):
        mine = (ring == r) & inlier
        want_t, want_h = _reference_line(x[mine], y[mine], prior)
        assert t[r] == pytest.approx(want_t, rel=1e-7, abs=1e-9)
        assert h[r] == pytest.approx(want_h, rel=1e-6, abs=1e-9)
    # the tight rings keep their own height; the one at a single distance takes the prior
    np.testing.assert_allclose(h[:2], 0.2, atol=2e-3)
    assert h[2] == pytest.approx(prior, abs=1e-3)
    assert determined.tolist() == [True, True, False, False]


# --------------------------------------------------------------------------------------------
# A hand-made camera view
# --------------------------------------------------------------------------------------------
# Cars parked along the road (centre x, y; 4 x 1.8 x 1.5 m): each ring meets some of them, so
# every ring's returns span a few distances, as a real street's do.
_CARS = ((7.0, -3.0), (10.0, 3.5), (14.0, -4.0), (19.0, 2.0), (24.0, -6.0))


def _camera_view_sweep(rng: np.random.Generator) -> tuple[np.ndarray, Sensor, np.ndarray]:
    """``(points (N, 4), the sensor, each point's beam)``: an HDL-64E whose upper block of
    lasers sits 0.20-0.21 m and lower block 0.12-0.13 m above the mount (as KITTI's), seen over
    the 90 degrees in front (a camera's view): a road 1.73 m below, a wall 30 m ahead, parked
    cars; stored ring by ring from azimuth 0, as KITTI's ``.bin`` files."""
    elevations = np.radians(hdl64e_elevations_deg())
    offsets = np.concatenate([np.linspace(0.21, 0.20, 32), np.linspace(0.13, 0.12, 32)])
    step = 2.0 * math.pi / 2000
    azimuth = (np.arange(2000) + 0.3) * step
    azimuth = np.where(azimuth >= math.pi, azimuth - 2.0 * math.pi, azimuth)
    azimuth = azimuth[np.abs(azimuth) <= 45.0 * DEG]
    azimuth = np.concatenate([azimuth[azimuth >= 0], azimuth[azimuth < 0]])
    beam = np.repeat(np.arange(64), len(azimuth))
    a, e = np.tile(azimuth, 64), elevations[beam]
    origin = np.zeros((len(a), 3))
    origin[:, 2] = offsets[beam]
    ray = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        hit = np.where(ray[:, 2] < 0, (-1.73 - origin[:, 2]) / ray[:, 2], np.inf)
        hit = np.minimum(hit, np.where(ray[:, 0] > 0, 30.0 / ray[:, 0], np.inf))
        for cx, cy in _CARS:
            low = (np.array([cx - 2.0, cy - 0.9, -1.73]) - origin) / ray
            high = (np.array([cx + 2.0, cy + 0.9, -0.23]) - origin) / ray
            enter = np.nanmax(np.minimum(low, high), axis=1)
            leave = np.nanmin(np.maximum(low, high), axis=1)
            hit = np.where((enter <= leave) & (enter > 0), np.minimum(hit, enter), hit)
    hit = hit + rng.normal(0.0, 0.002, len(hit))  # range noise
    kept = np.isfinite(hit) & (hit < 120.0)
    xyz = origin[kept] + ray[kept] * hit[kept, None]
    points = np.concatenate([xyz, np.zeros((len(xyz), 1))], axis=1).astype(np.float32)
    truth = Sensor(elevations=elevations, offsets=offsets, azimuth_step=step, name="truth")
    return points, truth, beam[kept]


def test_auto_recovers_two_blocks_of_origin_heights_from_a_camera_view(rng):
    """Each ring seen over 90 degrees spans too few distances for a strong pull to the others'
    height to leave it alone (the pull used to take the lower block to the upper's)."""
    points, truth, beam = _camera_view_sweep(rng)
    sensor = estimate_sensor(points)
    assert sensor.num_beams == 64
    assert sensor.azimuth_step == pytest.approx(truth.azimuth_step, rel=1e-9)
    assert np.abs(sensor.elevations - truth.elevations).max() < 0.05 * DEG
    assert np.abs(sensor.offsets - truth.offsets).max() < 0.005
    found, _, _ = sensor.cells(points)
    np.testing.assert_array_equal(found, beam)


# --------------------------------------------------------------------------------------------
# KITTI: the camera's view against the whole sweep
# --------------------------------------------------------------------------------------------
def test_auto_on_kittis_camera_view_renders_on_the_whole_sweeps_beams(kitti_sample):
    """The sensor a realistic pipeline estimates from a KITTI frame cut to the camera's view
    casts its rays, between the road and 1.5 m over the sensor at 4-50 m, within 0.1 degree of
    the beams of the one estimated from the whole sweep (the same beam, seen from its own
    origin: ``bench_realism.py --kitti``'s measure)."""
    from drcpo.datasets.kitti import KittiDataset
    from drcpo.datasets.kitti_coordinates import fov_mask

    dataset = KittiDataset(kitti_sample, "train")
    assert len(dataset.frame_ids) == 6
    for frame_id in dataset.frame_ids:
        frame = dataset.frame(frame_id)
        keep = fov_mask(frame.points, frame.metadata["calib"], dataset.image_shape(frame_id))
        whole, view = estimate_sensor(frame.points), estimate_sensor(frame.points[keep])
        assert whole.num_beams == 64 and 40 <= view.num_beams <= 64
        distance = np.linspace(4.0, 50.0, 47)
        beam = np.repeat(np.arange(view.num_beams), len(distance))
        d = np.tile(distance, view.num_beams)
        z = d * np.tan(view.elevations[beam]) + view.offsets[beam]
        above = (z > -1.6) & (z < 1.5)  # KITTI's road lies 1.73 m below the sensor
        points = np.stack([d, np.zeros_like(d), z], axis=1)[above]
        found, _, _ = whole.cells(points)
        np.testing.assert_array_equal(found, beam[above])  # the top beams are the same
        own = np.arctan2(points[:, 2] - whole.offsets[found], points[:, 0])
        miss = np.abs(own - whole.elevations[found])
        assert miss.max() <= 0.1 * DEG, frame_id
        assert np.percentile(miss, 99) <= 0.02 * DEG, frame_id
