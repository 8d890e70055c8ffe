"""The config section ``drcpo.sensor`` and its ``auto`` model: which LiDAR recorded the frames,
and how to tell its beams and azimuth step from a frame's own points
(:func:`estimate_sensor`; KITTI frames carry no ring index). The model itself is
:class:`drcpo.sensor.Sensor`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from drcpo.config_fields import Checked, spec
from drcpo.errors import ConfigError, DataError
from drcpo.sensor import SENSOR_PRESETS, Sensor, sensor_preset

__all__ = ["SENSOR_MODELS", "SensorConfig", "estimate_sensor"]


# --------------------------------------------------------------------------------------------
# sensor: auto — the beams and azimuth step of one frame, from its own points
# --------------------------------------------------------------------------------------------
_MIN_POINTS = 200  # fewer usable points than this: nothing to estimate a sensor from
_SAMPLE = 16384  # the fits use every k-th point, about this many (scan order kept)
_NEAR = 2.0  # metres: nearer returns (the car itself, mixed pixels) are left out of the fits
_FAR = 5.0  # metres: where a return's plain elevation is close to its beam's
_RING_DROP = math.radians(10.0)  # a fall of the sweep's azimuth this large starts a new ring
_MIN_RING = 4  # a ring is at least this many sampled points (fewer: jitter at its start)
_START_BINS = 360  # resolution of the sweep's start azimuth (1 degree)
_ON_BEAM = math.radians(0.1)  # a return this near its ring's fitted line lies on the beam
_PERFECT_FIT = 0.999  # share of the returns on their beams that needs no other ring cut tried
# A beam's origin height is drawn to the other beams' as a Gaussian prior of this spread
# (metres; KITTI's two laser blocks sit 0.20 and 0.12-0.13 m up), weighed against its
# own returns' scatter about their line: it decides only where those leave it open.
_HEIGHT_SPREAD = 0.05
_MIN_SCATTER = 1e-5  # radians: the least scatter of a ring's returns about its line
_MAX_STEP = math.radians(2.0)  # azimuth steps beyond this are gaps, not firings
_SAME_FIT = 0.002  # share of returns on their beams that origin heights must add to be kept
_MAX_BEAMS = 128  # more beams than any spinning LiDAR has: not a sweep
_MIN_GAP = math.radians(0.05)  # beams nearer than this: not a sweep
_PEAK_BIN = math.radians(0.01)  # bin of the elevation histogram (points in no scan order)


def estimate_sensor(points: np.ndarray, base: Sensor | None = None) -> Sensor:
    """The sensor that recorded ``points`` (``sensor: auto``): its beams' elevations and origin
    heights, its azimuth step and phase, estimated from the frame's own points.

    A frame stored ring by ring (KITTI's ``.bin`` files and the synthetic world's frames: each
    ring one turn of the sweep, in azimuth order) gives its rings by the order of its points: a
    ring ends where the sweep's azimuth comes back to where the rings start, which is where the
    points' elevation jumps from ring to ring. Each ring's elevation ``e`` and origin height
    ``h`` are fitted robustly to ``z = d tan(e) + h`` over its returns (``d`` the horizontal
    distance), since a real return's plain elevation drifts with range when the lasers sit at
    different heights. When the order holds no plausible ring structure (shuffled points,
    merged clouds), the beams are the peaks of the elevation histogram of the returns beyond
    2 m instead (origin heights 0). The azimuth step is the typical azimuth difference of
    successive firings of a beam, the phase their mean offset from the column grid.

    Args:
        points: ``(N, 3+)`` x, y, z (metres, LiDAR frame) and any features, as recorded.
        base: where the range noise, dropout, range limits and mount come from (default: the
            ``hdl64e`` preset); the points are seen from its mount.

    Returns:
        A :class:`Sensor` named ``"auto"``, beams top first.

    Raises:
        DataError: the points are malformed, hold NaN or inf, or are too few to estimate from.
    """
    base = base or sensor_preset("hdl64e")
    points = _usable_points(points)
    # The fits need a few hundred returns per beam, not all of them: every k-th, in scan order.
    k = max(1, len(points) // _SAMPLE)
    x, y, z = _seen_from(points[::k], base.mount)
    horizontal = np.sqrt(x * x + y * y)
    azimuth = np.arctan2(y, x)
    used = int((horizontal >= _NEAR).sum())
    if used < _MIN_POINTS:
        sampled = f" (every {k}th of {len(points)})" if k > 1 else ""
        raise DataError(
            f"sensor auto: {used} of {len(x)} points{sampled} lie {_NEAR} m or more from the "
            f"sensor; at least {_MIN_POINTS} are needed to estimate its beams"
        )
    slope = z / np.maximum(horizontal, _NEAR)  # bounded for the returns off the car itself
    beams = _ring_beams(azimuth, slope, z, horizontal)
    if beams is not None:
        elevations, offsets = beams
        # successive firings: a stretch of the scan as recorded (a few rings' worth)
        middle = len(points) // 2
        stretch = _seen_from(points[max(0, middle - 4096) : middle + 4096], base.mount)
        step = _scan_step(np.arctan2(stretch[1], stretch[0]))
    else:
        elevations, fullest = _histogram_beams(z, horizontal)
        offsets = np.zeros_like(elevations)
        step = _beam_step(_seen_from(points, base.mount), fullest)
    step = 2.0 * math.pi / round(2.0 * math.pi / step)  # a whole number of columns per turn
    gaps = np.diff(np.sort(elevations))
    if len(elevations) > _MAX_BEAMS or (len(gaps) and gaps.min() < _MIN_GAP):
        raise DataError(
            f"sensor auto: the points show no plausible beams ({len(elevations)} found, "
            f"{math.degrees(gaps.min()) if len(gaps) else 0:.3f} degrees apart at the least); "
            "they are not one sweep in scan order (merged or shuffled?): give the sensor "
            "(drcpo.sensor.model) instead"
        )
    order = np.argsort(-elevations, kind="stable")
    return Sensor(
        elevations=elevations[order],
        offsets=offsets[order],
        azimuth_step=step,
        phase=_phase(azimuth[:: max(1, len(azimuth) // 4096)], step),
        mount=base.mount,
        range_noise=base.range_noise,
        dropout=base.dropout,
        min_range=base.min_range,
        max_range=base.max_range,
        name="auto",
    )


def _usable_points(points: np.ndarray) -> np.ndarray:
    """``points`` as a float array, or :class:`DataError` naming what is wrong with them."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3 or points.dtype.kind not in "fiu":
        raise DataError(
            f"sensor auto: points must be a numeric (N, 3+) array, got "
            f"{points.dtype} {points.shape}"
        )
    if points.dtype.kind != "f":
        points = points.astype(np.float64)
    # one fast pass over the whole array first (a NaN feature sends it to the exact check)
    whole = points if points.flags.c_contiguous else points[:, :3]
    if not np.isfinite(whole.sum(dtype=np.float64)):
        bad = ~np.isfinite(points[:, :3]).all(axis=1)
        if bad.any():
            raise DataError(
                f"sensor auto: {int(bad.sum())} points have NaN or infinite coordinates "
                f"(first at row {int(np.argmax(bad))}); drop them before estimating the sensor"
            )
    return points


