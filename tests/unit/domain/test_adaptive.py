"""The adaptive policies (aoi3d.policy.adaptive): the delay estimator, the Γ curve, the
sliding-window bandit, their specs, and on the virtual clock the plug-in's Γ following a change
of the channel and the stepwise episode (aoi3d.experiment.adaptive) agreeing with the planned
one."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aoi3d.channel import simulate
from aoi3d.experiment import EpisodeConfig, Job, plan_episode, run_jobs, run_plans
from aoi3d.experiment.adaptive import run_stepwise
from aoi3d.experiment.episode import EpisodeLinks, episode_links
from aoi3d.policy import (
    BanditPolicy,
    PluginPolicy,
    PolicySpecError,
    decide,
    parse_policy,
    policy_from_json,
)
from aoi3d.policy.adaptive import (
    DelayEstimator,
    GammaCurve,
    SlidingWindowUCB,
    load_gamma_curve,
)
from aoi3d.scene import SceneDataset
from tests.support.tiny import N_TRAIN, TINY_FIELD

CURVE = GammaCurve((20.0, 100.0, 200.0), (40.0, 130.0, 250.0))


# --- the estimator ---------------------------------------------------------------------------
@given(st.lists(st.integers(0, 1000), min_size=1, max_size=50),
       st.floats(10, 1e5))
def test_the_estimate_lies_between_the_samples(delays: list[int], halflife: float) -> None:
    est = DelayEstimator(halflife)
    for i, y in enumerate(delays):
        est.observe(i * 30.0, i * 30.0 + y)
    assert min(delays) - 1e-6 <= est.mean_ms <= max(delays) + 1e-6
    assert est.count == len(delays)
    assert min(delays) <= est.quantile(0.5) <= max(delays)


def test_the_estimate_forgets_with_its_half_life() -> None:
    est = DelayEstimator(halflife_ms=1000)
    assert math.isnan(est.mean_ms) and math.isnan(est.quantile(0.9))
    for t in range(0, 10_000, 30):
        est.observe(t, t + 20)
    assert est.mean_ms == pytest.approx(20)
    for t in range(10_000, 13_000, 30):  # 3 half-lives of a 200-ms channel
        est.observe(t, t + 200)
    assert 170 < est.mean_ms < 200
    est.observe(5, -1)  # a negative delay is ignored
    est.observe(0, math.nan)
    assert est.count == len(range(0, 13_000, 30))


def test_a_late_report_weighs_by_its_age() -> None:
    est = DelayEstimator(halflife_ms=100)
    est.observe(900, 1000)  # y = 100 at t = 1000
    est.observe(0, 900)  # y = 900 at t = 900: one half-life older, half the weight
    assert est.mean_ms == pytest.approx((100 + 0.5 * 900) / 1.5)


# --- the curve -------------------------------------------------------------------------------
def test_the_curve_interpolates_in_log_delay_and_is_flat_beyond_its_ends() -> None:
    assert CURVE(20) == 40 and CURVE(100) == 130 and CURVE(200) == 250
    assert CURVE(5) == 40 and CURVE(1000) == 250
    assert CURVE(math.nan) == 130  # the middle point before any estimate
    mid = CURVE(math.sqrt(20 * 100))
    assert mid == pytest.approx(85)
    xs = np.geomspace(1, 2000, 50)
    assert np.all(np.diff([CURVE(x) for x in xs]) >= 0)
    with pytest.raises(ValueError):
        GammaCurve((20.0, 20.0), (40.0, 50.0))


def test_the_shipped_curve_is_measured_and_grows() -> None:
    curve = load_gamma_curve()
    assert len(curve.gamma_ms) >= 3 and "aoi3d experiment delay" in curve.source
    assert curve.gamma_ms[-1] > curve.gamma_ms[0]


# --- the bandit ------------------------------------------------------------------------------
def test_ucb_tries_every_arm_then_settles_on_the_best() -> None:
    ucb = SlidingWindowUCB(3, window=30, explore=0.5)
    rng = np.random.default_rng(0)
    means = [20.0, 23.0, 21.0]
    first = []
    for _ in range(60):
        arm = ucb.choose()
        first.append(arm)
        ucb.update(arm, means[arm] + rng.normal(0, 0.3))
    assert first[:3] == [0, 1, 2]
    assert first[-20:].count(1) >= 15


def test_ucb_forgets_beyond_its_window() -> None:
    ucb = SlidingWindowUCB(2, window=10, explore=0.2)
    for _ in range(40):
        a = ucb.choose()
        ucb.update(a, [30.0, 20.0][a])
    assert ucb.choose() == 0
    picks = []
    for _ in range(40):  # the world changes: arm 1 is now the better one
        a = ucb.choose()
        picks.append(a)
        ucb.update(a, [10.0, 20.0][a])
    assert picks[-10:].count(1) >= 8


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 3), st.floats(-50, 50)), max_size=60),
       st.integers(1, 20))
def test_ucb_window_counts(history: list[tuple[int, float]], window: int) -> None:
    ucb = SlidingWindowUCB(4, window=window)
    for a, r in history:
        ucb.update(a, r)
    counts, means = ucb.stats()
    assert counts.sum() == min(len(history), window)
    for a in range(4):
        tail = [r for b, r in history[-window:] if b == a] if history else []
        assert counts[a] == len(tail)
        if tail:
            assert means[a] == pytest.approx(np.mean(tail))
    assert 0 <= ucb.choose() < 4


def test_the_bandit_credits_the_arm_that_decided_and_switches_after_a_reward() -> None:
    pol = BanditPolicy(window=10, arms_ms=(40, 130), explore=0.0)
    aoi = np.array([30.0, 90.0, np.nan])
    pol.observe(0, ())
    assert pol.gamma_ms == 40 and pol.select(aoi).tolist() == [True, False, False]
    pol.observe(30, ())  # no reward yet: the arm stays
    assert pol.gamma_ms == 40
    pol.observe_quality(30, {"psnr_db": 20.0})  # the render for t = 30, decided by Γ 40
    pol.observe(60, ())  # rewarded: the next arm (untried first)
    assert pol.gamma_ms == 130 and pol.select(aoi).tolist() == [True, True, False]
    pol.observe_quality(45, {"psnr_db": 99.0, "reward": 0.5})  # for a time Γ 40 was in force
    pol.observe_quality(60, {"psnr_db": 25.0})
    counts, means = pol.ucb.stats()
    assert counts.tolist() == [2, 1] and means.tolist() == [pytest.approx(59.5), 25.0]
    pol.observe_quality(-5, {"psnr_db": 1.0})  # before any decision: ignored
    pol.observe_quality(60, {"psnr_db": math.nan})
    pol.observe_quality(60, {"reward": 1.0})  # not its metric  # not finite: ignored
    assert pol.ucb.t == 3
    pol.reset()
    assert pol.ucb.t == 0 and pol.gamma_ms == 40


# --- specs -----------------------------------------------------------------------------------
@pytest.mark.parametrize("spec", ["adaptive:plugin", "adaptive:plugin:1500", "adaptive:bandit",
                                  "adaptive:bandit:12", "adaptive:bandit:8:40/100/250:2:reward"])
def test_specs_round_trip(spec: str) -> None:
    pol = parse_policy(spec)
    assert pol.spec == spec
    assert policy_from_json(pol.to_json()).spec == spec
    assert pol.kind == "adaptive" and pol.wait_ms == 0 and not pol.learns
    assert pol.wants_quality == spec.startswith("adaptive:bandit")
    assert parse_policy(spec) == pol


@pytest.mark.parametrize("spec", ["adaptive", "adaptive:foo", "adaptive:plugin:0",
                                  "adaptive:plugin:1:2", "adaptive:bandit:0",
                                  "adaptive:bandit:5:40/40", "adaptive:bandit:5:40:1:lpips"])
def test_bad_specs(spec: str) -> None:
    with pytest.raises(PolicySpecError, match="Accepted forms"):
        parse_policy(spec)


def test_bad_json() -> None:
    for doc in ({"kind": "adaptive"}, {"kind": "adaptive", "mode": "plugin", "x": 1},
                {"kind": "adaptive", "mode": "bandit", "arms_ms": 40}):
        with pytest.raises(PolicySpecError):
            policy_from_json(doc)


def test_the_plugin_follows_its_estimate() -> None:
    pol = PluginPolicy(halflife_ms=500, curve=CURVE)
    assert pol.gamma_ms == 130 and math.isnan(pol.mean_delay_ms)
    pol.observe(100, [(0, 0.0, 20.0), (1, 10.0, 30.0)])
    assert pol.gamma_ms == 40 and pol.status()["samples"] == 2
    aoi = np.array([30.0, 50.0])
    assert pol.select(aoi).tolist() == [True, False]
    pol.reset()
    assert pol.gamma_ms == 130


# --- the virtual clock -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def cfg(dataset: SceneDataset) -> EpisodeConfig:
    return EpisodeConfig(dataset=str(dataset.root), field=dict(TINY_FIELD), warmup_ms=150,
                         scored_ms=90, score_every=1, steps_per_epoch=4, carry="fresh",
                         lpips=False)


def _switching_links(cfg: EpisodeConfig, dataset: SceneDataset, seed: int,
                     switch_ms: int, end_ms: int) -> EpisodeLinks:
    """Links at exp:20 before ``switch_ms`` and exp:200 after: two simulated runs spliced at
    the first frame each link generates at or after the switch."""
    base = episode_links(cfg, dataset, seed)
    fast = simulate("exp:20", cfg.period_ms, N_TRAIN, end_ms, seed, phase_ms=base.phase_ms)
    slow = simulate("exp:200", cfg.period_ms, N_TRAIN, end_ms, seed + 1,
                    phase_ms=base.phase_ms)
    gens, dels = [], []
    for gf, df, gs, ds in zip(fast.gen_ms, fast.delivery_ms, slow.gen_ms, slow.delivery_ms,
                              strict=True):
        keep = df < switch_ms
        last = df[keep][-1] if keep.any() else 0
        later = gs >= max(switch_ms, last)
        gens.append(np.concatenate([gf[keep], gs[later]]))
        dels.append(np.concatenate([df[keep], ds[later]]))
    run = replace(fast, delay_spec="exp:20→exp:200", gen_ms=tuple(gens),
                  delivery_ms=tuple(dels))
    return replace(base, run=run)


def test_the_plugins_gamma_follows_a_change_of_the_channel(cfg: EpisodeConfig,
                                                           dataset: SceneDataset) -> None:
    """On the virtual clock, at exp:20 for 6 s then exp:200: Γ starts near Γ*(20) and ends
    near Γ*(200) within a few half-lives."""
    long = replace(cfg, warmup_ms=150, scored_ms=11_850, score_every=1000)
    links = _switching_links(long, dataset, 7, 6000, long.end_ms + 1)
    pol = PluginPolicy(halflife_ms=600, curve=CURVE)
    feed = links.delivery_feed()
    gammas = {}
    for t in long.decision_times_ms():
        decide(pol, t, links.newest_ms, deliveries=feed)
        gammas[t] = pol.gamma_ms
    assert gammas[5970] < 55  # Γ*(20) = 40
    assert gammas[long.decision_times_ms()[-1]] > 220  # Γ*(200) = 250
    assert 0 < sum(1 for t, g in gammas.items() if t > 6000 and g < 55) < 60  # ≤ 1.8 s late
    # the same through plan_episode: the decisions' selections are Γ's
    plan = plan_episode(long, dataset, pol, 7, links=links)
    last = plan.decisions[-1]
    assert all(a < 250 + 1e-9 for a in last.aoi_ms)


def test_the_plugin_follows_a_regime_schedule(cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    """The same through the channel spec `regimes:` (aoi3d.channel): on the shipped curve, Γ
    sits low in the fast regime and high in the slow one, every time the schedule cycles."""
    long = replace(cfg, delay="regimes:exp:20@3s,exp:200@3s", warmup_ms=150,
                   scored_ms=11_850, score_every=1000)
    curve = load_gamma_curve()
    links = episode_links(long, dataset, 3)
    pol = PluginPolicy()
    feed = links.delivery_feed()
    by_regime: dict[str, list[float]] = {"fast": [], "slow": []}
    for t in long.decision_times_ms():
        decide(pol, t, links.newest_ms, deliveries=feed)
        phase = t % 6000
        if 1500 <= phase < 3000:  # the second half of each regime: the estimate has settled
            by_regime["fast"].append(pol.gamma_ms)
        elif 4500 <= phase < 6000:
            by_regime["slow"].append(pol.gamma_ms)
    assert np.median(by_regime["fast"]) <= curve(40)
    assert np.median(by_regime["slow"]) >= curve(120)


def test_stepwise_episodes_equal_the_planned_ones(cfg: EpisodeConfig,
                                                  dataset: SceneDataset) -> None:
    seeds = [0, 1]
    planned = run_jobs(cfg, [Job(p, cfg.delay, s) for s in seeds
                             for p in ("mat:70", "adaptive:plugin", "wait:40")],
                       processes=1, dataset=dataset).results

    def evaluate(plans):
        return run_plans(plans, processes=1, dataset=dataset).results

    for spec in ("mat:70", "adaptive:plugin", "wait:40"):
        step = run_stepwise(cfg, dataset, spec, seeds, evaluate)
        for ep in step:
            ref = next(r for r in planned if r.policy == spec and r.seed == ep.plan.seed)
            assert ep.result.psnr_db == pytest.approx(ref.psnr_db, abs=1e-9), spec
            assert ep.result.n_selected == pytest.approx(ref.n_selected), spec
            assert [e.eval_ms for e in ep.result.epochs] == [e.eval_ms for e in ref.epochs]
    bandit = run_stepwise(cfg, dataset, "adaptive:bandit:4:40/100", seeds, evaluate)
    for ep in bandit:
        assert ep.result.policy == "adaptive:bandit:4:40/100:1:psnr_db"
        assert {g for g in ep.gamma_ms} <= {40.0, 100.0}
        assert len(ep.result.epochs) == 3
    with pytest.raises(ValueError, match="run_stepwise"):
        plan_episode(cfg, dataset, "adaptive:bandit", 0)
    with pytest.raises(ValueError, match="fresh"):
        run_stepwise(replace(cfg, carry="warm"), dataset, "mat:70", seeds, evaluate)


def test_run_jobs_takes_a_bandit_beside_planned_policies(cfg: EpisodeConfig,
                                                         dataset: SceneDataset) -> None:
    """The sweep runs a policy rewarded by quality step by step, in job order, beside the
    planned ones (so `experiment compare --policy adaptive:bandit` works)."""
    jobs = [Job(p, cfg.delay, s) for s in (0, 1) for p in ("mat:70", "adaptive:bandit:3:40/70")]
    out = run_jobs(cfg, jobs, processes=1, dataset=dataset)
    assert [(r.policy, r.seed) for r in out.results] == [
        ("mat:70", 0), ("adaptive:bandit:3:40/70:1:psnr_db", 0), ("mat:70", 1),
        ("adaptive:bandit:3:40/70:1:psnr_db", 1)]
    assert len(out.plans) == len(out.keys) == 4
    assert all(len(r.epochs) == 3 for r in out.results)
