"""The budget in the decision (issue 40): the ``@<steps>`` spec and its JSON form, the display
lag L and its live estimate, the compute-aware kinds ``dmat`` and ``deadline``, the decision
step's budget, and the virtual clock that trains and charges each decision's budget (tiny
scene) — a policy without a budget gives the numbers it gave before."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

from aoi3d.experiment import EpisodeConfig, plan_episode, plan_key, run_plan
from aoi3d.experiment.episode import display_lag
from aoi3d.experiment.episode.plan import EpisodePlan, PlannedDecision, render_budget
from aoi3d.policy import (
    BUDGET_MAX_STEPS,
    Budgeted,
    DeadlinePolicy,
    DisplayLag,
    DisplayMatPolicy,
    LagEstimator,
    MatPolicy,
    PolicySpecError,
    check_budget,
    decide,
    parse_policy,
    policy_from_json,
)
from aoi3d.policy.budget import split_budget
from aoi3d.policy.display import BUDGET_CHOICES
from aoi3d.scene import SceneDataset
from tests.support.tiny import TINY_FIELD


# --- the spec and the JSON form ---------------------------------------------------------------
@pytest.mark.parametrize(("spec", "doc"), [
    ("mat:70@50", {"kind": "mat", "mat_ms": 70, "budget_steps": 50}),
    ("freshest:6@25", {"kind": "freshest", "k": 6, "budget_steps": 25}),
    ("all@100", {"kind": "all", "budget_steps": 100}),
    ("wait:40@10", {"kind": "wait", "wait_ms": 40, "budget_steps": 10}),
    ("dmat:100@50", {"kind": "dmat", "mat_ms": 100, "budget_steps": 50}),
    (f"mat:70@{BUDGET_MAX_STEPS}", {"kind": "mat", "mat_ms": 70,
                                    "budget_steps": BUDGET_MAX_STEPS}),
    ("mat:70@1", {"kind": "mat", "mat_ms": 70, "budget_steps": 1}),
])
def test_a_budget_round_trips_through_the_spec_and_the_json_form(spec: str, doc: dict) -> None:
    policy = parse_policy(spec)
    assert isinstance(policy, Budgeted)
    assert policy.spec == spec and policy.to_json() == doc
    assert policy.budget_steps == doc["budget_steps"]
    assert policy_from_json(doc) == policy == parse_policy(policy.spec)
    assert policy_from_json(policy.to_json()).spec == spec
    # the inner policy is untouched: the same spec, no budget
    assert policy.inner.budget_steps is None and policy.inner.spec == spec.rsplit("@", 1)[0]
    assert parse_policy(f" {spec.replace('@', ' @ ')} ").spec == spec  # spaces around '@'


def test_without_a_budget_nothing_changes() -> None:
    policy = parse_policy("mat:70")
    assert not isinstance(policy, Budgeted) and policy.budget_steps is None
    assert "budget_steps" not in policy.to_json()
    assert policy_from_json({"kind": "mat", "mat_ms": 70, "budget_steps": None}) == policy
    assert split_budget("mat:70") == ("mat:70", None)
    assert split_budget("mat:70@50") == ("mat:70", "50")
    # a baseline over a policy names a policy after its '@', not a budget
    assert split_budget("wsum:60@mat:130") == ("wsum:60@mat:130", None)


@pytest.mark.parametrize(("spec", "problem"), [
    ("mat:70@0", "budget must be 1 … 100000 steps, got 0"),
    ("mat:70@100001", "budget must be 1 … 100000 steps, got 100001"),
    ("mat:70@x", "budget 'x' after '@' is not a whole number"),
    ("mat:70@1e3", "budget '1e3' after '@' is not a whole number"),
    ("mat:70@5.0", "budget '5.0' after '@' is not a whole number"),
    ("mat:70@-5", "budget '-5' after '@' is not a whole number"),
    ("mat:70@", "budget '' after '@' is not a whole number"),
    ("mat:70@²", "budget '²' after '@' is not a whole number"),  # isdigit, but not int()
    ("@5", "nothing before the budget '@'"),
    ("mat:70@50@25", "a policy has one budget"),
    ("deadline:70:100@50", "deadline chooses each decision's budget itself"),
])
def test_bad_budgets_in_a_spec_are_refused_clearly(spec: str, problem: str) -> None:
    with pytest.raises(PolicySpecError) as err:
        parse_policy(spec)
    assert problem in err.value.problem
    assert "Accepted forms" in str(err.value) and "@<steps>" in str(err.value)


@pytest.mark.parametrize(("steps", "problem"), [
    (0, "1 … 100000 steps, got 0"),
    (100_001, "1 … 100000 steps, got 100001"),
    (-3, "1 … 100000 steps, got -3"),
    (True, "whole number of training steps, got True"),
    (False, "whole number of training steps, got False"),
    (50.0, "whole number of training steps, got 50.0"),
    ("50", "budget_steps must be a JSON integer, got '50'"),
    ("x", "budget_steps must be a JSON integer, got 'x'"),
    ([50], "whole number of training steps, got [50]"),
])
def test_bad_budgets_in_the_json_form_are_refused_clearly(steps: object, problem: str) -> None:
    with pytest.raises(PolicySpecError, match=problem.replace("[", r"\[").replace("]", r"\]")):
        policy_from_json({"kind": "mat", "mat_ms": 70, "budget_steps": steps})


def test_a_budget_on_deadline_is_refused_in_both_forms() -> None:
    with pytest.raises(PolicySpecError, match="chooses each decision's budget"):
        policy_from_json({"kind": "deadline", "mat_ms": 70, "deadline_ms": 100,
                          "budget_steps": 50})
    with pytest.raises(PolicySpecError, match="chooses each decision's budget"):
        parse_policy("deadline:70:100@50")


def test_check_budget() -> None:
    assert check_budget(1) == 1 and check_budget(np.int64(7)) == 7
    assert type(check_budget(np.int64(7))) is int
    for bad in (0, BUDGET_MAX_STEPS + 1, True, 2.0, "3", None):
        with pytest.raises(ValueError, match="my budget"):
            check_budget(bad, name="my budget")
    with pytest.raises(ValueError, match="1 … 100000"):
        Budgeted(MatPolicy(70), 0)


# --- the display lag ----------------------------------------------------------------------------
def test_display_lag_arithmetic() -> None:
    lag = DisplayLag(fixed_ms=10.0, step_ms=2.0, queue_ms=5.0, default_steps=20)
    assert lag.lag_ms() == 5 + 10 + 2 * 20  # the default budget
    assert lag.lag_ms(10) == 5 + 10 + 2 * 10
    assert lag.lag_ms(0) == 15.0
    at = lag.at(50)
    assert at.default_steps == 50 and at.lag_ms() == 5 + 10 + 2 * 50
    assert (at.fixed_ms, at.step_ms, at.queue_ms) == (10.0, 2.0, 5.0)
    assert lag.default_steps == 20  # frozen: at() makes a copy
    assert DisplayLag(0, 0).lag_ms() == 0.0


@pytest.mark.parametrize("bad", [
    {"fixed_ms": -1.0}, {"step_ms": math.nan}, {"queue_ms": math.inf}, {"fixed_ms": True},
    {"step_ms": "2"}, {"default_steps": -1}, {"default_steps": True},
])
def test_display_lag_refuses_bad_numbers(bad: dict) -> None:
    with pytest.raises(ValueError):
        DisplayLag(**{"fixed_ms": 1.0, "step_ms": 1.0, **bad})


def test_the_virtual_clock_lag_is_the_cost_model(dataset: SceneDataset) -> None:
    cfg = EpisodeConfig(dataset=str(dataset.root), carry="fresh", steps_per_epoch=40,
                        time_scale=0.5, compute_fixed_ms=20.0, compute_step_ms=3.0)
    lag = display_lag(cfg)
    assert lag.queue_ms == 0 and lag.default_steps == render_budget(cfg) == 40
    for steps in (1, 25, 100):
        assert lag.lag_ms(steps) == pytest.approx(cfg.compute_ms(steps))
    assert lag.lag_ms() == pytest.approx(cfg.compute_ms(40))


# --- the live estimate -------------------------------------------------------------------------
def test_lag_estimator_uses_the_prior_slope_with_one_budget() -> None:
    est = LagEstimator(step_ms_prior=2.0, min_renders=3)
    assert est.estimate() is None
    est.observe(50, 120.0)
    est.observe(50, 130.0)
    assert est.estimate() is None and len(est) == 2  # fewer than min_renders
    est.observe(50, 140.0)
    lag = est.estimate()
    assert lag is not None
    assert lag.step_ms == 2.0  # one budget: the slope cannot be fitted
    assert lag.fixed_ms == pytest.approx(130.0 - 2.0 * 50)  # the mean lag minus the steps'
    assert lag.default_steps == 50 and lag.queue_ms == 0
    assert lag.lag_ms() == pytest.approx(130.0) and lag.lag_ms(100) == pytest.approx(230.0)


def test_lag_estimator_fits_the_slope_with_two_budgets() -> None:
    est = LagEstimator(step_ms_prior=99.0, min_renders=2)
    for steps, lag_ms in ((25, 60.0), (50, 110.0), (25, 60.0), (100, 210.0)):
        assert est.observe(steps, lag_ms)
    lag = est.estimate()
    assert lag is not None
    assert lag.step_ms == pytest.approx(2.0) and lag.fixed_ms == pytest.approx(10.0)
    assert lag.default_steps == 100  # the newest render's budget
    # a slope that comes out negative (noise) is clamped to 0, and so is the intercept
    neg = LagEstimator(step_ms_prior=1.0, min_renders=2)
    neg.observe(10, 100.0)
    neg.observe(100, 50.0)
    lag = neg.estimate()
    assert lag is not None and lag.step_ms == 0.0 and lag.fixed_ms == pytest.approx(75.0)
    steep = LagEstimator(step_ms_prior=1.0, min_renders=2)
    steep.observe(10, 0.0)
    steep.observe(20, 100.0)
    lag = steep.estimate()
    assert lag is not None and lag.step_ms == pytest.approx(10.0) and lag.fixed_ms == 0.0


def test_lag_estimator_ignores_bad_observations() -> None:
    est = LagEstimator(step_ms_prior=1.0, min_renders=1)
    for steps, lag_ms in ((10, -1.0), (10, math.nan), (10, math.inf), (-1, 10.0)):
        assert not est.observe(steps, lag_ms)
    assert len(est) == 0 and est.estimate() is None
    assert est.observe(0, 0.0)  # a render of no steps at no lag is a render
    assert len(est) == 1


def test_lag_estimator_keeps_a_window() -> None:
    est = LagEstimator(step_ms_prior=0.0, window=4, min_renders=1)
    for _ in range(4):
        est.observe(10, 1000.0)  # an old regime
    for _ in range(4):
        est.observe(10, 20.0)
    assert len(est) == 4
    lag = est.estimate()
    assert lag is not None and lag.lag_ms() == pytest.approx(20.0)  # the old ones are gone


@pytest.mark.parametrize("kwargs", [{"step_ms_prior": -1.0}, {"step_ms_prior": math.nan},
                                    {"step_ms_prior": 1.0, "window": 1},
                                    {"step_ms_prior": 1.0, "min_renders": 0}])
def test_lag_estimator_refuses_bad_settings(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        LagEstimator(**kwargs)


# --- the compute-aware kinds --------------------------------------------------------------------
AOI = np.array([10.0, 45.0, 49.0, 50.0, 69.0, 70.0, 200.0, np.nan])


def test_dmat_selects_on_the_age_at_display() -> None:
    policy = parse_policy("dmat:70")
    assert isinstance(policy, DisplayMatPolicy) and policy.gamma_ms == 70
    # no lag told: it is mat:70
    assert (policy.select(AOI) == MatPolicy(70).select(AOI)).all()
    assert policy.lag_ms() == 0.0
    policy.observe_lag(DisplayLag(fixed_ms=15.0, step_ms=0.25, default_steps=20))  # L = 20
    assert policy.lag_ms() == 20.0
    assert policy.select(AOI).tolist() == [True, True, True, False, False, False, False, False]
    # Δ + L < Γ exactly: Δ = 50 is 70 at display, not under 70
    assert (policy.select(AOI) == MatPolicy(50).select(AOI)).all()
    policy.reset()  # a new episode forgets the lag
    assert policy.lag_ms() == 0.0 and policy.select(AOI)[4]


def test_dmat_with_a_budget_reads_the_lag_at_its_budget() -> None:
    """``dmat:70@40``: the decision trains 40 steps, so L is the lag of 40 steps, whatever
    the caller's default budget."""
    policy = parse_policy("dmat:70@40")
    lag = DisplayLag(fixed_ms=5.0, step_ms=0.5, default_steps=100)  # default: L = 55
    sel = decide(policy, 300, lambda s: s - AOI, lag=lag)
    assert sel.budget_steps == 40 and sel.lag_ms == 25.0  # 5 + 0.5·40
    expected = (AOI + 25.0 < 70)
    assert sel.mask.tolist() == expected.tolist()
    plain = decide(parse_policy("dmat:70"), 300, lambda s: s - AOI, lag=lag)
    assert plain.budget_steps is None and plain.lag_ms == 55.0
    assert plain.mask.tolist() == (AOI + 55.0 < 70).tolist()