def _seen_from(points: np.ndarray, mount: np.ndarray) -> tuple[np.ndarray, ...]:
    """``x, y, z`` (contiguous, the points' float type) of ``points`` relative to ``mount``."""
    x, y, z = (np.ascontiguousarray(points[:, i]) for i in range(3))
    if np.any(mount):
        x, y, z = x - mount[0], y - mount[1], z - mount[2]
    return x, y, z


def _turned(azimuth: np.ndarray, start: float) -> np.ndarray:
    """Azimuth swept since ``start``, in ``[0, 2 pi)`` (radians)."""
    turned = azimuth - azimuth.dtype.type(start)
    turned[turned < 0] += azimuth.dtype.type(2.0 * math.pi)
    return turned


def _ring_beams(
    azimuth: np.ndarray, slope: np.ndarray, z: np.ndarray, horizontal: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """Elevations and origin heights of the rings of a frame in scan order (see
    :func:`_fit_rings`), or ``None`` when the order shows no ring structure.

    Cut anywhere, the sweep falls into whole turns; the rings' own start (KITTI's near 0, the
    synthetic world's at -180 degrees) is where the points' elevation (``slope`` = z / d)
    changes from one ring to the next in every turn. An object spanning all the rings can do
    that too, so unless the rings of the best such place fit their lines well, the one of the
    few best whose rings fit best wins.
    """
    turns = _cut_rings(azimuth, -math.pi)
    if turns is None:
        return None
    cuts = [_cut_rings(azimuth, start - 1e-6) for start in _sweep_starts(azimuth, slope, turns)]
    # The -180 degree cut itself too: where the rings start outside the returns (a frame cut
    # to the camera's view), no bin shows the change, and a cut at an object's edge inside
    # the view mixes the ends of two rings into each, which still fit well enough to pass.
    cuts = [starts for starts in cuts if starts is not None] + [turns]
    fit = _fit_rings(z, horizontal, cuts[0])
    if fit is None or fit[2] < _PERFECT_FIT:
        # The others, judged on a quarter of the points; the best is fitted on all of them.
        quick = [_fit_rings(z, horizontal, starts, stride=4) for starts in cuts[1:]]
        share = [0.0 if q is None else q[2] for q in quick]
        if max(share) > (0.0 if fit is None else fit[2]):
            fit = _fit_rings(z, horizontal, cuts[1 + int(np.argmax(share))])
    return None if fit is None else fit[:2]


def _cut_rings(azimuth: np.ndarray, start: float) -> np.ndarray | None:
    """Ring boundaries when every ring's sweep begins at azimuth ``start``; ``None`` unless
    they look like rings (a few, each of many points)."""
    falls = np.flatnonzero(np.diff(_turned(azimuth, start)) < -_RING_DROP) + 1
    if len(falls) > len(azimuth) // (4 * _MIN_RING):
        return None  # the order is not a sweep (e.g. shuffled points)
    # Azimuth jitter at the sweep's start gives falls a few points apart: keep the first.
    kept, last = [0], 0
    for index in falls.tolist():
        if index - last >= _MIN_RING:
            kept.append(index)
            last = index
    starts = np.array([*kept, len(azimuth)], dtype=np.int64)
    lengths = np.diff(starts)
    if not 1 <= len(lengths) <= 1024 or np.median(lengths) < 8 * _MIN_RING:
        return None
    return starts


def _sweep_starts(azimuth: np.ndarray, slope: np.ndarray, turns: np.ndarray) -> list[float]:
    """Azimuths (radians) where the rings may start, best first: of the 1-degree bins of the
    turns ``turns`` (cut at -180 degrees), the (at most 3, 5 degrees apart) where the most
    turns change their mean elevation (over the 3 degrees after it against the 3 degrees
    before it): an object's edge changes it in the rings that meet the object, a new ring in
    all of them."""
    turn = np.repeat(np.arange(len(turns) - 1), np.diff(turns))
    column = np.minimum(
        (_turned(azimuth, -math.pi) * (_START_BINS / (2.0 * math.pi))).astype(np.int64),
        _START_BINS - 1,
    )
    cell = turn * _START_BINS + column
    size = (len(turns) - 1) * _START_BINS
    total = np.concatenate([[0.0], np.cumsum(np.bincount(cell, weights=slope, minlength=size))])
    count = np.concatenate([[0], np.cumsum(np.bincount(cell, minlength=size))])
    here = np.arange(size)
    before, after = np.maximum(here - 3, 0), np.minimum(here + 3, size)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_before = (total[here] - total[before]) / (count[here] - count[before])
        mean_after = (total[after] - total[here]) / (count[after] - count[here])
    change = np.abs(mean_after - mean_before).reshape(-1, _START_BINS)
    seen = ~np.isnan(change)
    # the share of turns (with returns there) whose elevation changes by over 0.1 degree;
    # the mean change (capped, in z / d) breaks ties
    change = np.where(seen, change, 0.0)
    turns_seen = np.maximum(seen.sum(axis=0), 1)
    share = (change > math.radians(0.1)).sum(axis=0) / turns_seen
    score = share + np.minimum(change, 0.01).sum(axis=0) / turns_seen
    chosen: list[int] = []
    for b in np.argsort(-score, kind="stable")[:20].tolist():
        if score[b] < 0.9 * score.max() or len(chosen) == 3:
            break
        if all(min(abs(b - c), _START_BINS - abs(b - c)) >= 5 for c in chosen):
            chosen.append(b)
    return [-math.pi + b * (2.0 * math.pi / _START_BINS) for b in chosen]


def _fit_rings(
    z: np.ndarray, horizontal: np.ndarray, starts: np.ndarray, stride: int = 1
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Per ring, the elevation (radians) and origin height (metres) of ``z = d tan(e) + h``
    fitted robustly, and the share of the returns within ``_ON_BEAM`` of their ring's line;
    ``None`` when the fits say the rings are not beams.

    The fit is linear in ``z / d = tan(e) + h / d``, so each point counts by its angular
    error; a prior draws ``h`` to the other rings' where the ring's returns span too few
    distances to fix it (see :func:`_line_fit`).
    ``stride``: fit every stride-th point only.
    """
    ring = np.repeat(np.arange(len(starts) - 1), np.diff(starts))[::stride]
    z, horizontal = z[::stride], horizontal[::stride]
    use = horizontal >= _NEAR
    ring = ring[use]
    # A ring with no usable return is left out (ring stays sorted, so its points contiguous).
    present = np.flatnonzero(np.bincount(ring, minlength=len(starts) - 1))
    if len(present) == 0:
        return None
    ring = np.cumsum(np.bincount(ring, minlength=len(starts) - 1) > 0)[ring] - 1
    d = horizontal[use].astype(np.float64)
    y, x = z[use] / d, 1.0 / d
    first = np.searchsorted(ring, np.arange(len(present)))
    guess = _ring_mode(y, ring, len(present), far=d >= _FAR)
    fits = [_robust_lines(x, y, ring, first, guess, heights) for heights in (True, False)]
    # Origin heights only where the returns need them: fitted to a ring that sees the road at
    # one distance, elevation and height trade off, and a wrong pair renders objects at other
    # distances off their beam. A sensor whose beams share one origin (the synthetic world's)
    # fits as well without them.
    (tan_e, height, share), (flat_e, flat_h, flat_share) = fits
    if flat_share >= share - _SAME_FIT:
        tan_e, height, share = flat_e, flat_h, flat_share
    if share < 0.5:
        return None  # most returns fit no ring's line: these are not beams
    elevations = np.arctan(tan_e)
    if len(np.unique(np.round(np.degrees(elevations), 2))) < len(elevations):
        return None  # two rings at one elevation: the order cut a beam in pieces
    return elevations, height, share


def _robust_lines(
    x: np.ndarray,
    y: np.ndarray,
    ring: np.ndarray,
    first: np.ndarray,
    tan_e: np.ndarray,
    heights: bool,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Per ring, ``tan(e)`` and ``h`` of ``y = tan(e) + h x`` by three passes of least squares
    over the inliers of the last (``heights=False``: ``h = 0``), starting from the elevations
    ``tan_e``; and the share of the returns within ``_ON_BEAM`` of their ring's line."""
    height = np.zeros(len(first))
    inlier = np.ones(len(y), dtype=bool)
    prior = 0.0
    for threshold in (math.radians(1.0), math.radians(0.3), None):
        miss = _misses(x, y, ring, tan_e, height if heights else None)
        if threshold is None:
            kept = np.add.reduceat(inlier.astype(np.float64), first)
            scale = np.sqrt(np.add.reduceat(miss**2 * inlier, first) / np.maximum(kept, 1.0))
            threshold = np.maximum(3.0 * scale, math.radians(0.03))[ring]
        inlier = miss < threshold
        if heights:
            tan_e, height, determined = _line_fit(x, y, first, inlier, prior)
            prior = float(np.median(height[determined])) if determined.any() else 0.0
        else:
            w = inlier.astype(np.float64)
            tan_e = np.add.reduceat(w * y, first) / np.maximum(np.add.reduceat(w, first), 1e-12)
    # Judged against a fixed tolerance: the last threshold grows with a ring's spread, so a
    # ring made of two beams would pass it.
    miss = _misses(x, y, ring, tan_e, height if heights else None)
    return tan_e, height, float((miss <= _ON_BEAM).mean())


def _misses(
    x: np.ndarray, y: np.ndarray, ring: np.ndarray, tan_e: np.ndarray, height: np.ndarray | None
) -> np.ndarray:
    """Each point's angular miss (radians) off its ring's line ``y = tan(e) + h x``;
    ``height`` ``None``: every ``h`` is 0 (the term then adds exactly nothing, so it is left
    out)."""
    along = tan_e[ring]
    off = y - along if height is None else y - along - height[ring] * x
    return np.abs(off) / (1.0 + along**2)


def _ring_mode(y: np.ndarray, ring: np.ndarray, rings: int, far: np.ndarray) -> np.ndarray:
    """Per ring, the most common ``y`` (= z / d) of its ``far`` points (of all its points when
    it has no far one), to 0.1 degree: a first guess of its elevation, blind to outliers."""
    has_far = np.bincount(ring[far], minlength=rings) > 0
    chosen = far | ~has_far[ring]
    width = math.radians(0.1)
    bins = math.ceil(2.0 / width)
    column = ((np.clip(y[chosen], -1.0, 1.0 - width) + 1.0) / width).astype(np.int64)
    counts = np.bincount(ring[chosen] * bins + column, minlength=rings * bins)
    return (np.argmax(counts.reshape(rings, bins), axis=1) + 0.5) * width - 1.0


def _line_fit(
    x: np.ndarray, y: np.ndarray, first: np.ndarray, weight: np.ndarray, prior: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per ring (points contiguous, ``first`` its first index), ``y = t + h x`` over the points
    of ``weight``, least squares with a Gaussian prior of ``h`` at ``prior`` (spread
    ``_HEIGHT_SPREAD``): ``(t, h, determined)``, ``determined`` where the returns alone fix
    ``h`` ten times better than the prior does.

    The prior's weight is the variance of the ring's returns about their own line fitted
    without it (radians^2, at least ``_MIN_SCATTER^2``) over ``_HEIGHT_SPREAD^2``; the
    returns' is their count times the variance of their ``x``. A ring whose returns span a
    few distances but lie tightly on their line (KITTI's: about 3e-5 radian) keeps its own
    height; one at a single distance, or scattered, takes the others'.
    """
    w = np.where(weight, 1.0, 0.0)
    wx, wy = w * x, w * y
    sums = [np.add.reduceat(v, first) for v in (w, wx, wy, wx * x, wx * y, wy * y)]
    n = np.maximum(sums[0], 1e-12)
    mean_x, mean_y = sums[1] / n, sums[2] / n
    spread = np.maximum(sums[3] / n - mean_x**2, 0.0)
    cross = sums[4] / n - mean_x * mean_y
    explained = np.divide(cross**2, spread, out=np.zeros_like(spread), where=spread > 0.0)
    residual = np.maximum(sums[5] / n - mean_y**2 - explained, _MIN_SCATTER**2)
    pull = residual / (n * _HEIGHT_SPREAD**2)  # the prior's weight per return
    height = (cross + pull * prior) / (spread + pull)
    return mean_y - height * mean_x, height, spread > 10.0 * pull


def _scan_step(azimuth: np.ndarray) -> float:
    """The azimuth step (radians) from successive points of ``azimuth``, a stretch of the scan
    as recorded (the odd step across a ring boundary is an outlier among thousands)."""
    step = np.diff(azimuth.astype(np.float64))
    return _typical_step(np.where(step < -math.pi, step + 2.0 * math.pi, step))


def _typical_step(step: np.ndarray) -> float:
    """The typical positive difference among ``step`` (radians): the mode of the histogram,
    refined by the median of those within 20 % of it (dropouts give multiples of the step)."""
    step = step[(step > 1e-6) & (step < _MAX_STEP)]
    if len(step) < 10:
        raise DataError(
            f"sensor auto: only {len(step)} successive returns of one beam were found; too "
            "few to estimate the azimuth step"
        )
    counts, edges = np.histogram(step, bins=1000, range=(0.0, _MAX_STEP))
    mode = (edges[np.argmax(counts)] + edges[np.argmax(counts) + 1]) / 2.0
    return float(np.median(step[np.abs(step - mode) <= 0.2 * mode]))


def _phase(azimuth: np.ndarray, step: float) -> float:
    """Azimuth of column 0 in ``[0, step)``: the circular mean of the points' offsets from
    the column grid."""
    angle = azimuth.astype(np.float64) * (2.0 * math.pi / step)
    mean = math.atan2(float(np.sin(angle).sum()), float(np.cos(angle).sum()))
    phase = (mean / (2.0 * math.pi)) % 1.0 * step
    return phase if phase < step else 0.0


def _histogram_beams(z: np.ndarray, horizontal: np.ndarray) -> tuple[np.ndarray, float]:
    """Beam elevations (radians) as the peaks of the elevation histogram of the returns beyond
    ``_NEAR``, and the elevation of the beam with the most returns."""
    # every return but the nearest: the lower beams of a sensor on a car meet the road
    # within 10 m
    far = horizontal >= _NEAR
    elevation = np.arctan2(z[far], horizontal[far]).astype(np.float64)
    low, high = elevation.min() - 2 * _PEAK_BIN, elevation.max() + 2 * _PEAK_BIN
    bins = max(1, math.ceil((high - low) / _PEAK_BIN))
    counts, edges = np.histogram(elevation, bins=bins, range=(low, high))
    smooth = np.convolve(counts, [1.0, 2.0, 1.0], mode="same")
    # A peak is the highest bin within 0.12 degree (beams are at least ~0.3 degree apart).
    window = 12
    padded = np.pad(smooth, window)
    local = np.lib.stride_tricks.sliding_window_view(padded, 2 * window + 1).max(axis=1)
    # ... and stands well above the returns between the beams
    floor = np.median(np.lib.stride_tricks.sliding_window_view(padded, 2 * window + 1), axis=1)
    tall = (smooth >= max(8.0, 0.02 * smooth.max())) & (smooth >= 4.0 * (floor + 1.0))
    peaks = np.flatnonzero((smooth == local) & tall)
    if len(peaks) == 0:
        raise DataError("sensor auto: the points' elevations show no beams")
    peaks = peaks[np.concatenate([[True], np.diff(peaks) > window])]  # one bin per flat top
    centres = (edges[peaks] + edges[peaks + 1]) / 2.0
    beam = np.searchsorted((centres[:-1] + centres[1:]) / 2.0, elevation)
    near = np.abs(elevation - centres[beam]) <= 3 * _PEAK_BIN
    total = np.bincount(beam[near], minlength=len(centres))
    elevations = np.bincount(beam[near], weights=elevation[near], minlength=len(centres)) / total
    return elevations, float(elevations[np.argmax(total)])


def _beam_step(xyz: tuple[np.ndarray, ...], elevation: float) -> float:
    """The azimuth step (radians) from the returns of the beam at ``elevation`` (radians), in
    azimuth order (for points in no scan order)."""
    x, y, z = xyz
    horizontal = np.sqrt(x * x + y * y)
    on_beam = (horizontal >= _NEAR) & (
        np.abs(np.arctan2(z, np.maximum(horizontal, 1e-6)) - elevation) <= 3 * _PEAK_BIN
    )
    azimuth = np.sort(np.arctan2(y[on_beam], x[on_beam]).astype(np.float64))
    return _typical_step(np.diff(azimuth))


# --------------------------------------------------------------------------------------------
# The YAML section drcpo.sensor
# --------------------------------------------------------------------------------------------
#: ``model`` choices: the presets, ``auto`` (estimated per frame) and ``custom`` (the keys).
SENSOR_MODELS = (*SENSOR_PRESETS, "auto", "custom")


@dataclass(frozen=True, eq=False)
class SensorConfig(Checked):
    """The config section ``drcpo.sensor``: which sensor recorded the frames.

    Attributes:
        model: a preset (``hdl64e``: KITTI's; ``hdl32e``: nuScenes'), ``auto`` (estimated
            from each frame, :func:`estimate_sensor`) or ``custom`` (``elevations_deg`` and
            ``azimuth_step_deg``).
        elevations_deg: ``custom`` only: the beam elevations, degrees, in any order.
        azimuth_step_deg: degrees between two firings of a beam (a preset's own when null;
            ``custom`` needs it; ``auto`` estimates it).
        mount: ``[x, y, z]`` the sensor's position in the LiDAR frame, metres (null: the
            preset's, the origin).
        range_noise: standard deviation of the range error, metres (null: the preset's).
        dropout: probability that a return is lost (null: the preset's).
    """

    KEY_PATH = "drcpo.sensor"

    model: str = field(
        default="hdl64e",
        metadata=spec(
            "choice", "a preset, auto (estimated per frame) or custom", choices=SENSOR_MODELS
        ),
    )
    elevations_deg: list[float] | None = field(
        default=None,
        metadata=spec(
            "floats",
            "custom: beam elevations, degrees",
            low=-90.0,
            high=90.0,
            low_open=True,
            high_open=True,
            nonempty=True,
            optional=True,
        ),
    )
    azimuth_step_deg: float | None = field(
        default=None,
        metadata=spec(
            "float",
            "degrees between two firings of a beam (null: the preset's)",
            low=0.01,
            high=10.0,
            optional=True,
        ),
    )
    mount: list[float] | None = field(
        default=None,
        metadata=spec(
            "floats",
            "[x, y, z] of the sensor in the LiDAR frame, m (null: the origin)",
            low=-100.0,
            high=100.0,
            length=3,
            optional=True,
        ),
    )
    range_noise: float | None = field(
        default=None,
        metadata=spec(
            "float", "range error std, m (null: the preset's)", low=0.0, high=1.0, optional=True
        ),
    )
    dropout: float | None = field(
        default=None,
        metadata=spec(
            "float",
            "share of returns lost (null: the preset's)",
            low=0.0,
            high=1.0,
            high_open=True,
            optional=True,
        ),
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        where = self.KEY_PATH
        if self.model == "custom":
            for key in ("elevations_deg", "azimuth_step_deg"):
                if getattr(self, key) is None:
                    raise ConfigError(f"config key '{where}.{key}' must be set for model custom")
            elevations = np.asarray(self.elevations_deg)
            if len(np.unique(elevations)) < len(elevations):
                raise ConfigError(
                    f"config key '{where}.elevations_deg' lists an elevation twice "
                    f"({', '.join(str(e) for e in _repeated(elevations))})"
                )
        elif self.elevations_deg is not None:
            raise ConfigError(
                f"config key '{where}.elevations_deg' is for model custom only; model "
                f"{self.model} has its own beams (set model: custom to list them)"
            )
        if self.model == "auto" and self.azimuth_step_deg is not None:
            raise ConfigError(
                f"config key '{where}.azimuth_step_deg' cannot be set with model auto, which "
                "estimates it from each frame (leave it null, or use model custom)"
            )

    def base(self) -> Sensor:
        """The sensor the keys describe without looking at a frame (for ``auto``: the
        ``hdl64e`` preset with this mount, noise and dropout, that the estimate starts from)."""
        preset = sensor_preset("hdl64e" if self.model in ("auto", "custom") else self.model)
        elevations, step = preset.elevations, preset.azimuth_step
        offsets = preset.offsets
        if self.model == "custom":
            elevations = np.sort(np.radians(np.asarray(self.elevations_deg)))[::-1]
            offsets = None
        if self.azimuth_step_deg is not None:
            step = math.radians(self.azimuth_step_deg)
        return Sensor(
            elevations=elevations,
            offsets=offsets,
            azimuth_step=step,
            mount=preset.mount if self.mount is None else np.asarray(self.mount),
            range_noise=_or(self.range_noise, preset.range_noise),
            dropout=_or(self.dropout, preset.dropout),
            min_range=preset.min_range,
            max_range=preset.max_range,
            name=self.model,
        )

    def sensor_for(self, points: np.ndarray | None = None) -> Sensor:
        """The sensor of a frame with ``points`` ``(N, 3+)``: estimated from them for ``auto``
        (:func:`estimate_sensor`, which raises :class:`DataError` on points it cannot use);
        the presets and ``custom`` ignore them."""
        if self.model != "auto":
            return self.base()
        if points is None:
            raise ConfigError(f"{self.KEY_PATH}.model auto needs the frame's points")
        return estimate_sensor(points, self.base())

    resolve = sensor_for


def _or(value: float | None, default: float) -> float:
    return default if value is None else value


def _repeated(values: np.ndarray) -> list[float]:
    unique, counts = np.unique(values, return_counts=True)
    return [float(v) for v in unique[counts > 1]]
