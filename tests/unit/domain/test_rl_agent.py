"""The PPO core: observation encoding, the single-step PPO agent (it must learn toy bandits),
checkpoints, and ``ppo:<checkpoint>`` as a registered policy."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from aoi3d.policy import PolicySpecError, parse_policy, policy_from_json
from aoi3d.policy.ppo import Batch, PPOConfig, PPOPolicy, encode_aoi
from aoi3d.policy.ppo.learner import PPOLearner


@pytest.fixture(autouse=True)
def one_torch_thread():
    """The networks are tiny: one thread is fastest, and immune to a loaded machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# --- observation -----------------------------------------------------------------------------
def test_encode_aoi_normalises_clips_and_flags_unknowns() -> None:
    obs = encode_aoi(np.array([0.0, 150.0, 300.0, 900.0, np.nan]), scale_ms=300.0)
    assert obs.dtype == np.float32 and obs.shape == (10,)
    assert obs[:5].tolist() == [0.0, 0.5, 1.0, 1.0, 1.0]  # unknown → 1.0 (as stale as it gets)
    assert obs[5:].tolist() == [0.0, 0.0, 0.0, 0.0, 1.0]  # … and flagged
    assert encode_aoi(np.array([60.0]), scale_ms=120.0).tolist() == [0.5, 0.0]
    for bad_aoi in (np.array([-1.0]), np.array([np.inf]), np.zeros((2, 2))):
        with pytest.raises(ValueError):
            encode_aoi(bad_aoi)
    with pytest.raises(ValueError, match="scale_ms"):
        encode_aoi(np.array([1.0]), scale_ms=0.0)


# --- the agent -------------------------------------------------------------------------------
def test_config_validation_and_round_trip() -> None:
    cfg = PPOConfig(n_cameras=3, clip_eps=0.1, seed=4)
    assert PPOConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="clip_eps"):
        PPOConfig(n_cameras=3, clip_eps=0.0)
    with pytest.raises(ValueError, match="n_cameras"):
        PPOConfig(n_cameras=0)
    with pytest.raises(ValueError, match="init_select_p"):
        PPOConfig(n_cameras=2, init_select_p=1.0)
    with pytest.raises(ValueError, match="arch"):
        PPOConfig(n_cameras=2, arch="transformer")
    with pytest.raises(ValueError, match="unknown PPO config key"):
        PPOConfig.from_dict({"n_cameras": 2, "gamma": 0.9})


@pytest.mark.parametrize("arch", ["mlp", "shared"])
def test_untrained_policy_selects_each_camera_with_half_chance(arch: str) -> None:
    agent = PPOLearner(PPOConfig(n_cameras=18, seed=1, arch=arch))
    act = agent.sample(agent.observe(np.full(18, 60.0)))
    assert act.action.dtype == np.int8 and act.action.shape == (18,)
    assert np.allclose(act.probs, 0.5, atol=0.02)
    assert act.logp == pytest.approx(18 * np.log(0.5), abs=0.2)
    assert act.entropy == pytest.approx(18 * np.log(2), abs=0.01)
    biased = PPOLearner(PPOConfig(n_cameras=4, init_select_p=0.9, arch=arch))
    assert np.allclose(biased.sample(biased.observe(np.zeros(4))).probs, 0.9, atol=0.02)


def test_acting_is_reproducible_per_seed() -> None:
    def actions(seed: int) -> list[list[int]]:
        agent = PPOLearner(PPOConfig(n_cameras=8, seed=seed))
        obs = agent.observe(np.linspace(0, 200, 8))
        return [agent.sample(obs).action.tolist() for _ in range(5)]

    assert actions(3) == actions(3)
    assert actions(3) != actions(4)