def test_deadline_picks_the_largest_budget_within_its_deadline() -> None:
    policy = parse_policy("deadline:200:100")
    assert isinstance(policy, DeadlinePolicy) and policy.spec == "deadline:200:100"
    assert policy.to_json() == {"kind": "deadline", "mat_ms": 200, "deadline_ms": 100}
    assert policy_from_json(policy.to_json()) == policy
    assert policy.budget_for(AOI) is None  # no lag known: the caller's default
    policy.observe_lag(DisplayLag(fixed_ms=10.0, step_ms=1.0))
    # 10 + b ≤ 100: 75 fits, 100 does not
    assert policy.budget_for(AOI) == 75
    assert policy.lag_ms() == 85.0
    assert policy.select(AOI).tolist() == (AOI + 85.0 < 200).tolist()
    # a longer queue buys fewer steps
    policy.observe_lag(DisplayLag(fixed_ms=10.0, step_ms=1.0, queue_ms=50.0))
    assert policy.budget_for(AOI) == 25
    # a deadline on the edge: exactly on screen at the deadline counts
    policy.observe_lag(DisplayLag(fixed_ms=0.0, step_ms=1.0))
    assert policy.budget_for(AOI) == 100
    # none fits: the smallest choice
    policy.observe_lag(DisplayLag(fixed_ms=1000.0, step_ms=1.0))
    assert policy.budget_for(AOI) == min(BUDGET_CHOICES)
    # everything fits: the largest
    policy.observe_lag(DisplayLag(fixed_ms=0.0, step_ms=0.0))
    assert policy.budget_for(AOI) == max(BUDGET_CHOICES)
    policy.reset()
    assert policy.budget_for(AOI) is None


