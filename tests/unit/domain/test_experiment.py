"""The experiment engine: plans, episodes, ω-wait, the cache, sweeps and the CLI (tiny scene)."""

from __future__ import annotations

import csv
import json
import math
import os

import numpy as np
import pytest
from typer.testing import CliRunner

from aoi3d.channel import simulate
from aoi3d.experiment import (
    EpisodeConfig,
    Job,
    ResultCache,
    aggregate,
    mean_ci95,
    plan_episode,
    plan_key,
    run_jobs,
    run_plan,
)
from aoi3d.policy import PolicySpecError, parse_policy, policy_from_json
from aoi3d.policy.wait import WaitPolicy
from aoi3d.scene import SceneDataset
from tests.support.tiny import N_TRAIN, TINY_FIELD


@pytest.fixture(scope="module")
def cfg(dataset: SceneDataset) -> EpisodeConfig:
    return EpisodeConfig(dataset=str(dataset.root), field=dict(TINY_FIELD), warmup_ms=150,
                         scored_ms=90, score_every=1, steps_per_epoch=2, lpips=False)


# --- ω-wait ----------------------------------------------------------------------------------
def test_wait_policy_spec_json_and_selection() -> None:
    pol = parse_policy("wait:40")
    assert isinstance(pol, WaitPolicy) and pol.spec == "wait:40" and pol.wait_ms == 40
    assert policy_from_json(pol.to_json()) == pol
    mask = pol.select(np.array([40.0, 41.0, np.nan, 0.0]))
    assert mask.tolist() == [True, False, False, True]  # Δ ≤ ω; unknown never
    assert parse_policy("mat:50").wait_ms == 0
    for bad in ("wait", "wait:-1", "wait:2.5", "wait:x", "wait:1:2"):
        with pytest.raises(PolicySpecError, match="Accepted forms"):
            parse_policy(bad)


