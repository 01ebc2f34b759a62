"""The suite's one wait: poll until something is true, for a time scaled by the one setting
(:data:`tests.support.timeouts.SCALE`, ``AOI3D_TEST_TIMEOUT_SCALE``)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, TypeVar

from tests.support.timeouts import SCALE

__all__ = ["settle", "wait_for"]

T = TypeVar("T")


def wait_for(check: Callable[[], T], timeout_s: float = 10.0, *, what: str = "",
             every_s: float = 0.01,
             tolerate: tuple[type[BaseException], ...] = ()) -> T:
    """Call ``check`` every ``every_s`` until it returns something truthy, and return that.

    ``timeout_s`` is multiplied by the timeout scale. An exception of a ``tolerate`` type
    (a service not up yet: an HTTP error) counts as "not yet". Past the deadline: an
    AssertionError naming ``what`` (or ``check``) and the last value or error seen."""
    deadline = time.monotonic() + timeout_s * SCALE
    last: Any = None
    while True:
        try:
            last = check()
            if last:
                return last
        except tolerate as err:
            last = err
        if time.monotonic() >= deadline:
            raise AssertionError(f"timed out waiting for {what or check} (last: {last!r})")
        time.sleep(every_s)


def settle(seconds: float) -> None:
    """Wait ``seconds`` × the timeout scale, for a check that something did NOT happen: the
    wait must be long enough that it would have happened were the code wrong, on this machine
    too (a busy one sets the scale above 1)."""
    time.sleep(seconds * SCALE)