def test_decide_fills_the_budget_and_the_lag() -> None:
    newest = lambda s: s - AOI  # noqa: E731 - U(s) such that Δ(s) = AOI
    lag = DisplayLag(fixed_ms=10.0, step_ms=2.0, default_steps=20)
    sel = decide(parse_policy("mat:70@50"), 300, newest, lag=lag)
    assert sel.budget_steps == 50 and sel.lag_ms == 110.0
    assert sel.mask.tolist() == MatPolicy(70).select(AOI).tolist()  # the selection: mat's
    sel = decide(parse_policy("mat:70"), 300, newest, lag=lag)
    assert sel.budget_steps is None and sel.lag_ms == 50.0  # the caller's default budget
    sel = decide(parse_policy("mat:70@50"), 300, newest)
    assert sel.budget_steps == 50 and math.isnan(sel.lag_ms)  # no lag given
    sel = decide(parse_policy("deadline:200:100"), 300, newest, lag=lag)
    assert sel.budget_steps == 25 and sel.lag_ms == 60.0  # 10 + 2·b ≤ 100: b = 25 (50: 110)

    class Greedy(MatPolicy):
        def budget_for(self, aoi_ms: np.ndarray) -> int:
            return 0

    with pytest.raises(ValueError, match="budget must be 1"):
        decide(Greedy(70), 300, newest, lag=lag)


