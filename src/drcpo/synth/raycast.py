"""Ray casting from the sensor (the origin) into a world of solids over an uneven ground.

Every ray starts at the origin. Solids are binned by the azimuth interval they cover and, within
a bin, sorted by their nearest horizontal distance, so a ray tests only the solids in its
direction and stops as soon as the next solid cannot be nearer than its current hit. The ground
is a smooth height field ``z = base + sum_k a_k sin(kx_k x + ky_k y + phi_k)``, hit by marching the
ray through the height band the field can occupy and refining the first crossing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np

from drcpo.synth.solids import BOX, ELLIPSOID, Solids

__all__ = ["GROUND", "MISS", "Ground", "RayHits", "Scene"]

MISS, GROUND = -2, -1  # hit codes besides solid rows
_MIN_GROUND_STEP = 0.02  # metres; smallest step of the height-field march
_REFINE_ITERATIONS = 40


@dataclass(frozen=True, eq=False)
class Ground:
    """A smooth height field: ``base + sum_k amplitude_k sin(wave_x_k x + wave_y_k y + phase_k)``.

    Attributes are ``float64 (K,)`` arrays except ``base`` (metres, the mean ground height in the
    LiDAR frame, i.e. minus the mount height).
    """

    base: float
    amplitude: np.ndarray
    wave_x: np.ndarray
    wave_y: np.ndarray
    phase: np.ndarray

    def __post_init__(self) -> None:
        for name in ("amplitude", "wave_x", "wave_y", "phase"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        if self.base + self.bound >= 0.0:
            raise ValueError("the ground must stay below the sensor (base + bound < 0)")

    @classmethod
    def flat(cls, base: float) -> Ground:
        return cls(base, np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))

    @property
    def bound(self) -> float:
        """Largest possible deviation from ``base``, metres."""
        return float(np.abs(self.amplitude).sum())

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Ground height (metres) at ``x, y`` (arrays of any matching shape)."""
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        phase = x[..., None] * self.wave_x + y[..., None] * self.wave_y + self.phase
        return self.base + (self.amplitude * np.sin(phase)).sum(axis=-1)


@dataclass(frozen=True, eq=False)
class RayHits:
    """First hits of rays from the origin.

    Attributes:
        t: ``float64 (R,)`` distance to the first hit, ``inf`` where the ray hit nothing in range.
        hit: ``int32 (R,)`` solid row of the first hit, :data:`GROUND` or :data:`MISS`.
        normal: ``float64 (R, 3)`` unit surface normal at the hit (zero on a miss).
    """

    t: np.ndarray
    hit: np.ndarray
    normal: np.ndarray


class _Field(NamedTuple):
    """The ground's height field as the kernels read it (:class:`Ground`'s terms)."""

    base: float
    amp: np.ndarray
    kx: np.ndarray
    ky: np.ndarray
    ph: np.ndarray


class _Solids(NamedTuple):
    kind: np.ndarray  # (S,) BOX, ELLIPSOID or cylinder
    centre: np.ndarray  # (S, 3)
    half: np.ndarray  # (S, 3) half extents (a cylinder's radius in x)
    cos_yaw: np.ndarray  # (S,)
    sin_yaw: np.ndarray


class _Bins(NamedTuple):
    """Per azimuth bin the solids to test, nearest first (:func:`_bin_solids`)."""

    start: np.ndarray  # (bins + 1,) CSR starts into items
    items: np.ndarray  # solid rows
    near: np.ndarray  # (S,) each solid's least horizontal distance
    elev_lo: np.ndarray  # (S,) the elevations it spans
    elev_hi: np.ndarray


