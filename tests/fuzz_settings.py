"""Hypothesis settings of the fuzz tests (``tests/test_fuzz_*.py``).

The profile ``drcpo-fuzz`` runs ``DRCPO_FUZZ_EXAMPLES`` cases per test (default 200, a few
seconds to tens of seconds per target on two cores); a long run sets it higher, e.g.
``DRCPO_FUZZ_EXAMPLES=20000 python -m pytest -q tests/test_fuzz_hpr.py``.
No deadline: timings on a shared machine vary too much for one.
"""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

DEFAULT_EXAMPLES = 200


def fuzz_examples() -> int:
    value = os.environ.get("DRCPO_FUZZ_EXAMPLES", "")
    try:
        count = int(value) if value else DEFAULT_EXAMPLES
    except ValueError:
        raise ValueError(f"DRCPO_FUZZ_EXAMPLES must be an integer, got {value!r}") from None
    return max(1, count)


settings.register_profile(
    "drcpo-fuzz",
    max_examples=fuzz_examples(),
    deadline=None,
    suppress_health_check=[
        HealthCheck.too_slow,
        HealthCheck.data_too_large,
        HealthCheck.function_scoped_fixture,
    ],
    print_blob=True,
)
FUZZ = settings.get_profile("drcpo-fuzz")