# --- the virtual clock ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fresh(dataset: SceneDataset) -> EpisodeConfig:
    """A fresh model per scored decision, a delay short enough that mat:70 uses every camera
    at every decision (so every scored decision trains its budget)."""
    return EpisodeConfig(dataset=str(dataset.root), field=dict(TINY_FIELD), delay="const:20",
                         carry="fresh", warmup_ms=150, scored_ms=60, score_every=1,
                         steps_per_epoch=10, lpips=False)


def test_plan_records_each_decisions_budget(fresh: EpisodeConfig, dataset: SceneDataset) -> None:
    plan = plan_episode(fresh, dataset, "mat:70@25", 3)
    assert plan.policy == "mat:70@25"
    assert {d.budget_steps for d in plan.decisions} == {25}
    doc = plan.decisions[0].to_dict()
    assert doc["budget_steps"] == 25
    assert PlannedDecision.from_dict(doc) == plan.decisions[0]
    # the budget is part of the cache key: the same selections at another budget differ
    other = plan_episode(fresh, dataset, "mat:70@100", 3)
    assert [d.cameras for d in other.decisions] == [d.cameras for d in plan.decisions]
    assert plan_key(plan, dataset, lpips=False) != plan_key(other, dataset, lpips=False)
    # deadline: its budget from the cost model (no queue on the virtual clock: a constant)
    lag = display_lag(fresh)
    deadline_ms = lag.lag_ms(50)
    dl = plan_episode(fresh, dataset, f"deadline:70:{deadline_ms}", 3)
    assert {d.budget_steps for d in dl.decisions} == {50}


