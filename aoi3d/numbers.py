"""Numbers in specs: the one way a number is written into a text spec.

Every spec that carries a number (``mat:51``, ``exp:60``, ``wsum:60``, ``tembed:2:300``) is
written with :func:`format_number`, so a spec read back and written again is the same text.
"""

from __future__ import annotations

__all__ = ["format_number"]


def format_number(x: float) -> str:
    """Shortest round-tripping text of ``x``: ``60`` rather than ``60.0``."""
    x = float(x)
    return str(int(x)) if x.is_integer() and abs(x) < 1e15 else repr(x)