def test_bad_observations_and_batches_are_rejected() -> None:
    agent = PPOLearner(PPOConfig(n_cameras=3))
    with pytest.raises(ValueError, match="trained for 3 cameras"):
        agent.observe(np.zeros(4))
    with pytest.raises(ValueError, match="observation must have shape"):
        agent.sample(np.zeros(5, dtype=np.float32))
    obs = np.zeros((2, 6), dtype=np.float32)
    with pytest.raises(ValueError, match="actions must be 0/1"):
        agent.update(Batch(obs, np.full((2, 3), 2), np.zeros(2), np.zeros(2)))
    with pytest.raises(ValueError, match="rewards"):
        agent.update(Batch(obs, np.zeros((2, 3)), np.zeros(2), np.array([0.0, np.nan])))


def _learn(agent: PPOLearner, rng: np.random.Generator, target_of, iters: int,
           batch: int) -> None:
    n = agent.config.n_cameras
    for _ in range(iters):
        obs, acts, logps, rewards = [], [], [], []
        for _ in range(batch):
            aoi = rng.uniform(0.0, 300.0, n)
            o = agent.observe(aoi)
            act = agent.sample(o)
            rewards.append(float((act.action.astype(bool) == target_of(aoi)).mean()))
            obs.append(o)
            acts.append(act.action)
            logps.append(act.logp)
        stats = agent.update(Batch(np.array(obs), np.array(acts), np.array(logps),
                                   np.array(rewards)))
        assert set(stats) == {"policy_loss", "value_loss", "entropy", "approx_kl",
                              "clip_frac", "mean_reward"}
        assert all(np.isfinite(v) for v in stats.values())
    assert agent.episodes == iters * batch and agent.updates == iters


def test_ppo_learns_a_fixed_target_mask() -> None:
    """Reward = fraction of bits matching a fixed mask: the best action is the mask."""
    target = np.array([1, 0, 1, 1, 0, 0, 1, 0], dtype=bool)
    agent = PPOLearner(PPOConfig(n_cameras=8, lr=3e-3, seed=0))
    _learn(agent, np.random.default_rng(0), lambda aoi: target, iters=25, batch=32)
    assert agent.select(np.full(8, 100.0)).tolist() == target.tolist()
    assert np.all(np.abs(agent.probabilities(agent.observe(np.full(8, 100.0))) - target) < 0.25)


@pytest.mark.parametrize(("arch", "iters"), [("mlp", 60), ("shared", 25)])
def test_ppo_learns_a_contextual_bandit(arch: str, iters: int) -> None:
    """Reward = fraction of bits equal to [AoI_n < 100 ms]: the best action depends on the
    observation (a MAT rule), and the best constant action scores only ≈ 2/3. The shared
    actor learns the per-camera rule from fewer episodes."""
    rng = np.random.default_rng(1)
    agent = PPOLearner(PPOConfig(n_cameras=6, lr=3e-3, ent_coef=0.01, seed=0, arch=arch))
    _learn(agent, rng, lambda aoi: aoi < 100.0, iters=iters, batch=32)
    test = rng.uniform(0.0, 300.0, (300, 6))
    acc = np.mean([(agent.select(a)
                    == (a < 100.0)).mean() for a in test])
    assert acc > 0.85  # (0.90–0.96 over seeds 0–4; the best constant action: ≈ 0.67)


def test_single_episode_update_uses_raw_advantage() -> None:
    """B = 1: no normalisation; a positive advantage raises the probability of that action."""
    agent = PPOLearner(PPOConfig(n_cameras=4, lr=1e-2, update_epochs=4))
    obs = agent.observe(np.full(4, 50.0))
    action = np.array([1, 1, 0, 0], dtype=np.int8)
    before = agent.probabilities(obs)
    logp = float(np.log(np.where(action == 1, before, 1 - before)).sum())
    agent.update(Batch(obs[None], action[None], np.array([logp]), np.array([5.0])))
    after = agent.probabilities(obs)
    assert np.all(after[:2] > before[:2]) and np.all(after[2:] < before[2:])


