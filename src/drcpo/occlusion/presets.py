"""The paper's e-HPR settings per detector: radius ``R`` and viewpoint height.

Data only (detector names live here, not in the kernels); imports nothing from drcpo.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["HPR_PRESETS", "HPRPreset"]


@dataclass(frozen=True)
class HPRPreset:
    """e-HPR setting of one detector in the paper: radius ``R`` and viewpoint ``(0, 0, z)``.

    Attributes:
        radius: HPR radius ``R``, metres.
        viewpoint_z: height of the viewpoint above the sensor origin, metres.
    """

    radius: float
    viewpoint_z: float


HPR_PRESETS: dict[str, HPRPreset] = {
    "second": HPRPreset(radius=300000.0, viewpoint_z=2.0),
    "pointrcnn": HPRPreset(radius=300000.0, viewpoint_z=1.0),
    "pv_rcnn": HPRPreset(radius=100000.0, viewpoint_z=0.0),
    "pv_rcnn_plusplus": HPRPreset(radius=100000.0, viewpoint_z=0.0),
}
