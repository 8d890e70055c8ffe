"""Occlusion (DR.CPO, step 5): Katz et al.'s hidden point removal (HPR), the paper's s-HPR and
e-HPR.

The paper's two uses are :func:`self_occlusion` (s-HPR, per placed object, ``R`` = box
diagonal x 200) and :func:`external_occlusion` (e-HPR, the whole frame after insertion, ``R``
and the viewpoint height per detector in the presets' YAML files); :func:`inserted_scope`
(two steps) is e-HPR's ``inserted`` scope. :func:`surface_samples` are the points on a box's
faces that placement's "occluded" test decides by e-HPR before anything is built.

Modules, each importing only those listed before it (and :mod:`drcpo.errors`,
:mod:`drcpo.geometry`), never anything above (:mod:`drcpo.placement`,
:mod:`drcpo.transforms`):

* :mod:`~drcpo.occlusion.checks`: input checks.
* :mod:`~drcpo.occlusion.grid`: points sorted into direction cells (numba), :class:`GridMemory`.
* :mod:`~drcpo.occlusion.hull_order`: the order the certified hull takes its points in (numba).
* :mod:`~drcpo.occlusion.hull`: the certified hull of small clouds (numba).
* :mod:`~drcpo.occlusion.kernels`: the per-point supporting-plane test (numba).
* :mod:`~drcpo.occlusion.frame_kernels`: :class:`FrameGrid`'s kernels (numba).
* :mod:`~drcpo.occlusion.flip`: the spherical flip's set-up and one Qhull hull of it.
* :mod:`~drcpo.occlusion.local`: the ``"local"`` method's driver.
* :mod:`~drcpo.occlusion.hpr`: :func:`hidden_point_removal` (methods and awkward inputs there).
* :mod:`~drcpo.occlusion.frame_grid`: :class:`FrameGrid`, a frame sorted once for e-HPR.
* :mod:`~drcpo.occlusion.view_windows`: the directions boxes cover, seen from the viewpoint,
  and the samples on their faces (:func:`surface_samples`).
* :mod:`~drcpo.occlusion.scopes`: s-HPR.
* :mod:`~drcpo.occlusion.external`: e-HPR over a whole frame, and scoped to the inserted objects
  in two steps.

Everything here runs on the calling thread and is safe in forked worker processes (PyTorch
DataLoader workers): numba kernels are compiled without a threading layer.
"""

from __future__ import annotations

from drcpo.occlusion.checks import MAX_RADIUS
from drcpo.occlusion.external import (
    InsertedScope,
    external_occlusion,
    inserted_scope,
)
from drcpo.occlusion.frame_grid import FrameGrid
from drcpo.occlusion.grid import GridMemory, thread_grid_memory
from drcpo.occlusion.hpr import (
    AUTO_CROWDED,
    AUTO_REFERENCE_MAX,
    HPR_METHODS,
    HULL_KERNEL_MAX,
    hidden_point_removal,
)
from drcpo.occlusion.scopes import self_occlusion
from drcpo.occlusion.view_windows import surface_samples

__all__ = [
    "AUTO_CROWDED",
    "AUTO_REFERENCE_MAX",
    "HPR_METHODS",
    "HULL_KERNEL_MAX",
    "MAX_RADIUS",
    "FrameGrid",
    "GridMemory",
    "InsertedScope",
    "external_occlusion",
    "hidden_point_removal",
    "inserted_scope",
    "self_occlusion",
    "surface_samples",
    "thread_grid_memory",
]
