"""make science's live-against-twin part (bench/science_twin.py): from the sweeps' results it
names each side's best Γ, the mean |live − twin| and the verdict, and writes the section.
The sweeps themselves run live pipelines (minutes): here their results.json are written by
hand, so each verdict is known in advance."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from bench import science_twin


def _stat(mean: float, n: int = 4) -> dict[str, Any]:
    return {"mean": mean, "ci95": 0.1, "n": n}


def _sweep(dest: Path, live: dict[str, float], twin: dict[str, float]) -> None:
    """The parts of a results.json of ``aoi3d live sweep --sim-pool`` that science_twin reads:
    one window per policy of 10 decisions, 5 of them rendered, each shown 40 ms late."""
    results, measurements, sim = [], [], {}
    for i, (policy, db) in enumerate(live.items()):
        results.append({"policy": policy, "n": 5, "psnr_display_db": _stat(db, 5),
                        "live_minus_sim_display_db": db - twin[policy]})
        measurements.append({"policy": policy, "first_decision": 10 * i,
                             "last_decision": 10 * i + 9,
                             "qualities": [{"time_ms": t, "display_time_ms": t + 40}
                                           for t in range(5)]})
        sim[policy] = {"psnr_display_db": _stat(twin[policy]),
                       "rendered_fraction": _stat(0.5), "display_lag_ms": _stat(38.0)}
    sim["_config"] = {"pool_workers": 2, "time_scale": 1.0,
                      "job_ms": [[25, 1, 110.0], [25, 18, 140.0], [100, -1, 400.0]]}
    dest.mkdir(parents=True)
    (dest / "results.json").write_text(json.dumps(
        {"results": results, "measurements": measurements, "sim": sim, "wall_s": 100.0,
         "settings": {"settle_s": 10, "measure_s": 40, "repeats": 2}}))


def test_the_verdict_holds_only_for_the_same_best_gamma_within_the_goal(tmp_path: Path) -> None:
    # time scale 0.3: the same best (mat:70), |Δ| 0.2 and 0.0 → mean 0.1: holds
    _sweep(tmp_path / "twin/ts0_3", {"mat:40": 23.0, "mat:70": 24.5, "all": 23.8},
           {"mat:40": 23.2, "mat:70": 24.5, "all": 23.7})
    # time scale 1: close on average, but the twin puts `all` first: does not hold
    _sweep(tmp_path / "twin/ts1", {"mat:40": 21.0, "mat:70": 22.4, "all": 22.3},
           {"mat:40": 21.0, "mat:70": 22.3, "all": 22.5})
    section = science_twin.verdicts(tmp_path)
    slow, real = section["scales"]["0.3"], section["scales"]["1"]
    assert (slow["live_best"], slow["twin_best"], slow["same_best"]) == ("mat:70", "mat:70", True)
    assert abs(slow["mean_abs_diff_db"] - 0.1) < 1e-9 and slow["holds"]
    assert (real["live_best"], real["twin_best"]) == ("mat:70", "all") and not real["holds"]
    row = slow["rows"][0]
    assert row["live_side"] == {"rendered_fraction": 0.5, "display_lag_ms": 40}
    assert row["twin_rendered_fraction"] == 0.5 and slow["twin_seeds"] == 4
    text = "\n".join(science_twin.render_lines(section, "results/science"))
    assert "### Time scale 0.3" in text and "### Time scale 1" in text
    assert "25 steps 110–140 ms (1–18 frames), 100 steps 400 ms" in text
    assert "| mat:70 | 24.50 ± 0.10 (n 5) | 24.50 ± 0.10 | +0.00 | 50% / 50% | 40 / 38 |" in text
    assert "(the same); mean |live − twin| 0.10 dB: **yes**" in text
    assert "(not the same)" in text and text.count("**no**") == 1


def test_a_time_scale_not_run_is_left_out(tmp_path: Path) -> None:
    # both sides 0.5 dB apart (exact in binary floats): at the goal, which holds
    _sweep(tmp_path / "twin/ts1", {"mat:40": 21.0, "all": 22.0}, {"mat:40": 20.5, "all": 21.5})
    section = science_twin.verdicts(tmp_path)
    assert list(section["scales"]) == ["1"]
    v = section["scales"]["1"]
    assert v["same_best"] and v["mean_abs_diff_db"] == 0.5 and v["holds"]
