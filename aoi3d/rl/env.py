"""``aoi3d/FrameSelection-v0``: one decision of the virtual-clock episode as a gymnasium env.

An episode of this environment is a single step — the paper's single-step formulation:

- :meth:`FrameSelectionEnv.reset` (seed s) simulates the N links for seed s with the
  experiment engine (:func:`aoi3d.experiment.episode.episode_links` and
  :func:`~aoi3d.experiment.plan_episode`: the same channel, camera phases and scene offset as
  an experiment episode of seed s), past the warm-up, and picks one of the config's scored
  decision epochs t (uniformly, from a stream of s). The observation is the AoI vector Δ(t),
  encoded by :func:`aoi3d.policy.ppo.obs.encode_aoi`.
- :meth:`FrameSelectionEnv.step` (a 0/1 mask over the N cameras) trains a *fresh* radiance
  field (``carry="fresh"``, model seed s) ``steps_per_epoch`` steps on the selected cameras'
  newest delivered frames (generated at U_n(t)), renders the held-out camera for time t and
  scores it against the truth: reward = w·(PSNR, SSIM, LPIPS) with the config's
  :class:`aoi3d.quality.RewardWeights`. ``terminated`` is always True. The action is taken
  through the decision step every setting shares (:func:`aoi3d.policy.decide.decide`, with
  the action in the policy's place): cameras whose AoI is unknown cannot be used (their bits
  are ignored); an empty selection is a valid action and scores the untrained model.

The training and scoring is :func:`aoi3d.experiment.run_plan` on a one-decision plan, so
the numbers are those of the experiment engine, and results can be kept in a
:class:`aoi3d.experiment.ResultCache` under :func:`aoi3d.experiment.plan_key` — a repeated
(seed, selection, budget) is then computed once.

Issue 40, what a viewer sees: ``reward="reward_display"`` makes the step's reward the one at
display time (the render scored against the truth once its compute is done, the virtual
clock's lag L later); ``budgets`` draws each episode's budget (training steps of its render)
from a small set, by the seed, so that L varies between episodes (at one budget L is a
constant of the cost model: no queue); ``observe_lag`` appends L at the episode's budget to
the observation (:func:`aoi3d.policy.ppo.obs.with_lag`).

``info`` of ``step``: ``psnr``, ``ssim``, ``lpips`` (None without LPIPS weights), ``reward``
(the decision-time reward, whatever the env's ``reward``), ``reward_display``,
``psnr_display``, ``n_selected``, ``selected`` (camera ids), ``aoi`` (the AoI vector, ms, NaN
unknown), ``aoi_used_ms``, ``eval_ms``, ``seed``, ``key``, ``budget`` and ``lag_ms``.
Wall time and whether the result came from
the cache are on the env (:attr:`FrameSelectionEnv.last_outcome`), not in ``info``: the same
seed and action give the same ``info``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from io import BytesIO
from pathlib import Path
from typing import Any, ClassVar, SupportsFloat

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from PIL import Image

from aoi3d.experiment import (
    EpisodeConfig,
    EpisodePlan,
    EpisodeResult,
    PlannedDecision,
    ResultCache,
    plan_episode,
    plan_key,
    run_plan,
)
from aoi3d.experiment.episode import EpisodeLinks, episode_links, planned_decision, train_ids
from aoi3d.experiment.episode.plan import display_lag
from aoi3d.experiment.sweep import lpips_available
from aoi3d.metric import REWARD, REWARD_DISPLAY
from aoi3d.policy import AllPolicy, Policy, Selection, decide
from aoi3d.policy.budget import check_budget
from aoi3d.policy.decide import Act
from aoi3d.policy.ppo.obs import encode_aoi, obs_size, with_lag
from aoi3d.quality import LpipsFn
from aoi3d.scene import SceneDataset, open_dataset, to_uint8

__all__ = ["REWARDS", "FrameSelectionEnv", "StepOutcome"]

_PICK_STREAM = 0x5E1
"""Stream (spawn key) of the decision epoch's draw; apart from the channel's and the aux's."""
_BUDGET_STREAM = 0x5E2
"""Stream of the episode's budget draw (``budgets``)."""
REWARDS = (REWARD.name, REWARD_DISPLAY.name)
"""What a step may return as its reward: the score at the decision's time, or at display."""


