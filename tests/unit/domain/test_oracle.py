"""The oracle bound (aoi3d.experiment.oracle) and the baselines as compare options, on a tiny
scene: the bound is never below what it searches over, is a real episode, pairs by seed; the
CLI takes and refuses the new specs."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from aoi3d.experiment import (
    EpisodeConfig,
    Job,
    ResultCache,
    plan_episode,
    plan_key,
    run_jobs,
    run_oracle,
    run_plan,
)
from aoi3d.experiment.baselines import (
    TrainerSpecError,
    baseline_label,
    is_trainer_spec,
    split_baseline,
)
from aoi3d.experiment.oracle import (
    OracleSpec,
    OracleSpecError,
    is_oracle_spec,
    parse_oracle,
    rule_masks,
)
from aoi3d.policy import FreshestPolicy, MatPolicy
from aoi3d.scene import SceneDataset
from tests.support.tiny import N_TRAIN, TINY_FIELD  # the same tiny rig and field

SEEDS = [0, 1, 2]
RULES = ["all", "mat:40", "mat:70", "mat:100", "mat:130",
         *(f"freshest:{k}" for k in range(1, N_TRAIN + 1))]


@pytest.fixture(scope="module")
def cfg(dataset: SceneDataset) -> EpisodeConfig:
    return EpisodeConfig(dataset=str(dataset.root), field=dict(TINY_FIELD), warmup_ms=150,
                         scored_ms=90, score_every=1, steps_per_epoch=4, carry="fresh",
                         lpips=False)


@pytest.fixture(scope="module")
def policies(cfg: EpisodeConfig, dataset: SceneDataset):
    return run_jobs(cfg, [Job(p, cfg.delay, s) for s in SEEDS for p in RULES], processes=1,
                    dataset=dataset).results


# --- specs -----------------------------------------------------------------------------------
def test_oracle_and_baseline_specs() -> None:
    assert parse_oracle("oracle") == OracleSpec("rules", "reward")
    assert parse_oracle("oracle:greedy").spec == "oracle:greedy:reward"
    assert parse_oracle(" oracle:rules:psnr_dynamic_db ").metric == "psnr_dynamic_db"
    assert parse_oracle("oracle:rules:lpips").sign == -1.0
    for bad in ("oracle:foo", "oracle:rules:bogus", "oracle:rules:reward:1", "oracles"):
        with pytest.raises(OracleSpecError, match="Accepted forms"):
            parse_oracle(bad)
    assert is_oracle_spec("oracle:greedy") and not is_oracle_spec("mat:70")
    option, policy = split_baseline("wsum:60")
    assert (option.spec, policy, option.field_overrides()) == (
        "wsum:60", "all", {"age_weight_tau_ms": 60.0})
    option, policy = split_baseline("tembed@mat:130")
    assert (option.spec, policy) == ("tembed:2:300", "mat:130")
    assert option.field_overrides() == {"age_features": 2, "age_scale_ms": 300.0}
    assert baseline_label(option, policy) == "tembed:2:300@mat:130"
    assert baseline_label(*split_baseline("tembed:1:150.5")) == "tembed:1:150.5"
    assert is_trainer_spec("wsum:60@all") and not is_trainer_spec("all")
    for bad in ("wsum", "wsum:0", "wsum:x", "wsum:1:2", "tembed:0", "tembed:1:-3",
                "tembed:a", "tembed:1:2:3", "wsum:60@"):
        with pytest.raises(TrainerSpecError, match="Accepted forms"):
            split_baseline(bad)


def test_rule_candidates_are_every_mat_and_freshest_selection() -> None:
    aoi = np.array([30.0, 60.0, np.nan, 30.0, 90.0, 150.0])
    masks = rule_masks(aoi)
    as_sets = [frozenset(np.flatnonzero(m)) for m in masks]
    assert len(set(as_sets)) == len(masks) == 5  # distinct: freshest:1 … freshest:N_known
    for gamma in range(0, 400, 5):
        chosen = frozenset(np.flatnonzero(MatPolicy(gamma).select(aoi)))
        assert not chosen or chosen in as_sets, gamma
    for k in range(1, 6):
        assert frozenset(np.flatnonzero(FreshestPolicy(k).select(aoi))) in as_sets
    assert all(not m[2] for m in masks)  # a camera of unknown AoI is never a candidate
    assert rule_masks(np.full(3, np.nan)) == []


# --- the bound -------------------------------------------------------------------------------
def test_rules_oracle_is_never_below_what_it_searches(cfg: EpisodeConfig, dataset: SceneDataset,
                                                      policies, tmp_path) -> None:
    cache = ResultCache(tmp_path / "cache")
    bound = run_oracle(cfg, "oracle", SEEDS, cache=cache, processes=1, dataset=dataset)
    assert [r.seed for r in bound.results] == SEEDS
    assert all(r.policy == "oracle:rules:reward" for r in bound.results)
    by_seed = {r.seed: r for r in bound.results}
    for r in policies:  # every rule, on the same seed, decision by decision
        mine = by_seed[r.seed]
        assert mine.reward >= r.reward - 1e-9, r.policy
        for a, b in zip(mine.epochs, r.epochs, strict=True):
            assert a.decision_ms == b.decision_ms
            assert a.reward >= b.reward - 1e-9, (r.policy, a.decision_ms)
    # ...and it reaches the best of them somewhere: the bound is one of the candidates
    for seed, mine in by_seed.items():
        best = [max(r.epochs[i].reward for r in policies if r.seed == seed)
                for i in range(len(mine.epochs))]
        assert [e.reward for e in mine.epochs] == pytest.approx(best, abs=1e-9)
    # cost: at most N_known reconstructions per decision, all computed once
    cost = bound.cost()
    assert cost["decisions"] == 3 * len(SEEDS)
    assert all(d.candidates == d.n_known for e in bound.episodes for d in e.decisions)
    assert 1 <= cost["reconstructions_per_decision"]["max"] <= N_TRAIN
    assert bound.computed + bound.cached == bound.reconstructions
    assert cost["compute_s"] > 0
    again = run_oracle(cfg, "oracle", SEEDS, cache=cache, processes=1, dataset=dataset)
    assert (again.computed, again.cached) == (0, bound.reconstructions)
    assert [r.reward for r in again.results] == [r.reward for r in bound.results]


def test_the_bound_is_a_real_episode(cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    bound = run_oracle(cfg, "oracle:rules:psnr_db", [1], processes=1, dataset=dataset)
    episode = bound.episodes[0]
    replay, _ = run_plan(episode.plan, dataset)  # the chosen selections, as one episode
    assert [e.psnr_db for e in replay.epochs] == pytest.approx(
        [e.psnr_db for e in episode.result.epochs], abs=1e-9)
    assert replay.n_selected == episode.result.n_selected
    assert episode.result.key == plan_key(episode.plan, dataset, lpips=False)
    scored = [d for d in episode.plan.decisions if d.scored]
    assert [d.cameras for d in scored] == [s.cameras for s in episode.decisions]


def test_greedy_oracle(cfg: EpisodeConfig, dataset: SceneDataset, policies) -> None:
    bound = run_oracle(cfg, "oracle:greedy", SEEDS, processes=1, dataset=dataset)
    by_seed = {r.seed: r for r in bound.results}
    for r in policies:  # its first round tries every single camera: never below freshest:1
        if r.policy == "freshest:1":
            for a, b in zip(by_seed[r.seed].epochs, r.epochs, strict=True):
                assert a.reward >= b.reward - 1e-9
    for ep in bound.episodes:
        for d in ep.decisions:
            # forward selection: N_known + (N_known − 1) + … one round per camera added, plus
            # the round that found no better addition (none when every camera got in)
            n = len(d.cameras)
            tried = sum(d.n_known - i for i in range(d.rounds))
            assert d.candidates == tried and d.rounds in (n, n + 1)
            assert d.rounds == n + 1 or n == d.n_known


def test_oracle_needs_the_fresh_carry(cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    with pytest.raises(ValueError, match="fresh"):
        run_oracle(cfg.with_(carry="warm"), "oracle", [0], processes=1, dataset=dataset)


# --- baselines in a sweep --------------------------------------------------------------------
def test_baseline_jobs_change_the_training_not_the_selection(cfg: EpisodeConfig,
                                                             dataset: SceneDataset) -> None:
    jobs = [Job("all", cfg.delay, 0), Job("all", cfg.delay, 0, trainer="wsum:30"),
            Job("all", cfg.delay, 0, trainer="tembed:2:300"),
            Job("mat:70", cfg.delay, 0, trainer="wsum:30")]
    out = run_jobs(cfg, jobs, processes=1, dataset=dataset)
    assert [r.policy for r in out.results] == ["all", "wsum:30", "tembed:2:300",
                                               "wsum:30@mat:70"]
    assert len(set(out.keys)) == 4
    plain, wsum, tembed, _ = out.results
    assert plain.n_selected == wsum.n_selected == tembed.n_selected  # the same frames
    assert plain.psnr_db != wsum.psnr_db and plain.psnr_db != tembed.psnr_db
    assert out.plans[1].config.field["age_weight_tau_ms"] == 30.0
    # a plain plan's key does not see the new settings at their "off" values
    assert plan_key(plan_episode(cfg, dataset, "all", 0), dataset, lpips=False) == out.keys[0]
    off = cfg.with_(field={**cfg.field, "age_weight_tau_ms": None, "age_features": 0})
    assert plan_key(plan_episode(off, dataset, "all", 0), dataset, lpips=False) == out.keys[0]


# --- the CLI ---------------------------------------------------------------------------------
def _args(dataset: SceneDataset, tmp_path, out: str, *extra: str) -> list[str]:
    args = ["compare", "--seeds", "2", "--dataset", str(dataset.root), "--out",
            str(tmp_path / out), "--cache", str(tmp_path / "cache"), "--processes", "1",
            "--steps-per-epoch", "2", "--no-lpips", "--carry", "fresh",
            "--set", f"field={json.dumps(TINY_FIELD)}", "--set", "warmup_ms=150",
            "--set", "scored_ms=60", "--set", "score_every=1"]
    return args + list(extra)


def test_cli_compare_with_the_bound_and_the_baselines(dataset: SceneDataset, tmp_path) -> None:
    from aoi3d_cli.experiment import app

    specs = ["all", "mat:70", "freshest:2", "wsum:50", "tembed", "oracle", "oracle:greedy"]
    res = CliRunner().invoke(app, _args(dataset, tmp_path, "c",
                                        *(a for s in specs for a in ("--policy", s))),
                             catch_exceptions=False)
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "c" / "results.json").read_text())
    rows = {r["policy"]: r for r in doc["policies"]}
    assert list(rows) == ["all", "mat:70", "freshest:2", "wsum:50", "tembed:2:300",
                          "oracle:rules:reward", "oracle:greedy:reward"]
    assert [r["bound"] for r in rows.values()] == [False] * 5 + [True] * 2
    # the policies' optimum set is judged without the bounds
    assert "oracle:rules:reward" not in doc["optimum"]["reward"]["best_minus"]
    bound = doc["bound"]["oracle:rules:reward"]
    assert bound["kind"] == "bound" and bound["search"] == "rules"
    assert bound["cost"]["reconstructions"] >= bound["cost"]["decisions"] == 4
    for p in ("all", "mat:70", "freshest:2"):  # never below the rules it searched
        d = bound["minus"]["reward"][p]
        assert d["n"] == 2 and d["mean"] >= -1e-9
    assert set(bound["minus"]["psnr_db"]) == {"all", "mat:70", "freshest:2", "wsum:50",
                                               "tembed:2:300"}
    assert rows["oracle:rules:reward"]["reward"] >= max(
        rows[p]["reward"] for p in ("all", "mat:70", "freshest:2")) - 1e-9
    assert doc["meta"]["args"]["oracles"] == ["oracle:rules:reward", "oracle:greedy:reward"]
    assert {e["policy"] for e in doc["episodes"]} == set(rows)
    assert "a bound" in res.output


@pytest.mark.parametrize(("extra", "message"), [
    (["--policy", "oracle:sideways"], "Accepted forms"),
    (["--policy", "oracle", "--carry", "warm"], "--carry fresh"),
    (["--policy", "wsum"], "wsum takes 1 parameter"),
    (["--policy", "tembed:0"], "features must be >= 1"),
    (["--policy", "wsum:50@bogus:1"], "in 'wsum:50@bogus:1'"),
    (["--policy", "tembed", "--backend", "ngp", "--set", 'field={"batch_rays": 64}'],
     "needs the grid backend"),
])
def test_cli_refuses_bad_new_specs(dataset: SceneDataset, tmp_path, extra, message) -> None:
    from aoi3d_cli.experiment import app

    res = CliRunner().invoke(app, _args(dataset, tmp_path, "x", *extra))
    assert res.exit_code == 2, res.output
    text = " ".join(res.output.translate(str.maketrans("", "", "│╭╮╰╯─")).split())
    assert message in text, res.output