def test_wait_evaluates_at_t_plus_omega(cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    omega = 45
    plan = plan_episode(cfg, dataset, "wait:45", seed=3)
    run = simulate(cfg.delay, cfg.period_ms, N_TRAIN, cfg.end_ms + omega + 1, 3)
    assert plan.wait_ms == omega
    for d in plan.decisions:
        assert d.eval_ms == d.decision_ms + omega
        newest = run.newest_ms(d.eval_ms)
        expected = [i + 1 for i in range(N_TRAIN) if newest[i] >= d.decision_ms]
        assert list(d.cameras) == expected  # captured since t, delivered by t + ω
        assert all(0 < a <= omega for a in d.aoi_ms)
    assert any(d.cameras for d in plan.decisions)
    # The render is scored against the truth at t + ω.
    seen = []
    result, _ = run_plan(plan, dataset, on_render=lambda d, img: seen.append(d.eval_ms))
    assert [e.eval_ms for e in result.epochs] == seen
    assert seen == [d.decision_ms + omega for d in plan.decisions if d.scored]
    # ω = 0 never selects: a frame needs at least one slot on the link.
    assert not any(d.cameras for d in plan_episode(cfg, dataset, "wait:0", 3).decisions)


# --- plans -----------------------------------------------------------------------------------
def test_plan_uses_newest_delivered_frames(cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    plan = plan_episode(cfg, dataset, "mat:70", seed=5)
    run = simulate(cfg.delay, cfg.period_ms, N_TRAIN, cfg.end_ms + 1, 5)
    assert [d.decision_ms for d in plan.decisions] == list(range(30, cfg.end_ms, 30))
    for d in plan.decisions:
        aoi = run.aoi_ms(d.eval_ms)
        chosen = [i + 1 for i in range(N_TRAIN) if aoi[i] < 70]
        assert list(d.cameras) == chosen
        assert list(d.gen_ms) == [int(run.newest_ms(d.eval_ms)[c - 1]) for c in chosen]
        assert list(d.aoi_ms) == [d.eval_ms - g for g in d.gen_ms]
    # warm: every decision trains; only the scored span is scored.
    assert all(d.train for d in plan.decisions)
    assert [d.decision_ms for d in plan.decisions if d.scored] == [150, 180, 210]


def test_fresh_trains_only_scored_decisions(cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    plan = plan_episode(cfg.with_(carry="fresh", score_every=2), dataset, "all", 1)
    assert [d.decision_ms for d in plan.decisions if d.train] == [150, 210]
    assert all(d.scored == d.train for d in plan.decisions)


def test_aoi_of_used_frames(cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    plan = plan_episode(cfg, dataset, "all", seed=2)
    result, png = run_plan(plan, dataset)
    run = simulate(cfg.delay, cfg.period_ms, N_TRAIN, cfg.end_ms + 1, 2)
    ts = [t for t in range(30, cfg.end_ms, 30) if t >= cfg.warmup_ms]
    aois = np.concatenate([run.aoi_ms(t) for t in ts])
    aois = aois[~np.isnan(aois)]
    assert result.aoi_used_ms == pytest.approx(aois.mean())
    assert result.n_selected == pytest.approx(len(aois) / len(ts))
    assert png.startswith(b"\x89PNG")
    scored = [d for d in plan.decisions if d.scored]
    assert [e.aoi_used_ms for e in result.epochs] == pytest.approx(
        [np.mean(d.aoi_ms) for d in scored])


def test_same_selection_same_key(cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    # Cameras capture at k·30 and decisions fall on k·30: every AoI is a multiple of 30, so
    # Γ = 70 and Γ = 80 select the same frames and share one result; Γ = 40 does not.
    keys = {g: plan_key(plan_episode(cfg, dataset, f"mat:{g}", 4), dataset, lpips=False)
            for g in (40, 70, 80)}
    assert keys[70] == keys[80] != keys[40]
    other_seed = plan_key(plan_episode(cfg, dataset, "mat:70", 5), dataset, lpips=False)
    assert other_seed != keys[70]


def test_bad_config() -> None:
    with pytest.raises(ValueError, match="carry"):
        EpisodeConfig(carry="sometimes")
    with pytest.raises(ValueError, match="Accepted forms"):
        EpisodeConfig(delay="exp")
    with pytest.raises(ValueError, match="steps_per_epoch"):
        EpisodeConfig(steps_per_epoch=0)
    with pytest.raises(ValueError, match="unknown episode config"):
        EpisodeConfig.from_dict({"warmup": 3})


# --- episodes --------------------------------------------------------------------------------
def test_episode_is_deterministic(cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    a, png_a = run_plan(plan_episode(cfg, dataset, "all", 7), dataset)
    b, png_b = run_plan(plan_episode(cfg, dataset, "all", 7), dataset)
    assert [e.psnr_db for e in a.epochs] == [e.psnr_db for e in b.epochs]
    assert (a.ssim, a.aoi_used_ms, a.train_steps) == (b.ssim, b.aoi_used_ms, b.train_steps)
    assert png_a == png_b
    c, _ = run_plan(plan_episode(cfg, dataset, "all", 8), dataset)
    assert [e.psnr_db for e in c.epochs] != [e.psnr_db for e in a.epochs]
    assert all(math.isfinite(e.psnr_db) and 0 < e.ssim <= 1 for e in a.epochs)
    assert a.train_steps == 2 * sum(1 for d in plan_episode(cfg, dataset, "all", 7).decisions
                                    if d.cameras)


def test_episode_scores_the_dynamic_region_of_the_truth(cfg: EpisodeConfig,
                                                        dataset: SceneDataset) -> None:
    from aoi3d.quality import dynamic_mask, dynamic_score

    plan = plan_episode(cfg, dataset, "all", 3)
    renders = []
    result, _ = run_plan(plan, dataset, on_render=lambda d, image: renders.append((d, image)))
    assert len(renders) == len(result.epochs) > 0

    def truth(t_ms: int) -> np.ndarray:
        return dataset.frame(dataset.heldout_id, dataset.frame_index(t_ms + plan.scene_offset_ms))

    for (d, image), e in zip(renders, result.epochs, strict=True):
        c = cfg.period_ms
        mask = dynamic_mask(truth(d.eval_ms), [truth(d.eval_ms - c), truth(d.eval_ms - 2 * c)])
        expected = dynamic_score(image, truth(d.eval_ms), mask)
        assert 0 < e.dynamic_fraction < 1 and e.dynamic_fraction == expected.fraction
        assert e.psnr_dynamic_db == pytest.approx(expected.psnr_db, abs=1e-9)
        assert e.ssim_dynamic == pytest.approx(expected.ssim, abs=1e-9)
        assert e.psnr_dynamic_db != pytest.approx(e.psnr_db, abs=1e-3)
    assert result.psnr_dynamic_db == pytest.approx(np.mean([e.psnr_dynamic_db
                                                            for e in result.epochs]))
    assert result.dynamic_fraction == pytest.approx(np.mean([e.dynamic_fraction
                                                             for e in result.epochs]))


def test_empty_selection_trains_nothing(cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    result, _ = run_plan(plan_episode(cfg, dataset, "mat:0", 1), dataset)
    assert result.train_steps == 0 and result.n_selected == 0
    assert math.isnan(result.aoi_used_ms)
    assert all(e.steps == 0 for e in result.epochs)


# --- sweeps and the cache --------------------------------------------------------------------
def test_cache_resumes_an_interrupted_sweep(cfg: EpisodeConfig, dataset: SceneDataset,
                                            tmp_path) -> None:
    jobs = [Job(p, "exp:60", s) for s in range(2) for p in ("mat:40", "mat:70", "all")]
    cache = ResultCache(tmp_path / "cache")

    class Stop(Exception):
        pass

    def stop_after_two(done: int, total: int) -> None:
        if done == 2:
            raise Stop

    with pytest.raises(Stop):
        run_jobs(cfg, jobs, cache=cache, processes=1, progress=stop_after_two, dataset=dataset)
    assert len(list(cache.root.glob("*/*.json"))) == 2
    resumed = run_jobs(cfg, jobs, cache=cache, processes=1, dataset=dataset)
    n_unique = len(set(resumed.keys))
    assert (resumed.cached, resumed.computed) == (2, n_unique - 2)
    again = run_jobs(cfg, jobs, cache=cache, processes=1, dataset=dataset)
    assert (again.cached, again.computed) == (n_unique, 0)
    fresh = run_jobs(cfg, jobs, cache=None, processes=1, dataset=dataset)
    assert [r.psnr_db for r in resumed.results] == [r.psnr_db for r in fresh.results]
    assert [r.policy for r in resumed.results] == [j.policy for j in jobs]
    assert [r.seed for r in resumed.results] == [j.seed for j in jobs]
    # An entry cached before the dynamic-region scores existed is a miss, recomputed in place.
    key = resumed.keys[0]
    path = cache.root / key[:2] / f"{key}.json"
    doc = json.loads(path.read_text())
    assert doc["psnr_dynamic_db"] is not None
    for name in ("psnr_dynamic_db", "ssim_dynamic", "dynamic_fraction"):
        del doc[name]
        for epoch in doc["epochs"]:
            del epoch[name]
    path.write_text(json.dumps(doc))
    assert cache.get(key) is None
    healed = run_jobs(cfg, jobs, cache=cache, processes=1, dataset=dataset)
    assert (healed.cached, healed.computed) == (n_unique - 1, 1)
    assert cache.get(key).psnr_dynamic_db == resumed.results[0].psnr_dynamic_db


@pytest.mark.slow  # two spawned workers import torch: ~8 s on 2 cores
def test_process_pool_matches_serial(cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    jobs = [Job("all", "exp:60", 0), Job("mat:70", "exp:30", 1)]
    serial = run_jobs(cfg, jobs, processes=1, dataset=dataset)
    pooled = run_jobs(cfg, jobs, processes=2, dataset=dataset)
    assert [r.psnr_db for r in pooled.results] == [r.psnr_db for r in serial.results]
    assert [r.delay for r in pooled.results] == ["exp:60", "exp:30"]


@pytest.mark.skipif(os.environ.get("AOI3D_RAY_TESTS") != "1",
                    reason="starting a local Ray takes 0.5–2 min: `make bench-ray` runs it")
def test_ray_matches_serial(cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    pytest.importorskip("ray", reason="Ray is optional (pip install '.[cluster]')")
    jobs = [Job("all", "exp:60", 0), Job("mat:70", "exp:60", 1)]
    serial = run_jobs(cfg, jobs, processes=1, dataset=dataset)
    on_ray = run_jobs(cfg, jobs, ray_address="local", dataset=dataset)
    assert [r.psnr_db for r in on_ray.results] == [r.psnr_db for r in serial.results]


def test_mean_ci95_and_aggregate() -> None:
    mean, half, n = mean_ci95([1.0, 2.0, 3.0, None, math.nan])
    assert (mean, n) == (2.0, 3)
    assert half == pytest.approx(4.302652729749464 * 1.0 / math.sqrt(3))
    assert math.isnan(mean_ci95([5.0])[1])
    assert mean_ci95([])[2] == 0


# --- the CLI ---------------------------------------------------------------------------------
def _cli(args: list[str]):
    from aoi3d_cli.experiment import app

    return CliRunner().invoke(app, args, catch_exceptions=False)


def _common(dataset: SceneDataset, tmp_path, out: str) -> list[str]:
    sets = [f"field={json.dumps(TINY_FIELD)}", "warmup_ms=150", "scored_ms=60", "score_every=1"]
    args = ["--dataset", str(dataset.root), "--out", str(tmp_path / out), "--cache",
            str(tmp_path / "cache"), "--processes", "1", "--steps-per-epoch", "2", "--no-lpips"]
    for s in sets:
        args += ["--set", s]
    return args


def test_cli_tradeoff_end_to_end(dataset: SceneDataset, tmp_path) -> None:
    res = _cli(["tradeoff", "--gammas", "0,40,70", "--seeds", "2",
                *_common(dataset, tmp_path, "t")])
    assert res.exit_code == 0, res.output
    out = tmp_path / "t"
    for name in ("points.csv", "episodes.csv", "results.json", "tradeoff.png"):
        assert (out / name).stat().st_size > 0, name
    doc = json.loads((out / "results.json").read_text())
    assert doc["meta"]["code_version"] and doc["meta"]["machine"]["cpu_count"] >= 1
    assert doc["meta"]["episode_config"]["steps_per_epoch"] == 2
    assert [p["gamma_ms"] for p in doc["points"]] == [0, 40, 70]
    assert doc["points"][0]["n_selected"] == 0 and doc["points"][0]["n"] == 2
    assert doc["reference"]["policy"] == "all"
    with (out / "episodes.csv").open() as fh:
        episodes = list(csv.DictReader(fh))
    assert len(episodes) == 2 * 4
    assert all(float(e["psnr_dynamic_db"]) > 0 and 0 < float(e["dynamic_fraction"]) < 1
               for e in episodes)
    with (out / "points.csv").open() as fh:
        points = list(csv.DictReader(fh))
    for column in ("psnr_dynamic_db", "psnr_dynamic_db_ci95", "ssim_dynamic",
                   "dynamic_fraction"):
        assert column in points[0], column
    assert all(math.isfinite(float(p["psnr_dynamic_db"])) for p in points)
    assert "psnr_dynamic_db" in doc["optimum"]
    # Γ = 0 selects nothing: the criterion leaves it out, and judges 40, 70 and all paired
    # over the two seeds.
    opt = doc["optimum"]["psnr_db"]
    assert opt["excluded"] == [0.0] and opt["seeds"] == [0, 1]
    assert set(opt["best_minus"]) == {"40.0", "70.0", "all"}
    assert doc["meta"]["seed_list"] == [0, 1] and doc["meta"]["seed_offset"] == 0
    # A re-run computes nothing; the other commands reuse the cached episodes.
    res = _cli(["tradeoff", "--gammas", "0,40,70", "--seeds", "2",
                *_common(dataset, tmp_path, "t")])
    assert "0 episode(s) computed" in res.output
    res = _cli(["views", "--gammas", "40,70", *_common(dataset, tmp_path, "v")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "v" / "views.png").is_file()
    assert "0 episode(s) computed" in res.output
    res = _cli(["compare", "--seeds", "2", "--policy", "all", "--policy", "mat:best",
                "--policy", "freshest:2", "--policy", "wait:40",
                *_common(dataset, tmp_path, "c")])
    assert res.exit_code == 0, res.output
    rows = json.loads((tmp_path / "c" / "results.json").read_text())["policies"]
    names = [r["policy"] for r in rows]
    assert names[0] == "all" and names[1].startswith("mat:") and names[2:] == ["freshest:2",
                                                                               "wait:40"]
    assert (tmp_path / "c" / "compare.png").is_file()


def test_cli_delay_and_bad_input(dataset: SceneDataset, tmp_path) -> None:
    res = _cli(["delay", "--delays", "exp:30,exp:90", "--gammas", "40,70,100", "--seeds", "2",
                "--seed-offset", "7", *_common(dataset, tmp_path, "d")])
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "d" / "results.json").read_text())
    optima = doc["optima"]
    assert [o["mean_delay_ms"] for o in optima] == [30, 90]
    # The seeds asked for, and only those, are run, and the optimum is paired over them.
    assert doc["meta"]["seed_list"] == [7, 8]
    assert sorted({e["seed"] for e in doc["episodes"]}) == [7, 8]
    for o in optima:
        curve = {c["gamma_ms"]: c["psnr_db"] for c in doc["curves"] if c["delay"] == o["delay"]}
        assert o["best_gamma_ms"] == max(curve, key=lambda g: curve[g])  # the best mean
        assert o["optimum"]["seeds"] == [7, 8]
        assert o["optimum_min_ms"] <= o["best_gamma_ms"] <= o["optimum_max_ms"]
        assert o["interior"] == (o["optimum"]["members"] == [70.0])
    assert (tmp_path / "d" / "delay.png").is_file()
    from aoi3d_cli.experiment import app

    runner = CliRunner()
    bad = runner.invoke(app, ["compare", "--policy", "bogus:1",
                              *_common(dataset, tmp_path, "x")])
    assert bad.exit_code == 2 and "Accepted forms" in bad.output
    bad = runner.invoke(app, ["tradeoff", "--delay", "exp", *_common(dataset, tmp_path, "x")])
    assert bad.exit_code == 2
    bad = runner.invoke(app, ["tradeoff", "--set", "carry=never",
                              *_common(dataset, tmp_path, "x")])
    assert bad.exit_code == 2 and "carry" in bad.output
    assert aggregate([]) == []


def test_cli_commands_take_their_own_options_then_the_shared_ones() -> None:
    import typer.main

    from aoi3d_cli.experiment import app

    shared = ["dataset", "out", "cache", "seeds", "seed_offset", "steps_per_epoch", "carry",
              "backend", "processes", "threads", "ray_address", "lpips", "device", "set_"]
    own = {"tradeoff": ["preset", "gammas", "delay"],
           "views": ["preset", "gammas", "rows", "delay"],
           "delay": ["preset", "delays", "gammas", "metric"],
           "compare": ["preset", "policy", "mat_ms", "best_metric", "delay"]}
    commands = typer.main.get_command(app).commands
    assert set(commands) == set(own)
    for name, sub in commands.items():
        expected = own[name] + [s for s in shared if name != "views" or s != "seeds"]
        assert [p.name for p in sub.params] == expected, name
    assert "--set" in next(p for p in commands["tradeoff"].params if p.name == "set_").opts
