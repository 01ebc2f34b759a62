"""bench/live_default.py's arithmetic: a configuration named on the command line is the
environment a user would set, and a window's share scored, display lag and PSNR come from the
decision ids the scheduler made in it (a decision never scored counts against the share)."""

from __future__ import annotations

import pytest

from bench import live_default


def test_a_configuration_is_the_environment_a_user_sets() -> None:
    assert live_default.parse_config("default") == ("default", {})
    assert live_default.parse_config(" stream@25") == (
        "stream@25", {"AOI3D_DISPATCHER_CARRY": "stream", "AOI3D_DISPATCHER_RENDER_STEPS": "25"})
    assert live_default.parse_config("default/all") == (
        "default/all", {"AOI3D_SCHEDULER_POLICY": "all"})
    assert live_default.parse_config("fresh@100/mat:130")[1] == {
        "AOI3D_DISPATCHER_CARRY": "fresh", "AOI3D_DISPATCHER_RENDER_STEPS": "100",
        "AOI3D_SCHEDULER_POLICY": "mat:130"}
    for bad in ("stream", "stream@", "@25", "fresh@0", "fresh@x", "fresh@-3", "stream/all"):
        with pytest.raises(ValueError, match="CARRY@STEPS"):
            live_default.parse_config(bad)
    with pytest.raises(ValueError, match="default/mat:x"):
        live_default.parse_config("default/mat:x")


def quality(decision_id: int, lag_ms: float | None, psnr: float, display: float | None) -> dict:
    t = 1000.0 + 100.0 * decision_id
    return {"decision_id": decision_id, "time_ms": t, "psnr_db": psnr,
            "display_time_ms": None if lag_ms is None else t + lag_ms,
            "psnr_display_db": display}


def test_the_window_counts_the_decisions_made_not_only_those_scored() -> None:
    history = [quality(2, 40.0, 20.0, 19.0),     # before the window: not counted
               quality(3, 50.0, 25.0, 24.0),
               quality(3, 50.0, 25.0, 24.0),     # the same decision twice counts once
               quality(5, 70.0, 27.0, 22.0),
               quality(6, None, 26.0, None),     # no display score: no lag either
               quality(8, 300.0, 21.0, 18.0),
               quality(12, 10.0, 30.0, 30.0)]    # after the window: not counted
    s = live_default.window_stats(history, first_id=2, last_id=10)
    assert (s["decisions"], s["scored"]) == (8, 4)
    assert s["scored_share"] == 0.5
    assert s["scored_share_of_span"] == pytest.approx(4 / 6)  # ids 3…8
    assert s["display_lag_ms_median"] == 70.0 and s["display_lag_ms_mean"]["n"] == 3
    assert s["psnr_db_median"] == 25.5 and s["psnr_db"]["n"] == 4
    assert s["psnr_display_db_median"] == 22.0


def test_an_empty_window_says_so() -> None:
    s = live_default.window_stats([quality(1, 10.0, 20.0, 20.0)], first_id=5, last_id=5)
    assert (s["decisions"], s["scored"], s["scored_share"]) == (0, 0, None)
    assert s["display_lag_ms_median"] is None and s["psnr_display_db_median"] is None