# --- checkpoints -----------------------------------------------------------------------------
def _trained(n: int = 5) -> PPOLearner:
    agent = PPOLearner(PPOConfig(n_cameras=n, lr=1e-2, seed=2))
    _learn(agent, np.random.default_rng(2), lambda aoi: aoi < 150.0, iters=3, batch=16)
    return agent


def test_checkpoint_round_trip(tmp_path) -> None:
    agent = _trained()
    path = tmp_path / "ckpt" / "agent.pt"
    agent.save(path, extra={"next_episode": 48})
    assert sorted(p.name for p in path.parent.iterdir()) == ["agent.pt"]  # no temp left
    loaded, extra = PPOLearner.load_with_extra(path)
    assert extra == {"next_episode": 48}
    assert loaded.config == agent.config
    assert (loaded.episodes, loaded.updates) == (agent.episodes, agent.updates)
    for a, b in zip(agent.net.state_dict().values(), loaded.net.state_dict().values(),
                    strict=True):
        assert torch.equal(a, b)
    # optimizer state restored: Adam's moments and step counts
    sa, sb = agent.optimizer.state_dict(), loaded.optimizer.state_dict()
    assert sa["param_groups"] == sb["param_groups"]
    for k, st in sa["state"].items():
        for name in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(st[name], sb["state"][k][name])
    # same actions: deterministic ones, and the sampled stream (the generator's state)
    rng = np.random.default_rng(9)
    for _ in range(10):
        obs = agent.observe(rng.uniform(0, 300, 5))
        assert np.array_equal(agent.probabilities(obs), loaded.probabilities(obs))
        x, y = agent.sample(obs), loaded.sample(obs)
        assert np.array_equal(x.action, y.action) and x.logp == pytest.approx(y.logp)
    # and the same update afterwards
    batch = Batch(np.stack([agent.observe(np.full(5, 10.0))] * 4), np.ones((4, 5), np.int8),
                  np.full(4, -3.0), np.array([1.0, 0.0, 0.5, 0.2]))
    assert agent.update(batch) == pytest.approx(loaded.update(batch))


def test_bad_checkpoints_give_clear_errors(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match="no PPO checkpoint"):
        PPOLearner.load(tmp_path / "missing.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a readable PPO checkpoint"):
        PPOLearner.load(junk)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, other)
    with pytest.raises(ValueError, match="not an aoi3d PPO checkpoint"):
        PPOLearner.load(other)
    agent = _trained()
    agent.save(tmp_path / "good.pt")
    doc = torch.load(tmp_path / "good.pt", weights_only=True)
    doc["version"] = 99
    torch.save(doc, tmp_path / "future.pt")
    with pytest.raises(ValueError, match="version 99"):
        PPOLearner.load(tmp_path / "future.pt")
    ckpt = agent.checkpoint()
    ckpt.config["n_cameras"] = 7  # weights no longer fit the config
    ckpt.write(tmp_path / "damaged.pt")
    with pytest.raises(ValueError, match="damaged PPO checkpoint"):
        PPOLearner.load(tmp_path / "damaged.pt")


# --- as a policy -----------------------------------------------------------------------------
def test_ppo_policy_via_registry(tmp_path) -> None:
    agent = _trained(5)
    path = tmp_path / "agent.pt"
    agent.save(path)
    pol = parse_policy(f"ppo:{path}")
    assert isinstance(pol, PPOPolicy) and pol.kind == "ppo"
    assert pol.spec == f"ppo:{path}" and parse_policy(pol.spec).spec == pol.spec
    assert pol.to_json() == {"kind": "ppo", "checkpoint": str(path), "learn": False}
    learner = policy_from_json({"kind": "ppo", "checkpoint": str(path), "learn": True})
    assert isinstance(learner, PPOPolicy) and learner.learn
    assert policy_from_json(learner.to_json()).to_json() == learner.to_json()
    aoi = np.array([10.0, 250.0, np.nan, 40.0, 120.0])
    mask = pol.select(aoi)
    assert mask.dtype == bool and mask.shape == (5,)
    expected = agent.select(aoi)
    assert mask.tolist() == (expected & ~np.isnan(aoi)).tolist()
    assert not pol.select(np.full(5, np.nan)).any()  # unknown AoI is never selected


