"""The budget of a decision and the lag to its display (aoi3d.policy.budget, the compute-aware
kinds of aoi3d.policy.display) — the spec and JSON forms and their refusals, the lag model and
its live estimate, the two compute-aware kinds, the decision step, and the virtual clock that
trains and charges each decision's budget."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aoi3d.experiment import EpisodeConfig, plan_episode, run_plan
from aoi3d.experiment.episode import plan_key
from aoi3d.policy import (
    BUDGET_MAX_STEPS,
    Budgeted,
    DeadlinePolicy,
    DisplayLag,
    DisplayMatPolicy,
    LagEstimator,
    PolicySpecError,
    decide,
    parse_policy,
    policy_from_json,
)
from aoi3d.scene import SceneDataset
from tests.support.tiny import TINY_FIELD

NAN = math.nan


@pytest.mark.parametrize("spec", ["mat:70@50", "freshest:6@25", "all@100", "wait:40@10",
                                  "dmat:100@50", f"mat:70@{BUDGET_MAX_STEPS}"])
def test_a_budget_round_trips_through_spec_and_json(spec: str) -> None:
    policy = parse_policy(spec)
    assert isinstance(policy, Budgeted) and policy.spec == spec
    assert policy.budget_steps == int(spec.rsplit("@", 1)[1])
    assert policy_from_json(policy.to_json()).spec == spec
    assert parse_policy(spec.split("@")[0]).budget_steps is None  # no budget: the caller's


@pytest.mark.parametrize(("spec", "why"), [
    ("mat:70@0", "1 … 100000"), (f"mat:70@{BUDGET_MAX_STEPS + 1}", "1 … 100000"),
    ("mat:70@x", "not a whole number"), ("mat:70@1e3", "not a whole number"),
    ("mat:70@-5", "not a whole number"), ("mat:70@²", "not a whole number"),
    ("@5", "nothing before"),
    ("mat:70@50@25", "one budget"), ("deadline:100:60@25", "chooses each decision's budget")])
def test_a_bad_budget_is_refused_saying_why(spec: str, why: str) -> None:
    with pytest.raises(PolicySpecError, match=why):
        parse_policy(spec)


@pytest.mark.parametrize("value", [0, BUDGET_MAX_STEPS + 1, True, 2.5, "50"])
def test_a_bad_json_budget_is_refused(value: object) -> None:
    with pytest.raises(PolicySpecError):
        policy_from_json({"kind": "mat", "mat_ms": 70, "budget_steps": value})


def test_the_display_lag_is_queue_plus_fixed_plus_steps() -> None:
    lag = DisplayLag(fixed_ms=1.6, step_ms=0.34, queue_ms=10.0, default_steps=100)
    assert lag.lag_ms() == pytest.approx(10.0 + 1.6 + 34.0)
    assert lag.lag_ms(50) == pytest.approx(10.0 + 1.6 + 17.0)
    assert lag.at(25).lag_ms() == pytest.approx(lag.lag_ms(25))
    with pytest.raises(ValueError, match="step_ms"):
        DisplayLag(fixed_ms=1.0, step_ms=-1.0)
    with pytest.raises(ValueError, match="queue_ms"):
        DisplayLag(fixed_ms=1.0, step_ms=1.0, queue_ms=math.inf)


def test_the_lag_estimator_learns_from_renders() -> None:
    est = LagEstimator(step_ms_prior=0.5, min_renders=3)
    assert est.estimate() is None
    assert not est.observe(25, NAN) and not est.observe(25, -1.0)  # ignored
    for lag in (30.0, 32.0, 34.0):  # one budget: the prior slope, the rest in the intercept
        assert est.observe(40, lag)
    one = est.estimate()
    assert one is not None and one.step_ms == 0.5 and one.default_steps == 40
    assert one.lag_ms(40) == pytest.approx(32.0)
    est2 = LagEstimator(step_ms_prior=0.5)
    for steps in (10, 20, 40, 80):  # two or more budgets: the slope is fitted
        est2.observe(steps, 5.0 + 2.0 * steps)
    two = est2.estimate()
    assert two is not None and two.step_ms == pytest.approx(2.0)
    assert two.fixed_ms == pytest.approx(5.0)
    window = LagEstimator(0.5, window=4)
    for k in range(10):
        window.observe(10, float(k))
    assert len(window) == 4


def test_dmat_selects_on_the_age_at_display_and_is_mat_without_a_lag() -> None:
    aoi = np.array([10.0, 40.0, 60.0, NAN])
    dmat = DisplayMatPolicy(70.0)
    assert dmat.select(aoi).tolist() == [True, True, True, False]  # no lag: mat:70
    dmat.observe_lag(DisplayLag(fixed_ms=0.0, step_ms=0.2, default_steps=100))  # L = 20
    assert dmat.select(aoi).tolist() == [True, True, False, False]
    budgeted = parse_policy("dmat:70@250")  # L = 50 at its own budget
    budgeted.observe_lag(DisplayLag(fixed_ms=0.0, step_ms=0.2, default_steps=100))
    assert budgeted.select(aoi).tolist() == [True, False, False, False]


def test_deadline_takes_the_largest_budget_on_screen_in_time() -> None:
    policy = DeadlinePolicy(100.0, 40.0)
    assert policy.budget_for(np.zeros(3)) is None  # no lag known: the caller's default
    policy.observe_lag(DisplayLag(fixed_ms=5.0, step_ms=0.2, queue_ms=10.0))
    assert policy.budget_for(np.zeros(3)) == 100  # 10 + 5 + 20 <= 40 < 10 + 5 + 30
    policy.observe_lag(DisplayLag(fixed_ms=5.0, step_ms=0.2, queue_ms=60.0))
    assert policy.budget_for(np.zeros(3)) == 10  # nothing fits: the smallest


def test_the_decision_step_carries_the_budget_and_the_expected_lag() -> None:
    newest = np.array([990.0, 950.0, 900.0, NAN])
    lag = DisplayLag(fixed_ms=1.6, step_ms=0.34, default_steps=300)
    plain = decide(parse_policy("mat:70"), 1000, lambda s: newest, lag=lag)
    assert plain.budget_steps is None and plain.lag_ms == pytest.approx(1.6 + 0.34 * 300)
    budgeted = decide(parse_policy("mat:70@50"), 1000, lambda s: newest, lag=lag)
    assert budgeted.budget_steps == 50 and budgeted.lag_ms == pytest.approx(1.6 + 17.0)
    assert budgeted.mask.tolist() == plain.mask.tolist()  # the budget changes no selection
    assert math.isnan(decide(parse_policy("all@5"), 1000, lambda s: newest).lag_ms)


@pytest.fixture(scope="module")
def cfg(dataset: SceneDataset) -> EpisodeConfig:
    return EpisodeConfig(dataset=str(dataset.root), field=dict(TINY_FIELD), warmup_ms=150,
                         scored_ms=90, score_every=1, steps_per_epoch=2, carry="fresh",
                         lpips=False)


def test_the_virtual_clock_trains_and_charges_each_decisions_budget(
        cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    results = {}
    for spec in ("mat:70", "mat:70@2", "mat:70@5"):
        plan = plan_episode(cfg, dataset, spec, seed=3)
        assert all(d.budget_steps == (None if "@" not in spec else int(spec[-1]))
                   for d in plan.decisions)
        results[spec] = run_plan(plan, dataset)[0]
    steps = {s: {e.steps for e in r.epochs} for s, r in results.items()}
    assert steps == {"mat:70": {2}, "mat:70@2": {2}, "mat:70@5": {5}}
    # the same selections and steps: the same numbers; more steps: more compute charged
    assert [e.psnr_db for e in results["mat:70"].epochs] == \
        [e.psnr_db for e in results["mat:70@2"].epochs]
    assert results["mat:70@5"].compute_ms == pytest.approx(cfg.compute_ms(5))
    assert results["mat:70"].compute_ms == pytest.approx(cfg.compute_ms(2))


def test_a_plan_without_a_budget_keeps_its_cache_key(cfg: EpisodeConfig,
                                                     dataset: SceneDataset) -> None:
    plan = plan_episode(cfg, dataset, "mat:70", seed=3)
    assert all("budget_steps" not in d.to_dict() for d in plan.decisions)
    budgeted = plan_episode(cfg, dataset, "mat:70@2", seed=3)
    assert plan_key(plan, dataset, lpips=False) != plan_key(budgeted, dataset, lpips=False)


def test_the_warm_carry_refuses_a_budget(cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    with pytest.raises(ValueError, match="warm carry"):
        plan_episode(cfg.with_(carry="warm"), dataset, "mat:70@5", seed=3)
