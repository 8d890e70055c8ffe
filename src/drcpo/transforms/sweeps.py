"""Multi-sweep frames (nuScenes-style: earlier sweeps joined to the key sweep, each point's
sweep named by its time lag) in DR.CPO.

How occlusion treats them: HPR needs one viewpoint per point set, and the sweeps were recorded
from different places (the ego moves between them; ``metadata["sweep_origins"]``). So DR.CPO
runs all its steps (placement, construction, s-HPR, insertion, e-HPR and the labels) on the
key sweep alone, seen from the key origin, and an inserted object exists in the key sweep only
(its points' time lag is 0, as every inserted point's). The earlier sweeps' points are then
settled per sweep, each from its own origin: those inside an inserted object's room (the space
it now fills) go, and those the inserted objects hide, seen from that sweep's origin (its
viewpoint: the origin raised by the e-HPR preset's height), go as e-HPR's ``inserted`` scope
removes the key sweep's (hidden with the objects, visible without them, in the objects' view
windows). Their other
points and all their features are kept bit for bit, after the key sweep's. The label rule
(original boxes left too sparse) counts the key sweep's points only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from drcpo import occlusion
from drcpo.config import ExternalOcclusionConfig
from drcpo.errors import DataError
from drcpo.frame import Frame
from drcpo.occlusion.view_windows import grown_boxes, window_spans
from drcpo.transforms.insertion import BOX_SOURCE, BoxQuery, take_rows, time_lag_column

__all__ = ["SWEEP_ORIGINS", "SWEEP_TIME_LAGS", "SweepSplit", "split_sweeps"]

#: ``float64 (S, 3)``: each sweep's sensor origin in the key frame's LiDAR coordinates (row 0:
#: the key sweep).
SWEEP_ORIGINS = "sweep_origins"
#: ``float64 (S,)``: each sweep's time lag, seconds (row 0: the key sweep, 0).
SWEEP_TIME_LAGS = "sweep_time_lags"


@dataclass(frozen=True, eq=False)
class SweepSplit:
    """A multi-sweep frame cut into its key sweep and the rest.

    Attributes:
        key: the frame with the key sweep's points only (metadata unchanged).
        rest: ``(R, 3 + C)`` the earlier sweeps' points, in frame order.
        sweep: ``int64 (R,)`` the sweep (row of the sweep metadata) of each of ``rest``.
        origins: ``float64 (S, 3)`` the sweeps' origins.
    """

    key: Frame
    rest: np.ndarray
    sweep: np.ndarray
    origins: np.ndarray

    def join(
        self,
        out: Frame,
        source: str,
        room: float,
        setting: ExternalOcclusionConfig | None,
    ) -> Frame:
        """The output frame: DR.CPO's output on the key sweep (``out``; its boxes from
        ``source`` are the inserted objects, their points the ones inside them) with the earlier
        sweeps' points settled as the module says.

        Args:
            out: the transform's output on :attr:`key`.
            source: the :data:`~drcpo.transforms.insertion.BOX_SOURCE` of the inserted boxes.
            room: metres by which an object's room exceeds its box.
            setting: e-HPR's radius and viewpoint height (``radius``, ``viewpoint_z`` of
                ``drcpo.external_occlusion``); a sweep's viewpoint is its origin raised by that
                height; ``None``: e-HPR off.
        """
        added = np.asarray(out.metadata.get(BOX_SOURCE, np.zeros(0, str))) == source
        boxes = out.boxes[added] if len(added) == len(out.boxes) else np.zeros((0, 7))
        rest = self.rest
        if len(boxes) and len(rest):
            keep = ~BoxQuery(rest).inside_any(grown_boxes(boxes, room))
            objects = take_rows(out.points, BoxQuery(out.points).inside_any(boxes))
            for s in np.unique(self.sweep) if setting is not None else ():
                rows = np.flatnonzero((self.sweep == s) & keep)
                viewpoint = self.origins[s] + np.array([0.0, 0.0, setting.viewpoint_z])
                hidden = _hidden_behind(
                    rest[rows], objects, boxes, float(setting.radius), viewpoint
                )
                keep[rows[hidden]] = False
            rest = take_rows(rest, keep)
        # the key sweep as DR.CPO left it (its points, then the inserted ones), then the others
        return out.replace(points=np.concatenate([out.points, rest]))


def _hidden_behind(
    originals: np.ndarray,
    objects: np.ndarray,
    boxes: np.ndarray,
    radius: float,
    viewpoint: np.ndarray,
) -> np.ndarray:
    """``bool (len(originals),)``: original points hidden by the inserted ``objects`` seen from
    ``viewpoint`` (e-HPR's ``inserted`` scope, step 2, in the boxes' view windows)."""
    if len(originals) == 0 or len(objects) == 0:
        return np.zeros(len(originals), dtype=bool)
    points = np.concatenate([originals[:, :3], objects[:, :3]])
    inserted = np.arange(len(points)) >= len(originals)
    scope = occlusion.inserted_scope(points, inserted, viewpoint, radius)
    return scope.removed_behind(window_spans(grown_boxes(boxes), viewpoint, True))


def split_sweeps(frame: Frame) -> SweepSplit | None:
    """The frame cut into its key sweep and the rest, or ``None`` when it holds one sweep (no
    sweep metadata, one sweep, or no ``time_lag`` point feature). Raises :class:`DataError`
    naming the frame and key on sweep metadata of the wrong shape, or a point whose time lag
    is none of the sweeps'."""
    origins, lags = frame.metadata.get(SWEEP_ORIGINS), frame.metadata.get(SWEEP_TIME_LAGS)
    column = time_lag_column(frame)
    if origins is None or lags is None or column is None:
        return None
    origins, lags = _checked(frame, origins, lags)
    if len(lags) < 2:
        return None
    sweep = _sweep_of(frame, frame.points[:, column], lags)
    key = sweep == 0
    return SweepSplit(
        key=frame.replace(points=take_rows(frame.points, key)),
        rest=take_rows(frame.points, ~key),
        sweep=sweep[~key],
        origins=origins,
    )


