"""The one setting every wait of the suite scales with: ``AOI3D_TEST_TIMEOUT_SCALE``.

A busy machine (CI beside other work) sets it above 1 (3: every wait three times longer). Unset
or empty means 1; anything else must be a positive number, and a wrong value fails the
collection with one line that names the variable (not a ValueError in 17 files)."""

from __future__ import annotations

import math
import os

__all__ = ["SCALE", "timeout_scale"]

VARIABLE = "AOI3D_TEST_TIMEOUT_SCALE"


def timeout_scale(environ: dict[str, str] | None = None) -> float:
    """The factor every wait is multiplied by."""
    raw = (os.environ if environ is None else environ).get(VARIABLE, "").strip()
    if not raw:
        return 1.0
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{VARIABLE}={raw!r}: a positive number of times longer to wait "
                         "(e.g. 3 on a busy machine), or unset for 1")
    return value
SCALE = timeout_scale()
