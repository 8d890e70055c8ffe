"""Test helper shared by the framework tests (each runs in its own environment): counting the
numba kernels drcpo has loaded in a process, to check that a forked worker loads none."""

from __future__ import annotations

import sys

__all__ = ["loaded_kernels"]


def loaded_kernels() -> int:
    """Compiled numba kernels (one per type signature) loaded so far in this process by drcpo's
    modules; each costs a compilation or a load from the disk cache when first called."""
    from numba.core.dispatcher import Dispatcher

    dispatchers = {
        id(value): value
        for name, module in list(sys.modules.items())
        if name.split(".")[0] == "drcpo" and module is not None
        for value in vars(module).values()
        if isinstance(value, Dispatcher)
    }
    return sum(len(d.overloads) for d in dispatchers.values())
