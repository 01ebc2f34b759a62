"""The frame-selection environment, PPO training/evaluation and the ``aoi3d ppo`` CLI, on a
tiny scene with a few field steps."""

from __future__ import annotations

import csv
import json

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from typer.testing import CliRunner

import aoi3d.rl
from aoi3d.experiment import EpisodeConfig, ResultCache, plan_episode, plan_key, run_plan
from aoi3d.policy.ppo import PPOConfig
from aoi3d.policy.ppo.learner import PPOLearner
from aoi3d.rl import ENV_ID
from aoi3d.rl.env import FrameSelectionEnv
from aoi3d.rl.evaluate import evaluate
from aoi3d.rl.presets import (
    EVAL_SEED_BASE,
    PPO_PRESETS,
    TRAIN_SEED_BASE,
    TrainConfig,
    eval_seeds,
    train_seed,
)
from aoi3d.rl.train import train
from aoi3d.scene import SceneDataset
from tests.support.tiny import N_TRAIN, TINY_FIELD


@pytest.fixture(autouse=True)
def one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def cfg(dataset: SceneDataset) -> EpisodeConfig:
    return EpisodeConfig(dataset=str(dataset.root), field=dict(TINY_FIELD), warmup_ms=150,
                         scored_ms=90, score_every=1, steps_per_epoch=3, lpips=False,
                         carry="fresh")