@pytest.mark.parametrize("spec", ["mat:70@25", "deadline:70:100"])
def test_the_warm_carry_refuses_a_budget(spec: str, dataset: SceneDataset) -> None:
    warm = EpisodeConfig(dataset=str(dataset.root), field=dict(TINY_FIELD), carry="warm",
                         warmup_ms=150, scored_ms=60, lpips=False)
    with pytest.raises(ValueError, match="the warm carry renders its model as it is"):
        plan_episode(warm, dataset, spec, 3)
    assert plan_episode(warm, dataset, "mat:70", 3).decisions  # without one: as before


def test_run_plan_trains_and_charges_each_decisions_budget(fresh: EpisodeConfig,
                                                           dataset: SceneDataset) -> None:
    results = {}
    for budget in (25, 100):
        plan = plan_episode(fresh, dataset, f"mat:70@{budget}", 3)
        assert all(d.cameras for d in plan.decisions if d.scored)
        result, _png = run_plan(plan, dataset)
        assert len(result.epochs) == 2
        for e in result.epochs:
            assert e.steps == budget  # fresh: a new model trained the decision's budget
            assert e.display_ms - e.eval_ms == pytest.approx(fresh.compute_ms(budget))
        assert result.compute_ms == pytest.approx(fresh.compute_ms(budget))
        assert result.train_steps == 2 * budget
        results[budget] = result
    assert results[25].compute_ms < results[100].compute_ms
    assert [e.psnr_db for e in results[25].epochs] != [e.psnr_db for e in results[100].epochs]