def _checked(frame: Frame, origins: Any, lags: Any) -> tuple[np.ndarray, np.ndarray]:
    where = f"frame {frame.frame_id}: metadata"
    origins = np.asarray(origins, dtype=np.float64)
    lags = np.asarray(lags, dtype=np.float64)
    if lags.ndim != 1 or not np.isfinite(lags).all():
        raise DataError(f"{where} {SWEEP_TIME_LAGS!r} must be (S,) finite seconds, got {lags}")
    if origins.shape != (len(lags), 3) or not np.isfinite(origins).all():
        raise DataError(
            f"{where} {SWEEP_ORIGINS!r} must be ({len(lags)}, 3) finite numbers (one origin per "
            f"sweep of {SWEEP_TIME_LAGS!r}), got shape {origins.shape}"
        )
    if len(lags) and lags[0] != 0:
        raise DataError(
            f"{where} {SWEEP_TIME_LAGS!r} row 0 (the key sweep) must be 0, got {lags[0]}"
        )
    return origins, lags


def _sweep_of(frame: Frame, time_lag: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """``int64 (N,)``: the sweep whose time lag (as float32, as the points hold it) each
    point's equals."""
    values = lags.astype(np.float32)
    order = np.argsort(values, kind="stable")
    position = np.clip(np.searchsorted(values[order], time_lag), 0, len(values) - 1)
    sweep = order[position]
    wrong = values[sweep] != time_lag
    if wrong.any():
        row = int(np.flatnonzero(wrong)[0])
        raise DataError(
            f"frame {frame.frame_id}: point row {row} has time lag {float(time_lag[row])!r}, "
            f"none of metadata {SWEEP_TIME_LAGS!r} {lags.tolist()}"
        )
    return sweep.astype(np.int64)
