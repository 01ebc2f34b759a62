"""The acting side of the agent (imports torch): a network that selects cameras.

:class:`Actor` holds the network (:class:`~aoi3d.policy.ppo.network.ActorCritic`) of an
:class:`~aoi3d.policy.ppo.config.AgentConfig`: it observes an AoI vector
(:func:`~aoi3d.policy.ppo.obs.encode_aoi`) and takes the deterministic action — camera n iff
p_n ≥ 0.5 — which is what a ``ppo`` policy (:class:`~aoi3d.policy.ppo.policy.PPOPolicy`)
does. :meth:`Actor.load` rebuilds one from a checkpoint
(:class:`~aoi3d.policy.ppo.checkpoint.Checkpoint`). The learning side,
:class:`~aoi3d.policy.ppo.learner.PPOLearner`, is an :class:`Actor` that also samples,
updates and writes checkpoints.

Imported only when a ``ppo`` policy or a learner is built: :mod:`aoi3d.policy.ppo.policy`
stays torch-free.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Self

import numpy as np
import torch

from aoi3d.device import resolve_device
from aoi3d.policy.ppo.checkpoint import Checkpoint
from aoi3d.policy.ppo.config import AgentConfig, PPOConfig
from aoi3d.policy.ppo.network import ActorCritic
from aoi3d.policy.ppo.obs import encode_aoi, with_camera_features, with_lag

__all__ = ["Actor"]


class Actor:
    """A network with its config, acting on AoI vectors.

    ``generator``: the ``torch.Generator`` (seeded from ``config.seed``) the initial weights
    are drawn from — and, in the learner, the sampled actions and minibatch orders.
    ``episodes`` / ``updates``: what the network has learned from (as its checkpoint says).
    """

    def __init__(self, config: AgentConfig, device: str = "cpu") -> None:
        if not isinstance(config, AgentConfig):
            raise TypeError(f"config must be an AgentConfig, got {type(config).__name__}")
        self.config = config
        self.device = torch.device(resolve_device(device))  # auto, cpu or cuda
        self.generator = torch.Generator(device="cpu").manual_seed(config.seed)
        self.net = ActorCritic(config, self.generator).to(self.device)
        self.episodes = 0
        self.updates = 0

    # --- acting --------------------------------------------------------------------------
    def observe(self, aoi_ms: np.ndarray, lag_ms: float | None = None) -> np.ndarray:
        """The observation of an AoI vector (ms, NaN = unknown), with the config's scale and,
        when the agent observes more of each camera, its rig's fixed camera features, and,
        when it observes the lag to the display (``config.lag``), ``lag_ms`` (None: 0, no
        lag known; ignored by an agent that does not observe it)."""
        aoi = np.asarray(aoi_ms, dtype=np.float64)
        cfg = self.config
        if aoi.ndim != 1 or aoi.shape[0] != cfg.n_cameras:
            raise ValueError(f"this agent was trained for {cfg.n_cameras} cameras; "
                             f"got an AoI vector of shape {aoi.shape}")
        obs = encode_aoi(aoi, cfg.aoi_scale_ms)
        if cfg.features:
            values = np.asarray(cfg.camera_features).reshape(cfg.values_per_camera,
                                                             cfg.n_cameras)
            obs = with_camera_features(obs, values.T)
        if cfg.lag:
            obs = with_lag(obs, cfg.n_cameras, 0.0 if lag_ms is None else float(lag_ms),
                           cfg.aoi_scale_ms)
        return obs

    def obs_tensor(self, obs: np.ndarray, batch: bool) -> torch.Tensor:
        """Observations (D,) or, with ``batch``, (B, D) as a tensor on the device, D the
        config's ``obs_dim`` (2N for the AoI vector alone)."""
        arr = np.asarray(obs, dtype=np.float32)
        ndim = 2 if batch else 1
        if arr.ndim != ndim or arr.shape[-1] != self.config.obs_dim or arr.shape[0] < 1:
            shape = "(B, D)" if batch else "(D,)"
            raise ValueError(f"observation must have shape {shape} with D = "
                             f"{self.config.obs_dim}, got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError("observation holds non-finite values")
        return torch.as_tensor(arr, device=self.device)

    @torch.no_grad()
    def probabilities(self, obs: np.ndarray) -> np.ndarray:
        """p_n, each camera's selection probability, on an observation (float32, N)."""
        return torch.sigmoid(self.net.logits(self.obs_tensor(obs, batch=False))).cpu().numpy()

    def select(self, aoi_ms: np.ndarray, lag_ms: float | None = None) -> np.ndarray:
        """The deterministic action on an AoI vector (and the lag to the display, for an
        agent that observes it): bit n = (p_n ≥ 0.5), as booleans."""
        return self.probabilities(self.observe(aoi_ms, lag_ms)) >= 0.5

    # --- checkpoints ---------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path, device: str = "cpu") -> Self:
        """Rebuild from a checkpoint. A missing file raises ``FileNotFoundError``; anything
        that is not a readable checkpoint of this format and version raises ``ValueError``
        saying why."""
        obj, _ = cls.load_with_extra(path, device)
        return obj

    @classmethod
    def load_with_extra(cls, path: str | Path, device: str = "cpu"
                        ) -> tuple[Self, dict[str, Any]]:
        """:meth:`load`, and the ``extra`` data saved with the checkpoint."""
        ckpt = Checkpoint.read(path)
        try:
            obj = cls(cls._config_of(PPOConfig.from_dict(ckpt.config)), device=device)
            obj.restore(ckpt)
        except (KeyError, TypeError, RuntimeError, ValueError) as err:
            raise ValueError(f"{path}: damaged PPO checkpoint: {type(err).__name__}: "
                             f"{str(err).splitlines()[0][:200]}") from None
        obj.net.eval()
        return obj, ckpt.extra

    @staticmethod
    def _config_of(stored: PPOConfig) -> AgentConfig:
        """The part of a checkpoint's config this side keeps: the acting one."""
        return stored.agent

    def restore(self, ckpt: Checkpoint) -> None:
        """Take the weights and counts of a checkpoint."""
        self.net.load_state_dict(ckpt.model)
        self.episodes = ckpt.episodes
        self.updates = ckpt.updates
