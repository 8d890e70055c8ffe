"""Adapters that run drcpo inside detector training frameworks.

* :mod:`drcpo.integrations.openpcdet`: a ``drcpo`` entry for OpenPCDet's ``DataAugmentor``.
* :mod:`drcpo.integrations.mmdet3d`: MMDetection3D's ``DRCPOAugment`` transform and
  ``DRCPOFadeHook`` (importing it registers them; it needs mmdet3d).

Each adapter imports its framework only when it is used, so ``import drcpo`` never needs one.
"""

__all__: list[str] = []  # one module per framework; importing one needs it
