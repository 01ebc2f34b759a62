"""The PPO checkpoint shipped in models/ppo/quick (the README's PPO example uses it)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from aoi3d.experiment.config import EXPERIMENT_SCENE
from aoi3d.policy import parse_policy

ROOT = Path(__file__).resolve().parents[3]
SHIPPED = ROOT / "models" / "ppo" / "quick"


def test_shipped_checkpoint_loads_and_fits_the_default_scene() -> None:
    policy = parse_policy(f"ppo:{SHIPPED / 'final.pt'}")
    assert policy.kind == "ppo"
    assert policy.n_cameras == EXPERIMENT_SCENE.n_train == 18
    aoi = np.array([30.0, 60.0, 90.0, np.nan] * 4 + [30.0, 120.0])
    mask = np.asarray(policy.select(aoi), dtype=bool)
    assert mask.shape == (18,) and not mask[3]  # never a camera without a frame


def test_shipped_checkpoint_loads_on_both_sides() -> None:
    """The checkpoint format is unchanged by the agent's move to aoi3d/policy/ppo/: the acting
    side keeps the AgentConfig part of the stored config, the learner the whole PPOConfig
    (its update's hyper-parameters, optimizer state and generator) — and both act alike."""
    from aoi3d.policy.ppo import AgentConfig, PPOConfig
    from aoi3d.policy.ppo.actor import Actor
    from aoi3d.policy.ppo.learner import PPOLearner

    actor, extra = Actor.load_with_extra(SHIPPED / "final.pt")
    learner = PPOLearner.load(SHIPPED / "final.pt")
    assert type(actor.config) is AgentConfig and isinstance(learner.config, PPOConfig)
    assert learner.config.agent == actor.config and learner.updates == actor.updates > 0
    assert extra["preset"] == "quick" and "episode_config" in extra
    aoi = np.random.default_rng(0).uniform(0, 300, (20, 18))
    assert all((actor.select(a) == learner.select(a)).all() for a in aoi)


def test_shipped_checkpoint_comes_with_its_training_record() -> None:
    command = (SHIPPED / "COMMAND").read_text()
    assert "aoi3d ppo train --preset quick" in command
    with (SHIPPED / "episodes.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 600


def test_the_experiments_budget_agent_observes_pose_and_comes_with_its_record() -> None:
    """models/ppo/quick300: trained at 300 field steps with features=pose (the compare run of
    `make science` scores it); its rig's geometry is in the checkpoint."""
    from aoi3d.policy.ppo.actor import Actor

    folder = ROOT / "models" / "ppo" / "quick300"
    actor, extra = Actor.load_with_extra(folder / "final.pt")
    cfg = actor.config
    assert cfg.features == ("pose",) and cfg.n_cameras == EXPERIMENT_SCENE.n_train
    assert len(cfg.camera_features) == 2 * cfg.n_cameras
    assert extra["episode_config"]["steps_per_epoch"] == 300
    assert actor.observe(np.full(cfg.n_cameras, 60.0)).shape == (4 * cfg.n_cameras,)
    policy = parse_policy(f"ppo:{folder / 'final.pt'}")
    aoi = np.array([30.0, 60.0, 90.0, np.nan] * 4 + [30.0, 120.0])
    assert not np.asarray(policy.select(aoi), dtype=bool)[3]
    assert "--features pose" in (folder / "COMMAND").read_text()
    with (folder / "episodes.csv").open() as f:
        assert len(list(csv.DictReader(f))) == 600