def test_ppo_policy_errors(tmp_path) -> None:
    path = tmp_path / "agent.pt"
    _trained(5).save(path)
    pol = parse_policy(f"ppo:{path}")
    with pytest.raises(ValueError, match=r"trained for 5 cameras.*has 18"):
        pol.select(np.zeros(18))
    for bad in ("ppo", "ppo:", f"ppo:{tmp_path / 'missing.pt'}"):
        with pytest.raises(PolicySpecError, match="Accepted forms"):
            parse_policy(bad)
    for doc in ({"kind": "ppo"}, {"kind": "ppo", "checkpoint": str(path), "learn": "yes"},
                {"kind": "ppo", "checkpoint": str(path), "lr": 1}):
        with pytest.raises(PolicySpecError):
            policy_from_json(doc)


def test_ppo_policy_answers_its_questions(tmp_path) -> None:
    path = tmp_path / "agent.pt"
    _trained(5).save(path)
    pol = parse_policy(f"ppo:{path}")
    pol.check_fits(5)
    with pytest.raises(PolicySpecError, match="trained for 5 cameras, but there are N = 4"):
        pol.check_fits(4)
    assert not pol.learns and pol.wait_ms == 0 and pol.gamma_ms is None
    assert policy_from_json({"kind": "ppo", "checkpoint": str(path), "learn": True}).learns
    assert pol.on_device("cpu") is pol and pol.device == "cpu"
    if not torch.cuda.is_available():
        with pytest.raises(PolicySpecError, match="CUDA is not available"):
            pol.on_device("cuda")
    with pytest.raises(PolicySpecError, match="unknown device"):
        pol.on_device("tpu")


# --- online learning -------------------------------------------------------------------------
def test_online_learner_matches_rewards_updates_and_reports_to_its_hook(tmp_path) -> None:
    """The domain learner without the scheduler: sampled actions by decision id, rewards in
    decision order (earlier pending ones unscored), an update per batch — the same update as
    offline training — and a checkpoint on close; everything reported to the hook."""
    from aoi3d.rl.online import LearnConfig, LearnerHook, OnlineLearner, Outcome

    class Events(LearnerHook):
        def __init__(self) -> None:
            self.seen: list[tuple] = []

        def rewarded(self, unscored: int, pending: int) -> None:
            self.seen.append(("rewarded", unscored, pending))

        def ignored(self, reason: str) -> None:
            self.seen.append(("ignored", reason))

        def updated(self, episodes, stats, seconds) -> None:
            self.seen.append(("updated", episodes, stats["mean_reward"]))

        def saved(self, path) -> None:
            self.seen.append(("saved", path.name))

    agent = PPOLearner(PPOConfig(n_cameras=3, seed=7))
    twin = PPOLearner(PPOConfig(n_cameras=3, seed=7))
    hook = Events()
    learner = OnlineLearner(agent, source="src.pt", save_to=tmp_path / "online.pt",
                            config=LearnConfig(batch_size=2), hook=hook, wall=lambda: 0.0)
    aois = [np.array([10.0, 200.0, np.nan]), np.array([50.0, 20.0, 300.0]),
            np.array([90.0, 60.0, 30.0])]
    bits = [learner.act(i, aoi, 30.0 * i) for i, aoi in enumerate(aois, start=1)]
    # the acting copy samples what the agent would have sampled from its own generator
    expected = [twin.sample(twin.observe(a)).action.astype(bool) for a in aois]
    assert [b.tolist() for b in bits] == [e.tolist() for e in expected]
    assert learner.reward(1, 30.0, 0.5) == Outcome.USED
    assert learner.reward(1, 30.0, 0.5) == Outcome.DUPLICATE
    assert learner.reward(3, 90.0, 0.1) == Outcome.USED  # decision 2: unscored
    assert learner.reward(2, 60.0, 0.3) == Outcome.LATE
    stats = learner.update_if_ready()
    assert stats is not None and stats["mean_reward"] == pytest.approx(0.3)
    assert learner.update_if_ready() is None
    assert agent.updates == 1 and agent.episodes == 2
    assert learner.close() == tmp_path / "online.pt"
    assert hook.seen == [("rewarded", 0, 2), ("ignored", "duplicate"), ("rewarded", 1, 0),
                         ("ignored", "late"), ("updated", 2, pytest.approx(0.3)),
                         ("saved", "online.pt")]
    saved = PPOLearner.load(tmp_path / "online.pt")
    assert saved.updates == 1 and saved.episodes == 2


