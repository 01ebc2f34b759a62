"""PPO for what a viewer sees (issue 40): the env's display-time reward, budgets drawn per
episode, the lag to the display in the observation; an agent that observes it trains, is
deterministic, and acts on the lag as a ``ppo`` policy (with a budget)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from aoi3d.experiment import EpisodeConfig
from aoi3d.experiment.episode.plan import display_lag
from aoi3d.policy import DisplayLag, decide, parse_policy
from aoi3d.policy.ppo import PPOConfig
from aoi3d.policy.ppo.learner import PPOLearner
from aoi3d.policy.ppo.obs import encode_aoi, with_lag
from aoi3d.rl.env import FrameSelectionEnv
from aoi3d.rl.presets import TrainConfig
from aoi3d.rl.train import train
from aoi3d.scene import SceneDataset
from tests.support.tiny import N_TRAIN, TINY_FIELD

BUDGETS = (2, 5, 9)


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


def test_the_env_observes_the_lag_and_rewards_at_display(cfg: EpisodeConfig,
                                                         dataset: SceneDataset) -> None:
    cfg = cfg.with_(time_scale=1.0)  # L ≥ 16 ms: the truth at display is a later frame
    env = FrameSelectionEnv(cfg, dataset, reward="reward_display", budgets=BUDGETS,
                            observe_lag=True)
    assert env.observation_space.shape == (3 * N_TRAIN,)
    lag = display_lag(env.config)
    seen = set()
    for seed in range(12):
        obs, info = env.reset(seed=seed)
        assert info["budget"] in BUDGETS and info["lag_ms"] == lag.lag_ms(info["budget"])
        seen.add(info["budget"])
        # the last N values are L / scale, the same for every camera
        assert obs[:2 * N_TRAIN] == pytest.approx(encode_aoi(info["aoi"], env.aoi_scale_ms))
        assert obs[2 * N_TRAIN:] == pytest.approx([info["lag_ms"] / env.aoi_scale_ms]
                                                  * N_TRAIN)
        assert env.observation_space.contains(obs)
    assert seen == set(BUDGETS)  # the budget varies with the seed, so L does
    obs, info = env.reset(seed=3)
    _, reward, done, _, step = env.step(np.ones(N_TRAIN, dtype=np.int8))
    result = env.last_outcome.result
    assert done and reward == result.epochs[0].reward_display == step["reward_display"]
    assert step["reward"] == result.epochs[0].reward != reward  # decision-time, reported
    assert result.epochs[0].steps == step["budget"] == info["budget"]
    assert result.epochs[0].display_ms == pytest.approx(
        result.epochs[0].eval_ms + info["lag_ms"])
    # deterministic: the same seed and action give the same observation and reward
    again = FrameSelectionEnv(cfg, dataset, reward="reward_display", budgets=BUDGETS,
                              observe_lag=True)
    obs2, _ = again.reset(seed=3)
    _, reward2, *_ = again.step(np.ones(N_TRAIN, dtype=np.int8))
    assert np.array_equal(obs, obs2) and reward2 == reward
    # the default env is unchanged: the AoI vector alone, the decision-time reward
    plain = FrameSelectionEnv(cfg, dataset)
    obs, info = plain.reset(seed=3)
    assert obs.shape == (2 * N_TRAIN,) and info["budget"] == env.config.steps_per_epoch
    with pytest.raises(ValueError, match="reward must be one of"):
        FrameSelectionEnv(cfg, dataset, reward="psnr")
    with pytest.raises(ValueError, match="budget must be 1"):
        FrameSelectionEnv(cfg, dataset, budgets=(0,))


def test_with_lag_and_the_agent_observation() -> None:
    obs = with_lag(np.zeros(4, dtype=np.float32), 2, 150.0, 300.0)
    assert obs.tolist() == [0, 0, 0, 0, 0.5, 0.5] and obs.dtype == np.float32
    assert with_lag(np.zeros(2), 1, 900.0, 300.0)[-1] == 1.0  # capped
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="lag_ms"):
            with_lag(np.zeros(2), 1, bad)
    agent = PPOLearner(PPOConfig(n_cameras=N_TRAIN, lag=True, arch="shared"))
    aoi = np.array([10.0, 40.0, np.nan, 100.0])
    assert agent.config.obs_dim == 3 * N_TRAIN
    assert agent.observe(aoi, 30.0)[-1] == pytest.approx(0.1)
    assert agent.observe(aoi)[-N_TRAIN:].tolist() == [0.0] * N_TRAIN  # no lag known: 0
    plain = PPOLearner(PPOConfig(n_cameras=N_TRAIN))
    assert plain.observe(aoi, 30.0).shape == (2 * N_TRAIN,)  # it ignores the lag
    with pytest.raises(ValueError, match="lag must be a bool"):
        PPOConfig(n_cameras=N_TRAIN, lag=1)  # type: ignore[arg-type]


def test_a_display_agent_trains_and_acts_on_the_lag(cfg: EpisodeConfig, dataset: SceneDataset,
                                                    tmp_path) -> None:
    def run(out: str) -> PPOLearner:
        tc = TrainConfig(episode=cfg, ppo=PPOConfig(n_cameras=N_TRAIN, lag=True, seed=1,
                                                    arch="shared"),
                         episodes=6, batch_size=3, preset="test", reward="reward_display",
                         budgets=BUDGETS)
        train(tc, tmp_path / out, dataset=dataset, processes=1)
        return PPOLearner.load(tmp_path / out / "final.pt")

    a, b = run("a"), run("b")
    for x, y in zip(a.net.state_dict().values(), b.net.state_dict().values(), strict=True):
        assert torch.equal(x, y)  # deterministic per seed
    assert a.config.lag
    rows = list(csv.DictReader((tmp_path / "a" / "episodes.csv").open()))
    assert all(float(r["reward"]) == float(r["reward_display"]) for r in rows)
    assert {int(r["budget"]) for r in rows} <= set(BUDGETS)
    meta = json.loads((tmp_path / "a" / "config.json").read_text())
    assert meta["train_config"]["reward"] == "reward_display"
    assert meta["train_config"]["budgets"] == list(BUDGETS)
    # as a policy: the decision step tells it L at its budget, and it observes exactly that
    policy = parse_policy(f"ppo:{tmp_path / 'a' / 'final.pt'}@5")
    seen: list[float | None] = []
    inner = policy.inner  # type: ignore[attr-defined]
    original = inner.actor.observe
    inner.actor.observe = lambda aoi, lag=None: (seen.append(lag), original(aoi, lag))[1]
    lag = DisplayLag(fixed_ms=1.6, step_ms=0.34, default_steps=3)
    newest = np.array([250.0, 280.0, 200.0, np.nan])
    sel = decide(policy, 300, lambda _t: newest, lag=lag)
    assert sel.budget_steps == 5 and seen == [pytest.approx(lag.lag_ms(5))]
    assert sel.lag_ms == pytest.approx(lag.lag_ms(5))


def test_cli_trains_for_the_display(dataset: SceneDataset, tmp_path) -> None:
    from aoi3d_cli import app

    out = tmp_path / "cli"
    args = ["ppo", "train", "--episodes", "4", "--batch-size", "2", "--out", str(out),
            "--reward", "reward_display", "--budgets", "2,4", "--observe-lag",
            "--dataset", str(dataset.root), "--steps-per-epoch", "2", "--no-lpips",
            "--set", f"field={json.dumps(TINY_FIELD)}", "--set", "warmup_ms=150",
            "--set", "scored_ms=90", "--set", "score_every=1", "--processes", "1"]
    res = CliRunner().invoke(app, args, env={"COLUMNS": "400"})
    assert res.exit_code == 0, res.output
    assert PPOLearner.load(out / "final.pt").config.lag
    res = CliRunner().invoke(app, [*args[:-2], "--reward", "bogus", "--out",
                                   str(tmp_path / "x"), "--processes", "1"],
                             env={"COLUMNS": "400"})
    assert res.exit_code == 2 and "reward must be one of" in res.output