@dataclass(frozen=True)
class StepOutcome:
    """How the last step was computed: its result, wall time, and whether it was cached."""

    result: EpisodeResult
    cached: bool
    wall_s: float


class FrameSelectionEnv(gym.Env[np.ndarray, np.ndarray]):
    """Select the cameras whose newest frames train the radiance field at one decision.

    ``config``: an :class:`~aoi3d.experiment.EpisodeConfig` (or its dict; None: the defaults)
    whose channel, warm-up, scored span, field and budget (``steps_per_epoch``), reward
    weights, LPIPS switch and device are used; ``carry`` is always ``fresh`` here.
    ``dataset``: a folder or an open :class:`~aoi3d.scene.SceneDataset` (default: the
    config's). ``aoi_scale_ms``: the observation's AoI scale (the agent's). ``cache``: a
    :class:`~aoi3d.experiment.ResultCache` or its folder, for repeated (seed, selection).
    ``lpips_fn``: the LPIPS network to use when the config asks for LPIPS (default: loaded
    from the cached weights at the first step that scores; without them, no LPIPS).
    ``reward``, ``budgets``, ``observe_lag``: what a viewer sees (see the module).
    """

    # gymnasium documents metadata as a class attribute but types it as an instance one
    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 1}  # type: ignore[misc]

    def __init__(
        self,
        config: EpisodeConfig | Mapping[str, Any] | None = None,
        dataset: str | Path | SceneDataset | None = None,
        *,
        aoi_scale_ms: float = 300.0,
        cache: ResultCache | str | Path | None = None,
        lpips_fn: LpipsFn | None = None,
        render_mode: str | None = None,
        reward: str = "reward",
        budgets: tuple[int, ...] = (),
        observe_lag: bool = False,
    ) -> None:
        super().__init__()
        if config is None:
            cfg = EpisodeConfig()
        elif isinstance(config, EpisodeConfig):
            cfg = config
        else:
            cfg = EpisodeConfig.from_dict(dict(config))
        if isinstance(dataset, SceneDataset):
            ds = dataset
        else:
            ds = open_dataset(dataset if dataset is not None else cfg.dataset)
        self.config = cfg.with_(carry="fresh", dataset=str(ds.root))
        self.dataset = ds
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of "
                             f"{self.metadata['render_modes']}, got {render_mode!r}")
        self.render_mode = render_mode
        encode_aoi(np.zeros(1), aoi_scale_ms)  # validates the scale
        self.aoi_scale_ms = float(aoi_scale_ms)
        self.cache = cache if isinstance(cache, ResultCache | None) else ResultCache(cache)
        self.lpips = self.config.lpips and (lpips_fn is not None
                                            or lpips_available(self.config))
        self._lpips_fn = lpips_fn if self.lpips else None  # else loaded by the first step
        if reward not in REWARDS:
            raise ValueError(f"reward must be one of {REWARDS}, got {reward!r}")
        self.reward = reward
        self.budgets = tuple(check_budget(b) for b in budgets)  # the carry is fresh here
        self.observe_lag = bool(observe_lag)
        self.lag = display_lag(self.config)
        self._budget: int | None = None
        self.camera_ids: tuple[int, ...] = tuple(train_ids(self.config, ds))
        n = len(self.camera_ids)
        self.observation_space = spaces.Box(0.0, 1.0, shape=(obs_size(n, int(observe_lag)),),
                                            dtype=np.float32)
        self.action_space = spaces.MultiBinary(n)
        self._plan: EpisodePlan | None = None
        self._decision: PlannedDecision | None = None
        self._links: EpisodeLinks | None = None
        self._aoi: np.ndarray | None = None
        self._last_image: np.ndarray | None = None
        self.last_outcome: StepOutcome | None = None

    @property
    def n_cameras(self) -> int:
        """N: cameras the agent chooses from (the config's first ``n_cameras``)."""
        return len(self.camera_ids)

    @property
    def aoi_ms(self) -> np.ndarray:
        """The AoI vector of the current episode (ms, NaN = unknown); after :meth:`reset`."""
        if self._aoi is None:
            raise RuntimeError("call reset() first")
        return self._aoi.copy()

    # --- gymnasium API ---------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        """Draw a channel state: seed s (``seed``, else drawn from the env's generator) →
        the links' history, a scored decision epoch t, the AoI vector Δ(t)."""
        super().reset(seed=seed)
        if seed is not None:
            if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
                raise ValueError(f"seed must be an int >= 0, got {seed!r}")
            episode_seed = int(seed)
        else:
            episode_seed = int(self.np_random.integers(0, 2**31 - 1))
        links = episode_links(self.config, self.dataset, episode_seed)
        plan = plan_episode(self.config, self.dataset, AllPolicy(), episode_seed, links=links)
        scored = [d for d in plan.decisions if d.scored]
        pick = np.random.default_rng(np.random.SeedSequence(episode_seed,
                                                            spawn_key=(_PICK_STREAM,)))
        decision = scored[int(pick.integers(len(scored)))]
        aoi = self._select(decision.decision_ms, links).aoi_ms
        self._plan, self._decision, self._links, self._aoi = plan, decision, links, aoi
        self._budget = None
        if self.budgets:
            draw = np.random.default_rng(np.random.SeedSequence(episode_seed,
                                                                spawn_key=(_BUDGET_STREAM,)))
            self._budget = self.budgets[int(draw.integers(len(self.budgets)))]
        self._last_image = None
        info = {"seed": episode_seed, "eval_ms": decision.eval_ms, "aoi": aoi.copy(),
                "budget": self.budget, "lag_ms": self.lag_ms}
        return self._observation(), info

    @property
    def budget(self) -> int:
        """The training steps of the current episode's render (drawn from ``budgets``, else
        the config's)."""
        return self.lag.default_steps if self._budget is None else self._budget

    @property
    def lag_ms(self) -> float:
        """L: the virtual clock's lag from the decision to its display at :attr:`budget`."""
        return self.lag.lag_ms(self.budget)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, SupportsFloat, bool, bool,
                                                dict[str, Any]]:
        """Train a fresh field on the selected cameras' newest frames, score the novel view."""
        if self._plan is None or self._decision is None or self._aoi is None:
            raise RuntimeError("call reset() before step(): every episode is a single step")
        mask = self._mask(action)
        plan = self.plan_for(mask)
        key = plan_key(plan, self.dataset, lpips=self.lpips)
        images: list[np.ndarray] = []
        hit = self.cache.get(key) if self.cache is not None else None
        if hit is not None:
            assert self.cache is not None  # a hit comes from the cache
            result = hit
            png = self.cache.render_png(key) if self.render_mode else None
            if png:
                images.append(np.asarray(Image.open(BytesIO(png)).convert("RGB")))
            self.last_outcome = StepOutcome(result, cached=True, wall_s=0.0)
        else:
            result, png = run_plan(plan, self.dataset, key=key, lpips_fn=self._lpips(),
                                   on_render=lambda _d, img: images.append(img))
            if self.cache is not None:
                self.cache.put(result, png)
            self.last_outcome = StepOutcome(result, cached=False, wall_s=result.wall_s)
        if images:
            image = images[-1]
            self._last_image = to_uint8(image)
        score = result.epochs[0]
        selected = plan.decisions[0].cameras
        info = {
            "seed": plan.seed, "eval_ms": score.eval_ms, "key": key,
            "psnr": score.psnr_db, "ssim": score.ssim, "lpips": score.lpips,
            "reward": score.reward, "n_selected": len(selected), "selected": list(selected),
            "aoi": self._aoi.copy(), "aoi_used_ms": score.aoi_used_ms,
            "reward_display": score.reward_display, "psnr_display": score.psnr_display_db,
            "budget": self.budget, "lag_ms": self.lag_ms,
        }
        obs = self._observation()
        self._plan = self._decision = None  # one step per episode
        return obs, float(getattr(score, self.reward)), True, False, info

    def render(self) -> np.ndarray | None:  # type: ignore[override]
        """The last novel-view render (uint8 H×W×3) with ``render_mode="rgb_array"``."""
        if self.render_mode != "rgb_array":
            return None
        if self._last_image is None:
            return np.zeros((self.dataset.height, self.dataset.width, 3), dtype=np.uint8)
        return self._last_image.copy()

    # --- helpers ---------------------------------------------------------------------------
    def plan_for(self, mask: np.ndarray) -> EpisodePlan:
        """The one-decision plan that trains on the cameras of ``mask`` (boolean, N) at the
        current episode's decision epoch; cameras of unknown AoI are dropped."""
        if self._plan is None or self._decision is None or self._links is None:
            raise RuntimeError("call reset() first")
        action = np.asarray(mask, dtype=bool)
        sel = self._select(self._decision.decision_ms, self._links, act=lambda _a, _s: action)
        bits = "".join("1" if u else "0" for u in sel.mask)
        decision = planned_decision(sel, self.camera_ids, train=True, scored=True)
        if self._budget is not None:
            decision = replace(decision, budget_steps=self._budget)
        return replace(self._plan, policy=f"mask:{bits}", decisions=(decision,))

    def check_policy(self, policy: Policy) -> None:
        """``ValueError`` unless ``policy`` can act here: it must fit the N cameras and decide
        at the epoch (a waiting policy is scored by ``aoi3d experiment compare``)."""
        if policy.wait_ms:
            raise ValueError(f"{policy.spec}: the environment decides at the epoch; waiting "
                             "policies are scored by `aoi3d experiment compare`")
        policy.check_fits(self.n_cameras)

    def policy_action(self, policy: Policy) -> np.ndarray:
        """What ``policy`` selects at the current episode's decision epoch (bool per camera),
        by the decision step every setting shares (:meth:`check_policy` first)."""
        if self._decision is None or self._links is None:
            raise RuntimeError("call reset() first")
        self.check_policy(policy)
        return decide(policy, self._decision.decision_ms, self._links.newest_ms).mask

    @staticmethod
    def _select(t_ms: int, links: EpisodeLinks, act: Act | None = None) -> Selection:
        """The decision step at epoch ``t_ms``: every known camera, or ``act``'s bits (the
        agent's action in place of a policy; the env decides at the epoch, no wait)."""
        return decide(AllPolicy(), t_ms, links.newest_ms, act=act)

    def _lpips(self) -> LpipsFn | None:
        if self.lpips and self._lpips_fn is None:
            from aoi3d.lpips import load_lpips_fn

            self._lpips_fn = load_lpips_fn(device=self.config.device)
            if self._lpips_fn is None:
                raise RuntimeError("LPIPS weights vanished while the environment ran")
        return self._lpips_fn

    def _mask(self, action: np.ndarray) -> np.ndarray:
        arr = np.asarray(action)
        if arr.shape != (self.n_cameras,):
            raise ValueError(f"action must be {self.n_cameras} bits (one per camera), got "
                             f"shape {arr.shape}")
        if arr.dtype != bool and not np.isin(arr, (0, 1)).all():
            raise ValueError(f"action bits must be 0 or 1, got {arr.tolist()}")
        return arr.astype(bool)

    def _observation(self) -> np.ndarray:
        assert self._aoi is not None
        obs = encode_aoi(self._aoi, self.aoi_scale_ms)
        if self.observe_lag:
            obs = with_lag(obs, self.n_cameras, self.lag_ms, self.aoi_scale_ms)
        return obs