# --- a richer state: fixed per-camera features (issue 25, item 3) ----------------------------
def test_pose_features_measure_each_camera_against_the_held_out_view() -> None:
    from aoi3d.policy.ppo.obs import pose_features
    from aoi3d.scene.camera import look_at

    def at(deg: float) -> np.ndarray:
        a = np.radians(deg)
        return look_at(np.array([2 * np.cos(a), 2 * np.sin(a), 0.0]), np.zeros(3))

    v = pose_features(np.stack([at(0), at(90), at(180)]), at(0))
    assert v.shape == (3, 2)
    np.testing.assert_allclose(v[:, 0], [0.0, 0.5, 1.0], atol=1e-9)  # angle / π
    np.testing.assert_allclose(v[:, 1], [0.0, np.sqrt(8) / 4, 1.0], atol=1e-9)  # / farthest
    with pytest.raises(ValueError, match="poses"):
        pose_features(np.eye(4), at(0))


def test_an_agent_observes_its_rigs_camera_features() -> None:
    n = 3
    values = (0.0, 0.5, 1.0, 0.2, 0.4, 0.6)  # pose_angle of cameras 1..3, then pose_distance
    cfg = PPOConfig(n_cameras=n, arch="shared", features=["pose"], camera_features=values)
    assert cfg.features == ("pose",) and cfg.obs_dim == 4 * n and cfg.values_per_camera == 2
    assert PPOConfig.from_dict(cfg.to_dict()) == cfg
    agent = PPOLearner(cfg)
    obs = agent.observe(np.array([30.0, 60.0, np.nan]))
    np.testing.assert_allclose(obs, [0.1, 0.2, 1.0, 0, 0, 1, *values], atol=1e-7)
    # the shared actor reads the features as each camera's own channels: swapping two
    # cameras' features (and nothing else) swaps what the network sees of them
    with torch.no_grad():
        for p in agent.net.actor.g.parameters():
            p.copy_(torch.randn(p.shape, generator=torch.Generator().manual_seed(0)))
        agent.net.actor.embedding.zero_()
        agent.net.actor.bias.zero_()
    swapped = obs.copy()
    swapped[6:8], swapped[9:11] = obs[[7, 6]], obs[[10, 9]]
    base = agent.net.logits(torch.as_tensor(obs)).detach().numpy()
    moved = agent.net.logits(torch.as_tensor(swapped)).detach().numpy()
    assert not np.allclose(base, moved)
    same = obs.copy()
    same[[0, 1]], same[6:8], same[9:11] = obs[[1, 0]], obs[[7, 6]], obs[[10, 9]]
    np.testing.assert_allclose(agent.net.logits(torch.as_tensor(same)).detach().numpy()[[1, 0, 2]],
                               base, atol=1e-6)  # camera 1 and 2 swapped whole: logits swap
    for bad, match in ((dict(features=["colour"]), "features"),
                       (dict(features=["pose", "pose"], camera_features=values * 2), "distinct"),
                       (dict(features=["pose"], camera_features=values[:5]), "need 6"),
                       (dict(features=["pose"], camera_features=(2.0,) * 6), r"\[0, 1\]"),
                       (dict(camera_features=values), "need 0")):
        with pytest.raises(ValueError, match=match):
            PPOConfig(n_cameras=n, **bad)
