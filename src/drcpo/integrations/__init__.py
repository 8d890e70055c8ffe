"""Adapters that run drcpo inside detector training frameworks.

* :mod:`drcpo.integrations.openpcdet`: a ``drcpo`` entry for OpenPCDet's ``DataAugmentor``.

Each adapter imports its framework only when it is used, so ``import drcpo`` never needs one.
"""