def test_env_passes_the_gymnasium_checker(cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    env = FrameSelectionEnv(cfg, dataset)
    check_env(env, skip_render_check=True)
    assert env.observation_space.shape == (2 * N_TRAIN,)
    assert env.action_space.n == N_TRAIN


def test_env_is_registered(cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    assert aoi3d.rl.ENV_ID in gymnasium.registry
    env = gymnasium.make(ENV_ID, config=cfg, dataset=str(dataset.root))
    obs, info = env.reset(seed=5)
    assert obs.shape == (2 * N_TRAIN,) and info["seed"] == 5
    _, reward, terminated, truncated, info = env.step(np.ones(N_TRAIN, dtype=np.int8))
    assert terminated and not truncated and reward == pytest.approx(info["reward"])


def test_step_is_the_experiment_engine_on_one_decision(cfg: EpisodeConfig,
                                                       dataset: SceneDataset) -> None:
    """The reward is run_plan's score of the same frames: a MAT policy in the env and the
    engine's own plan of that decision agree exactly."""
    env = FrameSelectionEnv(cfg, dataset)
    obs, info = env.reset(seed=11)
    aoi = info["aoi"]
    np.testing.assert_array_equal(obs, aoi3d.policy.ppo.encode_aoi(aoi, 300.0))
    mask = aoi < 70.0
    _, reward, _, _, step_info = env.step(mask.astype(np.int8))
    plan = plan_episode(cfg, dataset, "mat:70", seed=11)
    decision = next(d for d in plan.decisions if d.eval_ms == info["eval_ms"])
    assert step_info["selected"] == list(decision.cameras)
    one = plan.__class__(**{**vars(plan), "decisions": (decision,)})
    result, _ = run_plan(one, dataset)
    assert reward == pytest.approx(result.epochs[0].reward)
    assert step_info["psnr"] == pytest.approx(result.epochs[0].psnr_db)
    assert step_info["n_selected"] == int(mask.sum())
    assert step_info["lpips"] is None  # the config turns LPIPS off


def test_empty_selection_unknown_cameras_and_bad_actions(cfg: EpisodeConfig,
                                                         dataset: SceneDataset) -> None:
    env = FrameSelectionEnv(cfg.with_(warmup_ms=30, delay="const:200"), dataset)
    obs, info = env.reset(seed=0)
    assert np.isnan(info["aoi"]).all()  # nothing delivered yet: all unknown
    assert obs[N_TRAIN:].tolist() == [1.0] * N_TRAIN and obs[:N_TRAIN].tolist() == [1.0] * 4
    _, reward, terminated, _, step = env.step(np.ones(N_TRAIN, dtype=np.int8))
    assert terminated and step["n_selected"] == 0 and np.isfinite(reward)  # untrained model
    env = FrameSelectionEnv(cfg, dataset)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(N_TRAIN, dtype=np.int8))
    env.reset(seed=1)
    with pytest.raises(ValueError, match="4 bits"):
        env.step(np.zeros(3, dtype=np.int8))
    with pytest.raises(ValueError, match="0 or 1"):
        env.step(np.full(N_TRAIN, 2))


def test_cache_returns_identical_episodes(cfg: EpisodeConfig, dataset: SceneDataset,
                                          tmp_path) -> None:
    env = FrameSelectionEnv(cfg, dataset, cache=tmp_path / "cache")
    action = np.array([1, 0, 1, 1], dtype=np.int8)
    env.reset(seed=3)
    first = env.step(action)
    assert env.last_outcome is not None and not env.last_outcome.cached
    env.reset(seed=3)
    second = env.step(action)
    assert env.last_outcome.cached and second[1] == first[1]
    assert ResultCache(tmp_path / "cache").get(second[4]["key"]) is not None
    plan = env.plan_for(action.astype(bool)) if env._plan else None
    assert plan is None  # the episode is over after its step
    env.reset(seed=3)
    assert plan_key(env.plan_for(action.astype(bool)), dataset, lpips=False) == first[4]["key"]


def test_seeds_are_disjoint() -> None:
    assert train_seed(0) == TRAIN_SEED_BASE
    assert max(train_seed(i) for i in range(600)) < EVAL_SEED_BASE
    assert eval_seeds(3, 2) == [EVAL_SEED_BASE + 2, EVAL_SEED_BASE + 3, EVAL_SEED_BASE + 4]
    with pytest.raises(ValueError):
        TrainConfig(episode=EpisodeConfig(), ppo=PPOConfig(n_cameras=2),
                    episodes=EVAL_SEED_BASE, batch_size=8)
    quick = PPO_PRESETS["quick"]
    assert quick.episodes == 600 and quick.episode.carry == "fresh"


def _train_cfg(cfg: EpisodeConfig, episodes: int = 8) -> TrainConfig:
    return TrainConfig(episode=cfg, ppo=PPOConfig(n_cameras=N_TRAIN, lr=1e-3, seed=1),
                       episodes=episodes, batch_size=4, checkpoint_every=1, preset="test")


def test_train_writes_files_and_resumes_identically(cfg: EpisodeConfig, dataset: SceneDataset,
                                                    tmp_path) -> None:
    full = train(_train_cfg(cfg, 8), tmp_path / "full", dataset=dataset, processes=1,
                 cache=tmp_path / "cache")
    assert full.episodes == 8 and full.updates == 2 and full.computed + full.cached == 8
    for name in ("checkpoint.pt", "final.pt", "episodes.csv", "updates.csv", "reward.png",
                 "config.json"):
        assert (tmp_path / "full" / name).is_file(), name
    rows = list(csv.DictReader((tmp_path / "full" / "episodes.csv").open()))
    assert [int(r["episode"]) for r in rows] == list(range(8))
    assert [int(r["seed"]) for r in rows] == [train_seed(i) for i in range(8)]
    for key in ("reward", "psnr", "ssim", "lpips", "n_selected", "selected", "entropy"):
        assert key in rows[0]
    meta = json.loads((tmp_path / "full" / "config.json").read_text())
    assert meta["train_config"]["episodes"] == 8 and meta["code_version"]
    # Stop after 4 episodes, then resume to 8: the same agent as the uninterrupted run.
    half = train(_train_cfg(cfg, 4), tmp_path / "split", dataset=dataset, processes=1,
                 cache=tmp_path / "cache")
    assert half.episodes == 4
    with pytest.raises(FileExistsError):
        train(_train_cfg(cfg, 8), tmp_path / "split", dataset=dataset, processes=1)
    resumed = train(_train_cfg(cfg, 8), tmp_path / "split", dataset=dataset, processes=1,
                    cache=tmp_path / "cache", resume=True)
    assert resumed.episodes == 8 and resumed.cached == 4  # same actions → cache hits
    a = PPOLearner.load(tmp_path / "full" / "final.pt")
    b = PPOLearner.load(tmp_path / "split" / "final.pt")
    for x, y in zip(a.net.state_dict().values(), b.net.state_dict().values(), strict=True):
        assert torch.equal(x, y)
    with pytest.raises(ValueError, match="another config"):
        other = _train_cfg(cfg, 12)
        train(TrainConfig(**{**vars(other), "batch_size": 2}), tmp_path / "split",
              dataset=dataset, processes=1, resume=True)


def test_evaluate_on_held_out_seeds(cfg: EpisodeConfig, dataset: SceneDataset,
                                    tmp_path) -> None:
    agent = PPOLearner(PPOConfig(n_cameras=N_TRAIN))
    agent.save(tmp_path / "a.pt")
    seeds = eval_seeds(3)
    outcome = evaluate([f"ppo:{tmp_path / 'a.pt'}", "all", "mat:0"], cfg, seeds,
                       dataset=dataset, processes=1)
    assert len(outcome.rows) == 9 and {r["seed"] for r in outcome.rows} == set(seeds)
    summary = {r["policy"]: r for r in outcome.summary}
    assert summary["mat:0"]["n_selected"] == 0
    assert summary["all"]["n"] == 3 and np.isfinite(summary["all"]["reward_ci95"])
    assert "first_minus_this_reward" in summary["all"]
    with pytest.raises(ValueError, match="waiting"):
        evaluate(["wait:40"], cfg, seeds, dataset=dataset, processes=1)
    big = PPOLearner(PPOConfig(n_cameras=N_TRAIN + 1))
    big.save(tmp_path / "big.pt")
    with pytest.raises(ValueError, match="trained for 5 cameras"):
        evaluate([f"ppo:{tmp_path / 'big.pt'}"], cfg, seeds, dataset=dataset, processes=1)


# --- CLI -------------------------------------------------------------------------------------
def _cli(args: list[str]):
    from aoi3d_cli import app

    return CliRunner().invoke(app, args, env={"COLUMNS": "400"})  # no wrapped messages


def _tiny_sets(dataset: SceneDataset) -> list[str]:
    return ["--dataset", str(dataset.root), "--steps-per-epoch", "2", "--no-lpips",
            "--set", f"field={json.dumps(TINY_FIELD)}", "--set", "warmup_ms=150",
            "--set", "scored_ms=90", "--set", "score_every=1", "--processes", "1"]


def test_cli_train_and_eval_end_to_end(dataset: SceneDataset, tmp_path) -> None:
    out = tmp_path / "run"
    res = _cli(["ppo", "train", "--episodes", "6", "--batch-size", "3", "--out", str(out),
                "--cache", str(tmp_path / "cache"), *_tiny_sets(dataset)])
    assert res.exit_code == 0, res.output
    for name in ("checkpoint.pt", "final.pt", "episodes.csv", "reward.png", "config.json"):
        assert (out / name).is_file(), name
    rows = list(csv.DictReader((out / "episodes.csv").open()))
    assert len(rows) == 6
    res = _cli(["ppo", "eval", "--checkpoint", str(out / "final.pt"), "--seeds", "2",
                "--compare", "all", "--cache", str(tmp_path / "cache"), "--processes", "1",
                "--no-lpips"])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "eval" / "eval.json").read_text())
    assert [r["policy"] for r in doc["summary"]] == [f"ppo:{out / 'final.pt'}", "all"]
    assert all(s >= EVAL_SEED_BASE for s in doc["meta"]["seeds"])
    assert doc["meta"]["episode_config"]["steps_per_epoch"] == 2  # the checkpoint's config
    assert (out / "eval" / "eval.csv").is_file()
    # the same output folder again without --resume: refused, nothing overwritten
    res = _cli(["ppo", "train", "--episodes", "6", "--batch-size", "3", "--out", str(out),
                *_tiny_sets(dataset)])
    assert res.exit_code == 2 and "resume" in res.output


