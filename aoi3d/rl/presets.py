"""What a PPO training run is: the named budgets, the training config, and the seeds.

Seeds: training episode i uses channel seed ``TRAIN_SEED_BASE + i``; evaluation uses
``EVAL_SEED_BASE + k`` — disjoint by construction (training is capped below
``EVAL_SEED_BASE − TRAIN_SEED_BASE`` episodes), and both disjoint from the experiment
sweeps' seeds 0, 1, 2, … (so ``aoi3d experiment compare`` scores a trained agent on channel
draws it never saw).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

from aoi3d.experiment import EpisodeConfig, get_preset
from aoi3d.policy.ppo import PPOConfig

__all__ = [
    "EVAL_SEED_BASE",
    "MAX_TRAIN_EPISODES",
    "PPO_PRESETS",
    "TRAIN_SEED_BASE",
    "PPOPreset",
    "TrainConfig",
    "eval_seeds",
    "get_ppo_preset",
    "train_seed",
]

TRAIN_SEED_BASE = 100_000
"""Channel seed of training episode 0 (episode i: ``TRAIN_SEED_BASE + i``)."""
EVAL_SEED_BASE = 1_000_000
"""First held-out seed of :func:`evaluate` (``EVAL_SEED_BASE + k``)."""
MAX_TRAIN_EPISODES = EVAL_SEED_BASE - TRAIN_SEED_BASE


def train_seed(episode: int, offset: int = 0) -> int:
    """The channel seed of training episode ``episode`` (0-based) of a run whose seeds start
    ``offset`` after :data:`TRAIN_SEED_BASE`."""
    if not 0 <= offset + episode < MAX_TRAIN_EPISODES or offset < 0 or episode < 0:
        raise ValueError(f"training seed offset + episode index must be in [0, "
                         f"{MAX_TRAIN_EPISODES}), got {offset} + {episode}")
    return TRAIN_SEED_BASE + offset + episode


def eval_seeds(count: int, offset: int = 0) -> list[int]:
    """``count`` held-out seeds, the ``offset``-th first; never a training seed."""
    if count < 1 or offset < 0:
        raise ValueError(f"need count >= 1 and offset >= 0, got {count}, {offset}")
    return [EVAL_SEED_BASE + offset + k for k in range(count)]


@dataclass(frozen=True)
class PPOPreset:
    """A named training budget: the environment's episode config (an experiment preset's,
    with the PPO overrides), the episodes, the batch size, the agent's hyper-parameters
    (``ppo``: :class:`PPOConfig` fields but ``n_cameras``, which the dataset gives) and the
    held-out seeds of ``aoi3d ppo eval``."""

    name: str
    episode: EpisodeConfig
    episodes: int
    batch_size: int
    ppo: Mapping[str, Any]
    eval_seeds: int
    note: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "episode": self.episode.to_dict(), "episodes": self.episodes,
                "batch_size": self.batch_size, "ppo": dict(self.ppo),
                "eval_seeds": self.eval_seeds, "note": self.note}


_PPO_HYPER = {"arch": "shared", "hidden": 64, "lr": 1e-3, "clip_eps": 0.2,
              "update_epochs": 10, "minibatch_size": 8, "ent_coef": 0.01, "vf_coef": 0.5,
              "max_grad_norm": 0.5, "init_select_p": 0.5, "aoi_scale_ms": 300.0, "seed": 0}
"""The presets' agent: the camera-shared actor learns the per-camera rule within 600
episodes where the plain MLP barely moves (docs/ppo.md, "Which network")."""

PPO_PRESETS: dict[str, PPOPreset] = {
    "quick": PPOPreset(
        name="quick",
        episode=get_preset("quick").episode.with_(steps_per_epoch=100),
        episodes=600, batch_size=16, ppo=dict(_PPO_HYPER), eval_seeds=40,
        note="the experiment quick preset's episode with 100 field steps per decision "
             "instead of 300 (≈ 3 s instead of ≈ 9 s an episode on one core; see "
             "docs/ppo.md): 600 episodes ≤ 30 min on 2 cores",
    ),
    "paper": PPOPreset(
        name="paper",
        episode=get_preset("paper").episode,
        episodes=600, batch_size=16, ppo=dict(_PPO_HYPER), eval_seeds=100,
        note="the experiment paper preset's episode (1000 steps per decision): for a GPU or "
             "many cores",
    ),
}


def get_ppo_preset(name: str) -> PPOPreset:
    """The PPO preset ``name``; ``ValueError`` listing the known ones."""
    try:
        return PPO_PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown PPO preset {name!r}; known: {', '.join(PPO_PRESETS)}"
                         ) from None


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on (written to ``config.json`` and the checkpoint).

    ``checkpoint_every``: updates between two checkpoints (and CSV/plot refreshes).
    ``seed_offset``: training episode i uses channel seed ``TRAIN_SEED_BASE + seed_offset + i``.
    ``reward``: the env's reward (``reward_display``: at display time, issue 40);
    ``budgets``: the budgets an episode's render is drawn from (empty: the episode config's);
    see :class:`aoi3d.rl.env.FrameSelectionEnv`.
    """

    episode: EpisodeConfig
    ppo: PPOConfig
    episodes: int
    batch_size: int
    checkpoint_every: int = 5
    preset: str = "custom"
    seed_offset: int = 0
    reward: str = "reward"
    budgets: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        from aoi3d.policy.budget import check_budget
        from aoi3d.rl.env import REWARDS

        if self.reward not in REWARDS:
            raise ValueError(f"reward must be one of {REWARDS}, got {self.reward!r}")
        if isinstance(self.budgets, str) or not isinstance(self.budgets, list | tuple):
            raise ValueError(f"budgets must be a list of training steps, got {self.budgets!r}")
        object.__setattr__(self, "budgets", tuple(check_budget(b) for b in self.budgets))
        for name, value, low in (("episodes", self.episodes, 1),
                                 ("batch_size", self.batch_size, 1),
                                 ("seed_offset", self.seed_offset, 0),
                                 ("checkpoint_every", self.checkpoint_every, 1)):
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
        if self.seed_offset + self.episodes > MAX_TRAIN_EPISODES:
            raise ValueError(f"seed_offset + episodes must be <= {MAX_TRAIN_EPISODES} "
                             f"(training seeds stay below the held-out ones), got "
                             f"{self.seed_offset} + {self.episodes}")

    @classmethod
    def from_preset(cls, preset: PPOPreset, n_cameras: int, **changes: Any) -> TrainConfig:
        """The preset's config for ``n_cameras`` cameras, with ``changes`` applied."""
        ppo = PPOConfig(n_cameras=n_cameras, **dict(preset.ppo))
        base = cls(episode=preset.episode, ppo=ppo, episodes=preset.episodes,
                   batch_size=preset.batch_size, preset=preset.name)
        return replace(base, **changes)

    def to_dict(self) -> dict[str, Any]:
        return {"episode": self.episode.to_dict(), "ppo": self.ppo.to_dict(),
                "episodes": self.episodes, "batch_size": self.batch_size,
                "checkpoint_every": self.checkpoint_every, "preset": self.preset,
                "seed_offset": self.seed_offset, "reward": self.reward,
                "budgets": list(self.budgets)}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> TrainConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown training config key(s) {unknown}")
        doc = dict(data)
        doc["episode"] = EpisodeConfig.from_dict(dict(doc["episode"]))
        doc["ppo"] = PPOConfig.from_dict(dict(doc["ppo"]))
        return cls(**doc)
