"""bench/realtime.py's arithmetic: the window's renders per wall second, the share of the
decisions made, the lag's median and p90, each process's CPU with its children's and the
reconstruction workers' share, and the speedup over interleaved runs."""

from __future__ import annotations

from bench import realtime


def quality(decision_id: int, lag_ms: float | None) -> dict:
    t = 30.0 * decision_id
    return {"decision_id": decision_id, "time_ms": t, "psnr_db": 20.0,
            "display_time_ms": None if lag_ms is None else t + lag_ms,
            "psnr_display_db": None if lag_ms is None else 21.0}


def test_the_window_counts_renders_per_wall_second_among_the_decisions_made() -> None:
    history = [quality(1, 50.0)]  # before the window
    history += [quality(d, 100.0 + d) for d in range(11, 21)]  # lags 111 … 120
    history += [quality(21, None), quality(21, None)]  # scored once, no display score
    s = realtime.window_stats(history, 10, 30, 2.0)
    assert (s["decisions"], s["renders"], s["renders_per_s"], s["rendered_share"]) == (
        20, 11, 5.5, 0.55)
    assert s["display_lag_ms_median"] == 115.5 and s["display_lag_ms_p90"] == 119.9
    assert s["psnr_display_db"]["n"] == 10
    one = realtime.window_stats([quality(11, 80.0)], 10, 30, 2.0)
    assert one["display_lag_ms_median"] == 80.0 and one["display_lag_ms_p90"] is None


def test_cpu_is_shared_out_per_process_and_the_workers_share_is_theirs() -> None:
    before = {"recon-1": 0, "recon-2": 0, "metrics": 0, "camera": 50}
    after = {"recon-1": 300, "recon-2": 300, "metrics": 300, "camera": 150}
    ticks = realtime.CLK_TCK
    t = realtime.cpu_table({k: v * ticks // 100 for k, v in before.items()},
                           {k: v * ticks // 100 for k, v in after.items()}, 10.0)
    assert t["processes"]["recon-1"]["core_pct"] == 30.0
    assert t["processes"]["camera"]["core_pct"] == 10.0
    assert t["total_core_pct"] == 100.0 and t["recon_share"] == 0.6
    assert list(t["processes"])[-1] == "camera"  # the heaviest first


def test_the_speedup_is_the_means_of_interleaved_runs_and_each_pair() -> None:
    rows = [{"workers": w, "renders_per_s": r} for w, r in ((1, 10.0), (2, 16.0), (1, 8.0),
                                                            (2, 14.0))]
    assert realtime.speedup(rows) == {"speedup": round(15.0 / 9.0, 2),
                                      "speedup_pairs": [1.6, 1.75]}
    assert realtime.speedup(rows[:1]) == {}
