"""The agent's hyper-parameters, split by who needs them (torch-free).

:class:`AgentConfig` is what the acting side needs to rebuild the network of a checkpoint and
observe an AoI vector with it: N, the width, the actor's architecture, the untrained policy's
selection probability, the observation's AoI scale and the seed of the initial weights.
:class:`PPOConfig` is an :class:`AgentConfig` plus the PPO update's hyper-parameters (step
size, clip ε, epochs, minibatch, loss weights, gradient clipping) — what the learning side
(:class:`aoi3d.policy.ppo.learner.PPOLearner`) needs and the acting side never reads.

A checkpoint stores the learner's :class:`PPOConfig` as one flat dict (format
``aoi3d-ppo`` version 1, unchanged); the acting side reads it through :class:`PPOConfig` (so
a damaged value is caught the same way) and keeps its :attr:`PPOConfig.agent` part.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any, Self

from aoi3d.policy.ppo.obs import CAMERA_FEATURES, obs_size

__all__ = ["ARCHS", "AgentConfig", "PPOConfig"]

ARCHS = ("mlp", "shared")
"""Actor networks: a plain MLP over the observation, or one MLP shared by the cameras."""


def _check_int(name: str, value: Any, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}")


def _check_float(name: str, value: Any, low: float, high: float = math.inf, *,
                 open_low: bool = False, open_high: bool = False) -> None:
    ok = (isinstance(value, int | float) and not isinstance(value, bool)
          and math.isfinite(value)
          and (value > low if open_low else value >= low)
          and (value < high if open_high else value <= high))
    if not ok:
        lo, hi = "(" if open_low else "[", ")" if open_high else "]"
        raise ValueError(f"{name} must be a number in {lo}{low:g}, {high:g}{hi}, got {value!r}")


@dataclass(frozen=True)
class AgentConfig:
    """The network and its observation: what acting needs.

    ``n_cameras``: N, the length of the AoI vector and of the action. ``hidden``: width of the
    two hidden tanh layers of actor and critic. ``init_select_p``: the untrained policy's
    probability of selecting a camera. ``aoi_scale_ms``: the AoI that maps to 1.0 in the
    observation. ``seed``: initial weights (and, in the learner, sampled actions and
    minibatch order). ``arch``: the actor, ``mlp`` (CleanRL's: an MLP from the whole
    observation to the N logits) or ``shared``
    (:class:`aoi3d.policy.ppo.network.SharedCameraActor`: one small MLP applied to every
    camera's AoI with the mean over the cameras as context, plus a learned per-camera
    embedding and bias; it learns a per-camera rule from N samples per episode — see
    docs/ppo.md for the measured gain). ``features``: what the agent observes of each camera
    besides its AoI (:data:`aoi3d.policy.ppo.obs.CAMERA_FEATURES`; empty: the AoI vector
    alone, the paper's state); ``camera_features``: their values for the rig it was trained on
    (fixed per rig, so the checkpoint carries them: N values per feature value, value-major),
    appended to every observation. ``lag``: the agent also observes the expected lag L from
    the decision to its display (issue 40: :class:`aoi3d.policy.budget.DisplayLag` at the
    decision's budget), ``min(L / aoi_scale_ms, 1)`` as one more value per camera (the same
    for every camera, appended last), so an age Δn is read beside the delay to the screen.
    """

    n_cameras: int
    hidden: int = 64
    init_select_p: float = 0.5
    aoi_scale_ms: float = 300.0
    seed: int = 0
    arch: str = "mlp"
    features: tuple[str, ...] = ()
    camera_features: tuple[float, ...] = ()
    lag: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.lag, bool):
            raise ValueError(f"lag must be a bool, got {self.lag!r}")
        if self.arch not in ARCHS:
            raise ValueError(f"arch must be one of {ARCHS}, got {self.arch!r}")
        if isinstance(self.features, str) or not isinstance(self.features, list | tuple):
            raise ValueError(f"features must be a list of names, got {self.features!r}")
        unknown = [f for f in self.features if f not in CAMERA_FEATURES]
        if unknown or len(set(self.features)) != len(self.features):
            raise ValueError(f"features must be distinct names among "
                             f"{sorted(CAMERA_FEATURES)}, got {list(self.features)!r}")
        object.__setattr__(self, "features", tuple(self.features))
        if not isinstance(self.camera_features, list | tuple) or not all(
                isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                and 0.0 <= v <= 1.0 for v in self.camera_features):
            raise ValueError("camera_features must be numbers in [0, 1]")
        object.__setattr__(self, "camera_features", tuple(float(v) for v in self.camera_features))
        _check_int("n_cameras", self.n_cameras, 1)
        _check_int("hidden", self.hidden, 1)
        _check_int("seed", self.seed, 0)
        _check_float("init_select_p", self.init_select_p, 0.0, 1.0, open_low=True,
                     open_high=True)
        _check_float("aoi_scale_ms", self.aoi_scale_ms, 0.0, open_low=True)
        want = self.n_cameras * self.values_per_camera
        if len(self.camera_features) != want:
            raise ValueError(f"features {list(self.features)} need {want} camera_features "
                             f"(N = {self.n_cameras} × {self.values_per_camera}), got "
                             f"{len(self.camera_features)}")

    @property
    def values_per_camera(self) -> int:
        """Fixed values observed per camera besides its AoI and unknown flag."""
        return sum(len(CAMERA_FEATURES[f]) for f in self.features)

    @property
    def channels(self) -> int:
        """Values observed per camera: its AoI, its unknown flag, its fixed features and,
        with ``lag``, the lag to the display."""
        return 2 + self.values_per_camera + int(self.lag)

    @property
    def obs_dim(self) -> int:
        """Length of the observation (channels · N)."""
        return obs_size(self.n_cameras, self.channels - 2)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Self:
        """Build from a dict; unknown keys or bad values raise ``ValueError``."""
        if not isinstance(data, dict):
            raise ValueError(f"PPO config must be a JSON object, got {type(data).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown PPO config key(s) {unknown}; known: {sorted(known)}")
        if "n_cameras" not in data:
            raise ValueError("PPO config needs n_cameras")
        return cls(**data)


@dataclass(frozen=True)
class PPOConfig(AgentConfig):
    """An :class:`AgentConfig` and the PPO update's hyper-parameters: what learning needs
    (everything a checkpoint stores).

    ``lr``: Adam step size. ``clip_eps``: ε of the clipped surrogate. ``update_epochs``
    passes over each batch in ``minibatch_size`` chunks. ``vf_coef`` / ``ent_coef``: weights
    of the value loss and the entropy bonus. ``max_grad_norm``: gradient clipping.
    ``norm_adv``: normalise advantages within a batch (of more than one episode).
    """

    lr: float = 3e-4
    clip_eps: float = 0.2
    update_epochs: int = 10
    minibatch_size: int = 16
    vf_coef: float = 0.5
    ent_coef: float = 0.01
    max_grad_norm: float = 0.5
    norm_adv: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_int("update_epochs", self.update_epochs, 1)
        _check_int("minibatch_size", self.minibatch_size, 1)
        _check_float("lr", self.lr, 0.0, open_low=True)
        _check_float("clip_eps", self.clip_eps, 0.0, open_low=True)
        _check_float("vf_coef", self.vf_coef, 0.0)
        _check_float("ent_coef", self.ent_coef, 0.0)
        _check_float("max_grad_norm", self.max_grad_norm, 0.0, open_low=True)
        if not isinstance(self.norm_adv, bool):
            raise ValueError(f"norm_adv must be a bool, got {self.norm_adv!r}")

    @property
    def agent(self) -> AgentConfig:
        """The acting side's part of this config."""
        return AgentConfig(**{f.name: getattr(self, f.name) for f in fields(AgentConfig)})
