"""The frame-wide ground plane ``z = a x + b y + c`` (LiDAR frame) of :mod:`drcpo.ground`.

- :func:`fit_plane`: RANSAC over the lowest points of the BEV cells (plane hypotheses through
  random triples whose normal is within a tilt limit of vertical, scored on a random subset of
  at most 1000 points), refined by least squares on the best hypothesis' inliers.
- :func:`road_plane_to_lidar`: a KITTI road plane (rectified camera frame) as such a plane,
  which then replaces the fit.
- :func:`plane_height`: the plane's height at BEV positions.

Sums over coordinates run in one fixed order, not through BLAS, so the same points give the same
plane on every machine (BLAS's rounding, which decides ties between hypotheses, depends on the
machine's kernels).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from drcpo.errors import DataError

__all__ = ["fit_plane", "plane_height", "road_plane_to_lidar"]

#: Most points a plane hypothesis is scored on.
_RANSAC_SCORED = 1000


def road_plane_to_lidar(plane: np.ndarray, calib) -> np.ndarray:
    """KITTI road plane ``(a, b, c, d)`` (rectified camera frame) as LiDAR ``z = a x + b y + c``.

    The rectified frame is ``p_rect = R0 (T[:, :3] p + T[:, 3])``, so the plane's LiDAR normal is
    ``(R0 T[:, :3])^T n`` and its offset ``n . (R0 T[:, 3]) + d``. OpenPCDet instead fixes the
    rectified x, z of a box centre, solves the plane for y and converts back
    (``put_boxes_on_road_planes``); both give the same surface.
    """
    plane = np.asarray(plane, dtype=np.float64).reshape(-1)
    if plane.shape != (4,) or not np.isfinite(plane).all():
        raise DataError(
            f"road plane must be four finite numbers (a, b, c, d), got {plane.tolist()}"
        )
    if calib is None:
        raise DataError("a KITTI road plane needs the frame's calibration (calib)")
    r0 = np.asarray(calib.R0_rect, dtype=np.float64)
    tr = np.asarray(calib.Tr_velo_to_cam, dtype=np.float64)
    normal = (r0 @ tr[:, :3]).T @ plane[:3]
    offset = plane[:3] @ (r0 @ tr[:, 3]) + plane[3]
    if abs(normal[2]) < 1e-6 * max(np.linalg.norm(normal), 1e-12):
        raise DataError(f"road plane {plane.tolist()} is vertical in the LiDAR frame")
    return np.array([-normal[0], -normal[1], -offset]) / normal[2]


def fit_plane(
    seeds: np.ndarray,
    rng: np.random.Generator,
    iterations: int,
    threshold: float,
    max_tilt_deg: float,
) -> np.ndarray | None:
    """``(a, b, c)`` of ``z = a x + b y + c`` through most ``(S, 3)`` seeds; ``None`` if S < 3.

    ``iterations`` hypotheses (normals within ``max_tilt_deg`` of vertical), inliers within
    ``threshold`` metres of a hypothesis (:class:`drcpo.ground.GroundConfig`'s ``ransac_*`` and
    ``max_tilt_deg``).
    """
    if len(seeds) < 3:
        return None
    z = seeds[:, 2]
    picks = rng.integers(0, len(z), size=(iterations, 3))
    # Hypotheses are scored on a random subset: enough to rank planes, much cheaper.
    scored = (
        seeds[rng.choice(len(z), _RANSAC_SCORED, replace=False)]
        if len(z) > _RANSAC_SCORED
        else seeds
    )
    cos_tilt = float(np.cos(np.deg2rad(max_tilt_deg)))
    normals, offsets, length = _plane_hypotheses(seeds, picks, cos_tilt)
    if len(normals) == 0:
        return _least_squares_plane(seeds)
    # The distances n . p are summed in one fixed order, not by BLAS, whose rounding (which
    # decides ties) depends on the machine's kernels.
    limit = threshold * length
    best = _most_inliers(scored, normals, offsets, limit)
    inliers = _within(seeds, normals[best], offsets[best], limit[best])
    chosen = seeds[inliers]
    return _least_squares_plane(chosen) if len(chosen) >= 3 else _least_squares_plane(seeds)


@numba.njit(cache=True, nogil=True)
def _plane_hypotheses(seeds, picks, cos_tilt):  # pragma: no cover - numba
    # Normals (p1 - p0) x (p2 - p0) of the picked triples, their lengths and the offsets
    # n . p0, of the triples whose normal is within the tilt limit of vertical, in pick order.
    count = picks.shape[0]
    normals = np.empty((count, 3))
    offsets = np.empty(count)
    length = np.empty(count)
    kept = 0
    for h in range(count):
        a, b, c = seeds[picks[h, 0]], seeds[picks[h, 1]], seeds[picks[h, 2]]
        u0, u1, u2 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        v0, v1, v2 = c[0] - a[0], c[1] - a[1], c[2] - a[2]
        n0, n1, n2 = u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0
        norm = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        if abs(n2) >= cos_tilt * norm and norm > 1e-9:
            normals[kept, 0], normals[kept, 1], normals[kept, 2] = n0, n1, n2
            offsets[kept] = n0 * a[0] + n1 * a[1] + n2 * a[2]
            length[kept] = norm
            kept += 1
    return normals[:kept].copy(), offsets[:kept].copy(), length[:kept].copy()


@numba.njit(cache=True, nogil=True)
def _most_inliers(points, normals, offsets, limit):  # pragma: no cover - numba
    # The hypothesis with the most points p with |n . p - offset| <= limit (the first on
    # ties); n . p summed as x, then y, then z, as _within sums it.
    nx, ny, nz = normals[:, 0].copy(), normals[:, 1].copy(), normals[:, 2].copy()
    counts = np.zeros(normals.shape[0], np.int64)
    for s in range(points.shape[0]):
        x, y, z = points[s, 0], points[s, 1], points[s, 2]
        for h in range(nx.shape[0]):  # branch-free: vectorises
            distance = x * nx[h] + y * ny[h] + z * nz[h]
            counts[h] += np.int64(abs(distance - offsets[h]) <= limit[h])
    return np.argmax(counts)


@numba.njit(cache=True, nogil=True)
def _within(points, normal, offset, limit):  # pragma: no cover - numba
    # bool per point: |n . p - offset| <= limit, summed as _most_inliers sums it.
    out = np.empty(points.shape[0], dtype=np.bool_)
    for s in range(points.shape[0]):
        distance = points[s, 0] * normal[0] + points[s, 1] * normal[1] + points[s, 2] * normal[2]
        out[s] = abs(distance - offset) <= limit
    return out


def plane_height(xy: np.ndarray, plane: np.ndarray, offset: float | None = None) -> np.ndarray:
    """``a x + b y + c`` of ``plane = (a, b, c)`` at ``(K, 2+)`` positions (``offset`` in place
    of ``c`` if given), element-wise: the same sums on every machine, unlike a BLAS product."""
    xy = np.asarray(xy, dtype=np.float64)
    out = xy[:, 0] * plane[0]
    out += xy[:, 1] * plane[1]
    out += plane[2] if offset is None else offset
    return out


def _least_squares_plane(xyz: np.ndarray) -> np.ndarray:
    design = np.column_stack([xyz[:, 0], xyz[:, 1], np.ones(len(xyz))])
    coef, *_ = np.linalg.lstsq(design, xyz[:, 2], rcond=None)
    return coef
