"""The fuzz tests' budget (issue 44): every property-based test of a hostile input takes its
number of examples from here. ``make test`` runs each with its base count (a few seconds);
``AOI3D_FUZZ_DEPTH=N`` multiplies every count by N (``make fuzz`` sets 20), and the REST
fuzz's examples per operation are ``AOI3D_FUZZ_EXAMPLES`` (15 by default)."""

from __future__ import annotations

import math
import os

from hypothesis import HealthCheck, settings

DEPTH_VARIABLE = "AOI3D_FUZZ_DEPTH"


def fuzz_depth() -> float:
    raw = os.environ.get(DEPTH_VARIABLE, "").strip()
    if not raw:
        return 1.0
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{DEPTH_VARIABLE}={raw!r}: a positive factor of the fuzz tests' "
                         "examples (20 for `make fuzz`), or unset for 1")
    return value


def fuzz(base: int) -> settings:
    """Hypothesis settings of ``base`` examples × the depth: no deadline (the tests time
    each example themselves), no example database, no health check that a slow machine
    trips."""
    return settings(max_examples=max(1, round(base * fuzz_depth())), deadline=None,
                    database=None, suppress_health_check=list(HealthCheck))
