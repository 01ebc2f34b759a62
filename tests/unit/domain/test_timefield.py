"""Issue 41's question as stated before any run (aoi3d/experiment/timefield.py): its arms at
equal CPU seconds, its static-region PSNR and its goal, on made-up results documents."""

from __future__ import annotations

import math

import pytest

from aoi3d.experiment import timefield as tf

SEEDS = (1, 2, 3, 4)
LABELS = ("40", "70", "100", "130", "160", "all")


def _doc(level: dict[str, float], noise: float = 0.1) -> dict:
    """A tradeoff results document: every Γ at ``level[Γ]`` dB (default 15) in every metric,
    give or take ``noise`` by seed."""
    episodes = []
    for g in LABELS:
        for s in SEEDS:
            v = level.get(g, 15.0) + noise * ((s % 2) - 0.5)
            episodes.append({
                "policy": "all" if g == "all" else f"mat:{g}", "seed": s, "delay": "exp:60",
                "n_selected": 3.0, **{m: v for m in tf.METRICS},
                "epochs": [{"psnr_db": v, "psnr_dynamic_db": v, "dynamic_fraction": 0.1}]})
    return {"episodes": episodes}


def _analysis(flow: dict[str, dict[str, float]]) -> dict:
    static = {"grid-fresh-50": {"40": 17.0}, "grid-fresh-100": {"40": 16.5},
              "grid-stream-25": {"all": 16.0}}
    docs = {a.name: _doc(static.get(a.name, {}) if not a.time_aware else flow.get(a.name, {}))
            for a in tf.ARMS}
    return tf.analyse({"exp:60": docs})


def test_each_static_arm_has_a_time_aware_twin_at_the_same_cpu() -> None:
    static = [a for a in tf.ARMS if not a.time_aware]
    assert [a.name for a in static] == ["grid-fresh-50", "grid-fresh-100", "grid-stream-25"]
    for a in static:
        twin = tf.twin(a)
        assert twin in tf.ARMS and twin.level == a.level and twin.carry == a.carry
        assert twin.cost == pytest.approx(a.cost, rel=0.02)
        assert "flow" in twin.options() and any(o.startswith("compute_step_ms=")
                                                 for o in twin.options())
    assert tf.ARMS[-1].options()[-4:-2] == ["--set", "render_steps=16"]


def test_the_static_region_psnr_takes_the_moving_pixels_out() -> None:
    doc = {"episodes": [{"policy": "mat:40", "seed": 1, "epochs": [
        {"psnr_db": 20.0, "psnr_dynamic_db": 15.0, "dynamic_fraction": 0.1}]}]}
    mse = (0.01 - 0.1 * 10 ** -1.5) / 0.9
    assert tf.static_psnr(doc)["40"][1] == pytest.approx(-10 * math.log10(mse))


def test_the_goal_lets_the_time_aware_field_spend_no_more_cpu_than_the_best_static() -> None:
    # the best static: grid-fresh-50 at Γ = 40 (17 dB); flow-stream-16 (cheaper) 2 dB above
    a = _analysis({"flow-stream-16": {"all": 19.0}})
    v = tf.goal(a, "exp:60")
    assert v.holds, v.evidence
    assert v.numbers["static"] == {"arm": "grid-fresh-50", "gamma": "40"}
    assert v.numbers["time_aware"] == {"arm": "flow-stream-16", "gamma": "all"}
    assert v.numbers["difference"]["mean"] == pytest.approx(2.0)
    # a better time-aware field that costs more (fresh@100) does not count against fresh@50
    b = tf.goal(_analysis({"flow-fresh-65": {"130": 30.0}, "flow-fresh-32": {"100": 17.5}}),
                "exp:60")
    assert not b.holds and b.numbers["time_aware"]["arm"] == "flow-fresh-32"
    assert b.numbers["difference"]["mean"] == pytest.approx(0.5)
    # 1 dB asked, 0.9 dB found: no
    assert not tf.goal(_analysis({"flow-fresh-32": {"70": 17.9}}), "exp:60").holds
    # the levels compare each twin with its static arm at their own best Γ
    lv = a["exp:60"]["levels"]["stream@25"][tf.DISPLAY]
    assert (lv["time_aware"], lv["static"], round(lv["mean"], 6)) == ("all", "all", 3.0)