def test_a_policy_without_a_budget_gives_the_numbers_it_gave_before(
        fresh: EpisodeConfig, dataset: SceneDataset) -> None:
    """No budget: the plan has none (its JSON no ``budget_steps`` key, so plans cached before
    the budget existed read the same), the cache key is the one without it, and the episode
    trains the config's steps, as it did."""
    plan = plan_episode(fresh, dataset, "mat:70", 3)
    assert all(d.budget_steps is None for d in plan.decisions)
    assert all("budget_steps" not in d.to_dict() for d in plan.decisions)
    explicit = EpisodePlan(**{**vars(plan), "decisions": tuple(
        replace(d, budget_steps=None) for d in plan.decisions)})
    key = plan_key(plan, dataset, lpips=False)
    assert plan_key(explicit, dataset, lpips=False) == key
    # a budget equal to the config's default trains the same steps, but is a budget: its key
    # differs (it names it), its numbers are the same
    same = plan_episode(fresh, dataset, f"mat:70@{render_budget(fresh)}", 3)
    assert plan_key(same, dataset, lpips=False) != key
    result, _ = run_plan(plan, dataset)
    budgeted, _ = run_plan(same, dataset)
    assert [e.steps for e in result.epochs] == [render_budget(fresh)] * 2
    assert result.compute_ms == pytest.approx(fresh.compute_ms(render_budget(fresh)))
    assert [e.psnr_db for e in result.epochs] == [e.psnr_db for e in budgeted.epochs]
    assert [e.display_ms for e in result.epochs] == [e.display_ms for e in budgeted.epochs]


# --- the command ---------------------------------------------------------------------------------
def test_compare_runs_budgeted_policies_side_by_side(dataset: SceneDataset, tmp_path) -> None:
    from aoi3d_cli.experiment import app

    out = tmp_path / "c"
    args = ["compare", "--policy", "mat:70@50", "--policy", "mat:100@25", "--seeds", "2",
            "--delay", "const:20", "--carry", "fresh", "--dataset", str(dataset.root),
            "--out", str(out), "--cache", str(tmp_path / "cache"), "--processes", "1",
            "--steps-per-epoch", "10", "--no-lpips", "--set", f"field={json.dumps(TINY_FIELD)}",
            "--set", "warmup_ms=150", "--set", "scored_ms=60", "--set", "score_every=1"]
    res = CliRunner().invoke(app, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    with (out / "compare.csv").open() as fh:
        rows = {r["policy"]: r for r in csv.DictReader(fh)}
    assert set(rows) == {"mat:70@50", "mat:100@25"}
    cfg = EpisodeConfig.from_dict(json.loads((out / "results.json").read_text())
                                  ["meta"]["episode_config"])
    assert float(rows["mat:70@50"]["compute_ms"]) == pytest.approx(cfg.compute_ms(50))
    assert float(rows["mat:100@25"]["compute_ms"]) == pytest.approx(cfg.compute_ms(25))
    assert int(rows["mat:70@50"]["n"]) == 2
    doc = json.loads((out / "results.json").read_text())
    as_json = {r["policy"]: r["policy_json"] for r in doc["policies"]}
    assert as_json["mat:70@50"] == {"kind": "mat", "mat_ms": 70, "budget_steps": 50}


@pytest.mark.parametrize("spec", ["mat:70@50", "deadline:70:100"])
def test_compare_refuses_a_budget_under_the_warm_carry_before_running(
        spec: str, dataset: SceneDataset, tmp_path) -> None:
    from aoi3d_cli.experiment import app

    out = tmp_path / "w"
    res = CliRunner().invoke(app, [
        "compare", "--policy", spec, "--policy", "all", "--seeds", "1", "--carry", "warm",
        "--dataset", str(dataset.root), "--out", str(out), "--cache", str(tmp_path / "cache"),
        "--workers", "1", "--no-lpips"])  # --workers: the old name still works
    assert res.exit_code == 2, res.output
    assert "warm carry" in " ".join(res.output.replace("│", "").split())
    assert not (out / "results.json").exists()  # nothing ran
    assert not any((tmp_path / "cache").rglob("*.json"))
