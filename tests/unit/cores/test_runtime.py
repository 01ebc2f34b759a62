"""The runtime every service worker shares (services/kit/runtime.py): its threads."""

from __future__ import annotations

import logging
import threading
import time

import pytest

from services.kit.runtime import Loops, guarded
from tests.support.waits import settle, wait_for


def test_loops_run_until_stopped_and_say_which_is_not_running() -> None:
    loops = Loops("svc")
    ticks: list[float] = []
    seen = threading.Event()
    loops.every("tick", 0.01, lambda: ticks.append(time.monotonic()))
    loops.thread("own", lambda stop: (seen.set(), stop.wait()))
    assert loops.not_running() == "not started"
    loops.start()
    wait_for(lambda: len(ticks) >= 3 and seen.is_set())
    assert loops.not_running() is None
    assert loops.stop(timeout_s=2.0) == [] and loops.stopping
    n = len(ticks)
    settle(0.2)  # 20 periods of the 10-ms loop: a loop still running would tick
    assert len(ticks) == n  # stopped for good
    assert loops.not_running() == "tick thread not running"


def test_a_failing_step_is_logged_and_the_loop_goes_on(caplog: pytest.LogCaptureFixture) -> None:
    loops = Loops("svc")
    calls = []

    def step() -> None:
        calls.append(1)
        time.sleep(0.001)
        if len(calls) == 1:
            raise RuntimeError("a bug")

    loops.forever("work", step)
    with caplog.at_level(logging.ERROR):
        loops.start()
        wait_for(lambda: len(calls) >= 3)
        loops.stop()
    assert any("svc work failed" in r.getMessage() for r in caplog.records)


def test_a_target_that_returns_shows_in_readiness() -> None:
    loops = Loops("svc")
    loops.thread("once", lambda stop: None)
    loops.start()
    wait_for(lambda: loops.not_running() is not None)
    assert loops.not_running() == "once thread not running"
    loops.stop()


def test_loops_are_planned_once_and_before_start() -> None:
    loops = Loops("svc")
    loops.forever("a", lambda: time.sleep(0.01))
    with pytest.raises(ValueError, match="already planned"):
        loops.forever("a", lambda: None)
    with pytest.raises(ValueError, match="period_s"):
        loops.every("b", 0.0, lambda: None)
    loops.start()
    with pytest.raises(RuntimeError, match="before start"):
        loops.forever("c", lambda: None)
    with pytest.raises(RuntimeError, match="already started"):
        loops.start()
    loops.stop()


def test_guarded_returns_the_value_or_none_after_logging(caplog) -> None:
    assert guarded("adding", lambda a, b: a + b, 1, b=2) == 3
    with caplog.at_level(logging.ERROR):
        assert guarded("dividing", lambda: 1 / 0) is None
    assert "dividing failed" in caplog.text