def test_cli_bad_input(dataset: SceneDataset, tmp_path) -> None:
    res = _cli(["ppo", "train", "--preset", "nope", "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "unknown PPO preset" in res.output
    res = _cli(["ppo", "train", "--ppo-set", "clip_eps=-1", "--out", str(tmp_path / "x"),
                *_tiny_sets(dataset)])
    assert res.exit_code == 2 and "clip_eps" in res.output
    bad = tmp_path / "bad.pt"
    bad.write_text("nope")
    res = _cli(["ppo", "eval", "--checkpoint", str(bad)])
    assert res.exit_code == 2 and "not a readable PPO checkpoint" in res.output
    agent = PPOLearner(PPOConfig(n_cameras=N_TRAIN))
    agent.save(tmp_path / "a.pt")
    res = _cli(["ppo", "eval", "--checkpoint", str(tmp_path / "a.pt"), "--seeds", "1",
                "--compare", "bogus:1", *_tiny_sets(dataset)[:-2], "--processes", "1"])
    assert res.exit_code == 2 and "Accepted forms" in res.output


def test_experiment_compare_accepts_a_ppo_checkpoint(dataset: SceneDataset, tmp_path) -> None:
    """``ppo:<checkpoint>`` in `aoi3d experiment compare`: its deterministic action at every
    decision, through the normal planning path; a checkpoint of another N is refused."""
    agent = PPOLearner(PPOConfig(n_cameras=N_TRAIN, init_select_p=0.9))  # selects all
    agent.save(tmp_path / "a.pt")
    common = ["--dataset", str(dataset.root), "--cache", str(tmp_path / "cache"),
              "--processes", "1", "--steps-per-epoch", "2", "--no-lpips", "--seeds", "2",
              "--set", f"field={json.dumps(TINY_FIELD)}", "--set", "warmup_ms=150",
              "--set", "scored_ms=60", "--set", "score_every=1"]
    spec = f"ppo:{tmp_path / 'a.pt'}"
    res = _cli(["experiment", "compare", "--policy", spec, "--policy", "all",
                "--out", str(tmp_path / "c"), *common])
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "c" / "results.json").read_text())
    rows = {r["policy"]: r for r in doc["policies"]}
    assert set(rows) == {spec, "all"}
    # p = 0.9 everywhere → every known camera, i.e. the same frames as `all`: same numbers
    assert rows[spec]["reward"] == pytest.approx(rows["all"]["reward"])
    assert rows[spec]["n_selected"] == rows["all"]["n_selected"]
    PPOLearner(PPOConfig(n_cameras=N_TRAIN + 2)).save(tmp_path / "b.pt")
    res = _cli(["experiment", "compare", "--policy", f"ppo:{tmp_path / 'b.pt'}",
                "--out", str(tmp_path / "d"), *common])
    assert res.exit_code == 2 and "trained for 6 cameras" in res.output