class Scene:
    """Solids (and optionally a ground) prepared for fast ray casting from the origin."""

    def __init__(self, solids: Solids, ground: Ground | None = None, num_bins: int = 720) -> None:
        self.solids = solids
        self.ground = ground
        self.num_bins = int(num_bins)
        self._bins = _Bins(*_bin_solids(solids, self.num_bins))

    def cast(self, directions: np.ndarray, t_max: np.ndarray | float) -> RayHits:
        """First hits of rays from the origin along unit ``directions (R, 3)`` up to ``t_max``.

        ``t_max`` (metres) is a scalar or ``(R,)``; hits at or beyond it count as misses.
        """
        directions = np.ascontiguousarray(directions, dtype=np.float64)
        if directions.ndim != 2 or directions.shape[1] != 3:
            raise ValueError(f"directions must have shape (R, 3), got {directions.shape}")
        t_max = np.ascontiguousarray(
            np.broadcast_to(np.asarray(t_max, dtype=np.float64), (len(directions),))
        )
        ground = self.ground or Ground(-1.0, np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
        s = self.solids
        solids = _Solids(s.kind, s.centre, s.half, np.cos(s.yaw), np.sin(s.yaw))
        field = _Field(
            float(ground.base), ground.amplitude, ground.wave_x, ground.wave_y, ground.phase
        )
        t, hit, normal = _cast(
            directions, t_max, self._bins, solids, field, self.ground is not None
        )
        return RayHits(t, hit, normal)


def _bin_solids(solids: Solids, num_bins: int):
    """CSR lists of the solids each azimuth bin must test, nearest first, and culling bounds."""
    n = len(solids)
    if n == 0:
        empty = np.zeros(0)
        return np.zeros(num_bins + 1, np.int64), np.zeros(0, np.int64), empty, empty, empty
    radius = solids.horizontal_radius() * (1 + 1e-9) + 1e-9
    extent_z = solids.half[:, 2] * (1 + 1e-9) + 1e-9
    cx, cy, cz = solids.centre.T
    dist = np.hypot(cx, cy)
    near = np.maximum(dist - radius, 0.0)
    far = dist + radius
    top, bottom = cz + extent_z, cz - extent_z
    elev_hi = np.arctan2(top, np.where(top > 0, near, far))
    elev_lo = np.arctan2(bottom, np.where(bottom > 0, far, near))
    width = 2.0 * np.pi / num_bins
    covers_all = dist <= radius
    half_angle = np.arcsin(np.clip(radius / np.maximum(dist, 1e-12), 0.0, 1.0))
    centre_angle = np.arctan2(cy, cx)
    first = np.floor((centre_angle - half_angle + np.pi) / width).astype(np.int64)
    last = np.floor((centre_angle + half_angle + np.pi) / width).astype(np.int64)
    first = np.where(covers_all, 0, first)
    last = np.where(covers_all, num_bins - 1, np.minimum(last, first + num_bins - 1))
    count = last - first + 1
    solid = np.repeat(np.arange(n), count)
    offset = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    bins = (np.repeat(first, count) + offset) % num_bins
    order = np.lexsort((near[solid], bins))
    bins, solid = bins[order], solid[order]
    start = np.searchsorted(bins, np.arange(num_bins + 1))
    return start.astype(np.int64), solid.astype(np.int64), near, elev_lo, elev_hi


@numba.njit(cache=True)
def _ground_z(x, y, field):
    z = field.base
    amp, kx, ky, ph = field.amp, field.kx, field.ky, field.ph
    for k in range(amp.shape[0]):
        z += amp[k] * np.sin(kx[k] * x + ky[k] * y + ph[k])
    return z


@numba.njit(cache=True)
def _ground_hit(d, t_max, field):
    """First crossing of the ray with the height field, by Lipschitz-safe marching.

    ``f(t) = ray height - ground height`` changes at most ``|dz| + G |d_xy|`` per metre (G: the
    field's largest slope), so a step of ``f / L`` cannot pass the crossing; near it the step
    falls to ``_MIN_GROUND_STEP`` and the bracketed crossing is refined by the Illinois method.
    """
    dx, dy, dz = d
    if dz >= 0.0:
        return np.inf
    base, amp, kx, ky = field.base, field.amp, field.kx, field.ky
    bound, slope = 0.0, 0.0
    for k in range(amp.shape[0]):
        bound += abs(amp[k])
        slope += abs(amp[k]) * np.sqrt(kx[k] * kx[k] + ky[k] * ky[k])
    t_lo = (base + bound) / dz
    if t_lo >= t_max:
        return np.inf
    t_hi = min((base - bound) / dz, t_max)
    lipschitz = -dz + slope * np.sqrt(dx * dx + dy * dy)
    a = t_lo
    fa = a * dz - _ground_z(a * dx, a * dy, field)
    while a < t_hi:
        b = min(a + max(fa / lipschitz, _MIN_GROUND_STEP), t_hi)
        fb = b * dz - _ground_z(b * dx, b * dy, field)
        if fb <= 0.0:
            return _refine_crossing((a, fa), (b, fb), d, field, t_max)
        a, fa = b, fb
    return np.inf


@numba.njit(cache=True)
def _refine_crossing(above, below, d, field, t_max):
    """Illinois regula falsi on a bracket ``(a, fa)``, ``(b, fb)`` with ``fa > 0 >= fb``;
    returns the crossing distance."""
    (a, fa), (b, fb) = above, below
    dx, dy, dz = d
    side = 0
    for _ in range(_REFINE_ITERATIONS):
        if b - a < 1e-9 or fb == 0.0:
            break
        m = (a * fb - b * fa) / (fb - fa)
        fm = m * dz - _ground_z(m * dx, m * dy, field)
        if fm <= 0.0:
            b, fb = m, fm
            if side == -1:
                fa *= 0.5
            side = -1
        else:
            a, fa = m, fm
            if side == 1:
                fb *= 0.5
            side = 1
    return b if b < t_max else np.inf


@numba.njit(cache=True)
def _hit_solid(s, d, solids):
    """Distance along the ray to solid s (inf on a miss) and the local axis code of the face."""
    dx, dy, dz = d
    kind, centre, half = solids.kind, solids.centre, solids.half
    ox, oy, oz = -centre[s, 0], -centre[s, 1], -centre[s, 2]
    c, sn = solids.cos_yaw[s], solids.sin_yaw[s]
    lox, loy = c * ox + sn * oy, -sn * ox + c * oy
    ldx, ldy = c * dx + sn * dy, -sn * dx + c * dy
    hx, hy, hz = half[s, 0], half[s, 1], half[s, 2]
    if kind[s] == BOX:
        t_near, t_far, axis = -np.inf, np.inf, 0
        for a in range(3):
            o = lox if a == 0 else (loy if a == 1 else oz)
            d = ldx if a == 0 else (ldy if a == 1 else dz)
            h = hx if a == 0 else (hy if a == 1 else hz)
            if abs(d) < 1e-15:
                if abs(o) > h:
                    return np.inf, 0
                continue
            t1, t2 = (-h - o) / d, (h - o) / d
            if t1 > t2:
                t1, t2 = t2, t1
            if t1 > t_near:
                t_near, axis = t1, a
            t_far = min(t_far, t2)
            if t_near > t_far:
                return np.inf, 0
        if t_near <= 1e-9:
            return np.inf, 0
        return t_near, axis
    if kind[s] == ELLIPSOID:
        px, py, pz = lox / hx, loy / hy, oz / hz
        qx, qy, qz = ldx / hx, ldy / hy, dz / hz
        a = qx * qx + qy * qy + qz * qz
        b = 2.0 * (px * qx + py * qy + pz * qz)
        cc = px * px + py * py + pz * pz - 1.0
        disc = b * b - 4.0 * a * cc
        if disc < 0.0:
            return np.inf, 0
        t = (-b - np.sqrt(disc)) / (2.0 * a)
        return (t, 0) if t > 1e-9 else (np.inf, 0)
    best, code = np.inf, 0
    a = ldx * ldx + ldy * ldy
    if a > 1e-18:
        b = 2.0 * (lox * ldx + loy * ldy)
        cc = lox * lox + loy * loy - hx * hx
        disc = b * b - 4.0 * a * cc
        if disc >= 0.0:
            t = (-b - np.sqrt(disc)) / (2.0 * a)
            if t > 1e-9 and abs(oz + t * dz) <= hz:
                best, code = t, 0
    if abs(dz) > 1e-15:
        for sign in (-1.0, 1.0):
            t = (sign * hz - oz) / dz
            if 1e-9 < t < best:
                x, y = lox + t * ldx, loy + t * ldy
                if x * x + y * y <= hx * hx:
                    best, code = t, 1
    return best, code


@numba.njit(cache=True)
def _solid_normal(s, t, code, d, solids):
    dx, dy, dz = d
    kind, centre, half = solids.kind, solids.centre, solids.half
    c, sn = solids.cos_yaw[s], solids.sin_yaw[s]
    px, py, pz = t * dx - centre[s, 0], t * dy - centre[s, 1], t * dz - centre[s, 2]
    lx, ly = c * px + sn * py, -sn * px + c * py
    ldx, ldy = c * dx + sn * dy, -sn * dx + c * dy
    nx, ny, nz = 0.0, 0.0, 0.0
    if kind[s] == BOX:
        if code == 0:
            nx = -1.0 if ldx > 0 else 1.0
        elif code == 1:
            ny = -1.0 if ldy > 0 else 1.0
        else:
            nz = -1.0 if dz > 0 else 1.0
    elif kind[s] == ELLIPSOID:
        nx = lx / half[s, 0] ** 2
        ny = ly / half[s, 1] ** 2
        nz = pz / half[s, 2] ** 2
    elif code == 0:
        nx, ny = lx, ly
    else:
        nz = -1.0 if dz > 0 else 1.0
    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
    nx, ny, nz = nx / norm, ny / norm, nz / norm
    return c * nx - sn * ny, sn * nx + c * ny, nz


@numba.njit(cache=True)
def _cast(dirs, t_max, bins, solids, field, use_ground):
    bin_start, bin_items, near = bins.start, bins.items, bins.near
    amp, kx, ky, ph = field.amp, field.kx, field.ky, field.ph
    n = dirs.shape[0]
    num_bins = bin_start.shape[0] - 1
    t_out = np.full(n, np.inf)
    hit_out = np.full(n, MISS, dtype=np.int32)
    normal = np.zeros((n, 3))
    inv_width = num_bins / (2.0 * np.pi)
    for r in range(n):
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        d = (dx, dy, dz)
        best, hit, code = t_max[r], MISS, 0
        if use_ground:
            tg = _ground_hit(d, best, field)
            if tg < best:
                best, hit = tg, GROUND
        b = int((np.arctan2(dy, dx) + np.pi) * inv_width)
        b = min(max(b, 0), num_bins - 1)
        elevation = np.arcsin(min(max(dz, -1.0), 1.0))
        for k in range(bin_start[b], bin_start[b + 1]):
            s = bin_items[k]
            if near[s] >= best:
                break
            if elevation < bins.elev_lo[s] or elevation > bins.elev_hi[s]:
                continue
            t, c = _hit_solid(s, d, solids)
            if t < best:
                best, hit, code = t, s, c
        if hit == MISS:
            continue
        t_out[r], hit_out[r] = best, hit
        if hit == GROUND:
            x, y = best * dx, best * dy
            gx, gy = 0.0, 0.0
            for k in range(amp.shape[0]):
                cos_phase = amp[k] * np.cos(kx[k] * x + ky[k] * y + ph[k])
                gx += cos_phase * kx[k]
                gy += cos_phase * ky[k]
            norm = np.sqrt(gx * gx + gy * gy + 1.0)
            normal[r, 0], normal[r, 1], normal[r, 2] = -gx / norm, -gy / norm, 1.0 / norm
        else:
            nx, ny, nz = _solid_normal(hit, best, code, d, solids)
            normal[r, 0], normal[r, 1], normal[r, 2] = nx, ny, nz
    return t_out, hit_out, normal
