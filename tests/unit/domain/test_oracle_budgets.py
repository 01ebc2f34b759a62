"""The oracle over (Γ, steps) at display time (``oracle:budgets:<metric>``, issue 40) on a
tiny scene: never below any cell per decision, reaches the best cell, a real episode, the
grid's cells cost nothing once run, and no live policy."""

from __future__ import annotations

import pytest

from aoi3d.experiment import EpisodeConfig, Job, ResultCache, run_jobs, run_oracle, run_plan
from aoi3d.experiment.oracle import (
    BUDGET_GAMMAS,
    BUDGET_STEPS,
    OracleSpecError,
    budget_cells,
    is_oracle_spec,
    parse_oracle,
)
from aoi3d.policy import PolicySpecError, parse_policy, policy_from_json
from aoi3d.scene import SceneDataset
from tests.support.tiny import TINY_FIELD

SEEDS = [0, 1]
SPEC = "oracle:budgets:psnr_display_db"


@pytest.fixture(scope="module")
def cfg(dataset: SceneDataset) -> EpisodeConfig:
    return EpisodeConfig(dataset=str(dataset.root), field=dict(TINY_FIELD), warmup_ms=150,
                         scored_ms=90, score_every=1, steps_per_epoch=4, carry="fresh",
                         lpips=False)


@pytest.fixture(scope="module")
def grid(cfg: EpisodeConfig, dataset: SceneDataset, tmp_path_factory):
    """The cells run as the science grid runs them (compare's jobs), into a cache."""
    cache = ResultCache(tmp_path_factory.mktemp("cache"))
    out = run_jobs(cfg, [Job(c, cfg.delay, s) for s in SEEDS for c in budget_cells()],
                   processes=1, dataset=dataset, cache=cache)
    return cache, out.results


def test_spec_and_cells() -> None:
    spec = parse_oracle(SPEC)
    assert (spec.search, spec.metric, spec.sign) == ("budgets", "psnr_display_db", 1.0)
    assert parse_oracle("oracle:budgets").spec == "oracle:budgets:reward"
    assert parse_oracle("oracle:rules:reward_display").metric == "reward_display"
    assert parse_oracle("oracle:budgets:lpips_display").sign == -1.0
    with pytest.raises(OracleSpecError, match="budgets"):
        parse_oracle("oracle:budget")
    assert is_oracle_spec(SPEC)
    cells = budget_cells()
    assert len(cells) == len(set(cells)) == (len(BUDGET_GAMMAS) + 1) * len(BUDGET_STEPS)
    assert cells[0] == "mat:40@25" and cells[-1] == "all@100"
    assert {parse_policy(c).budget_steps for c in cells} == set(BUDGET_STEPS)


def test_a_bound_is_refused_where_a_policy_is_expected() -> None:
    """Live (PUT /policy, the scheduler) takes policies through parse_policy /
    policy_from_json: the bound is refused there, saying it is a bound."""
    for make, spec in ((parse_policy, SPEC),
                       (policy_from_json, {"kind": "oracle", "search": "budgets",
                                           "metric": "psnr_display_db"})):
        with pytest.raises(PolicySpecError, match=r"bound.*not a policy"):
            make(spec)  # type: ignore[operator]


def test_never_below_a_cell_and_reaches_the_best(cfg: EpisodeConfig, dataset: SceneDataset,
                                                 grid) -> None:
    cache, cells = grid
    bound = run_oracle(cfg, SPEC, SEEDS, cache=cache, processes=1, dataset=dataset)
    # every cell was in the cache: the grid's episodes are the candidates, free (cells whose
    # plans coincide, mat:160@s and all@s on this tiny rig, share one key)
    assert bound.computed == 0 and 0 < bound.cached <= len(budget_cells()) * len(SEEDS)
    assert bound.cost()["counted"] == "cell episodes"
    by_seed = {r.seed: r for r in bound.results}
    assert all(r.policy == SPEC for r in bound.results)
    for seed, mine in by_seed.items():
        theirs = [r for r in cells if r.seed == seed]
        for j, e in enumerate(mine.epochs):
            scores = [r.epochs[j].psnr_display_db for r in theirs]
            assert all(r.epochs[j].decision_ms == e.decision_ms for r in theirs)
            assert e.psnr_display_db >= max(scores) - 1e-9  # ≥ every cell, per decision
            assert e.psnr_display_db == pytest.approx(max(scores), abs=1e-9)  # one of them
        assert mine.psnr_display_db >= max(r.psnr_display_db for r in theirs) - 1e-9
    searches = [d for e in bound.episodes for d in e.decisions]
    assert {d.candidates for d in searches} == {len(budget_cells())}
    assert all(d.cell in budget_cells() for d in searches)
    assert all(d.to_dict()["cell"] == d.cell for d in searches)


def test_the_budget_bound_is_a_real_episode(cfg: EpisodeConfig, dataset: SceneDataset,
                                            grid) -> None:
    """Replayed as one plan (the chosen selection and budget at each decision), the oracle's
    episode scores what its search found: the decisions are independent under 'fresh'."""
    cache, _ = grid
    bound = run_oracle(cfg, SPEC, [1], cache=cache, processes=1, dataset=dataset)
    episode = bound.episodes[0]
    scored = [d for d in episode.plan.decisions if d.scored]
    assert [d.budget_steps for d in scored] == [
        parse_policy(s.cell).budget_steps for s in episode.decisions]
    replay, _ = run_plan(episode.plan, dataset)
    assert [e.psnr_display_db for e in replay.epochs] == pytest.approx(
        [e.psnr_display_db for e in episode.result.epochs], abs=1e-9)
    assert [e.steps for e in replay.epochs] == [e.steps for e in episode.result.epochs]


def test_the_budget_bound_needs_the_fresh_carry(cfg: EpisodeConfig,
                                                dataset: SceneDataset) -> None:
    with pytest.raises(ValueError, match="fresh"):
        run_oracle(cfg.with_(carry="stream", render_steps=2), SPEC, [0], processes=1,
                   dataset=dataset)