def test_worker_pool_matches_in_process(cfg: EpisodeConfig, dataset: SceneDataset) -> None:
    from aoi3d.rl.runner import EpisodeRunner

    items = [(7, np.array([1, 0, 1, 1], np.int8)), (8, np.array([0, 1, 1, 0], np.int8))]
    with EpisodeRunner(cfg, aoi_scale_ms=300.0, cache=None, processes=1) as pool:
        serial = dict(pool.run(items))
    with EpisodeRunner(cfg, aoi_scale_ms=300.0, cache=None, processes=2) as pool:
        parallel = dict(pool.run(items))
    for i in range(2):
        assert parallel[i]["reward"] == serial[i]["reward"]
        assert parallel[i]["selected"] == serial[i]["selected"]


def test_an_agent_with_pose_features_trains_and_acts(dataset: SceneDataset, cfg: EpisodeConfig,
                                                     tmp_path) -> None:
    """``--features pose``: the rig's geometry goes into the checkpoint, training observes it,
    and the policy acts on it in evaluation; a config whose values are not this rig's is
    refused."""
    from aoi3d.policy.ppo.obs import CAMERA_FEATURES
    from aoi3d.rl.train import camera_feature_values

    ids = FrameSelectionEnv(cfg, dataset).camera_ids
    for name, values in CAMERA_FEATURES.items():  # every feature has its values
        assert len(camera_feature_values((name,), dataset, ids)) == len(values) * N_TRAIN
    out = tmp_path / "pose"
    res = _cli(["ppo", "train", "--episodes", "4", "--batch-size", "2", "--out", str(out),
                "--features", "pose", "--ppo-set", "arch=shared", *_tiny_sets(dataset)])
    assert res.exit_code == 0, res.output
    agent = PPOLearner.load(out / "final.pt")
    assert agent.config.features == ("pose",)
    assert agent.config.camera_features == camera_feature_values(("pose",), dataset, ids)
    rows = list(csv.DictReader((out / "episodes.csv").open()))
    assert len(rows) == 4
    res = _cli(["ppo", "eval", "--checkpoint", str(out / "final.pt"), "--seeds", "1",
                "--processes", "1", "--no-lpips"])
    assert res.exit_code == 0, res.output
    res = _cli(["ppo", "train", "--features", "colour", "--out", str(tmp_path / "x"),
                *_tiny_sets(dataset)])
    assert res.exit_code == 2 and "unknown camera feature" in res.output
    wrong = PPOConfig(n_cameras=N_TRAIN, features=("pose",), camera_features=(0.5,) * 8)
    with pytest.raises(ValueError, match="not those of this rig"):
        train(TrainConfig(episode=cfg, ppo=wrong, episodes=2, batch_size=2, preset="test"),
              tmp_path / "wrong", dataset=dataset, processes=1)
