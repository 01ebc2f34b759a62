"""An episode's numbers: the score of each scored decision (:class:`EpochScore`) and their
means (:class:`EpisodeResult`, :func:`episode_result`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from aoi3d.experiment.episode.plan import EpisodePlan, total_steps


@dataclass(frozen=True)
class EpochScore:
    """The quality of the novel view after one scored decision; ``*_dynamic*``: over the
    dynamic region (:func:`aoi3d.quality.dynamic_mask`; None where its mask is empty)."""

    decision_ms: int
    eval_ms: int
    n_selected: int
    aoi_used_ms: float
    psnr_db: float
    ssim: float
    lpips: float | None
    reward: float
    loss: float
    steps: int
    psnr_dynamic_db: float | None
    ssim_dynamic: float | None
    dynamic_fraction: float
    display_ms: float
    """When the render is shown: ``eval_ms`` plus its reconstruction's compute in scene time
    (:meth:`EpisodeConfig.compute_ms` of the steps it trained)."""
    psnr_display_db: float
    """The render scored against the truth at ``display_ms`` (what a viewer sees), likewise
    the other ``*_display`` scores."""
    ssim_display: float
    lpips_display: float | None
    reward_display: float
    psnr_dynamic_display_db: float | None


@dataclass(frozen=True)
class EpisodeResult:
    """An episode's numbers: per scored decision, and their means (the episode's point)."""

    key: str
    policy: str
    delay: str
    seed: int
    epochs: tuple[EpochScore, ...]
    n_selected: float
    """Mean number of cameras used per training decision of the scored span."""
    aoi_used_ms: float
    """Mean AoI (at the time it is used) of the frames used in the scored span; NaN: none."""
    mean_aoi_all_ms: float
    """Mean AoI over all cameras at those decisions (what the channel offers)."""
    drop_ratio: float
    psnr_db: float
    ssim: float
    lpips: float | None
    reward: float
    psnr_dynamic_db: float | None
    """Mean dynamic-region PSNR over the scored decisions whose mask is not empty; None: none."""
    ssim_dynamic: float | None
    """Mean dynamic-region SSIM, likewise."""
    dynamic_fraction: float
    """Mean pixel fraction of the dynamic mask over the scored decisions."""
    train_steps: int
    wall_s: float
    compute_ms: float
    """Mean scene ms charged for a scored decision's reconstruction (display − eval time)."""
    psnr_display_db: float
    """Mean PSNR against the truth at display time (``EpochScore.display_ms``)."""
    ssim_display: float
    lpips_display: float | None
    reward_display: float
    psnr_dynamic_display_db: float | None
    rendered_fraction: float | None = None
    """With the pool's twin (``pool_workers``): the share of the scored span's decisions the
    pool rendered (the epochs); None without a pool (every ``score_every``-th is)."""

    def to_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in vars(self).items() if k != "epochs"}
        out["epochs"] = [vars(e) for e in self.epochs]
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EpisodeResult:
        """The result :meth:`to_dict` wrote; a document lacking a field (one cached before
        the dynamic-region scores existed) raises TypeError — the sweep's cache takes it as
        a miss and recomputes it under the same key, so every result has every field."""
        data = dict(d)
        data["epochs"] = tuple(EpochScore(**e) for e in d["epochs"])
        return cls(**data)

    def relabel(self, policy: str, delay: str) -> EpisodeResult:
        """The same numbers under another policy's name (a shared, cached plan)."""
        return EpisodeResult(**{**vars(self), "policy": policy, "delay": delay})


def _mean_or_none(values: list[float | None]) -> float | None:
    """The mean of the values that are not None; None when there are none."""
    present = [v for v in values if v is not None]
    return float(np.mean(present)) if present else None


def _nanmean(values: list[float]) -> float:
    arr = np.asarray(values, dtype=np.float64)
    arr = arr[~np.isnan(arr)]
    return float(arr.mean()) if arr.size else math.nan


def episode_result(plan: EpisodePlan, epochs: Sequence[EpochScore], *, key: str = "",
                   wall_s: float = math.nan, train_steps: int | None = None,
                   rendered_fraction: float | None = None) -> EpisodeResult:
    """The episode's numbers from the scores of its scored decisions (``epochs``, in order):
    their means, and the selections of the plan's reported decisions. ``train_steps``: the
    steps taken, when not the plan's (:func:`total_steps`: the pool's twin counts its jobs');
    ``rendered_fraction``: the pool's, with one."""
    cfg = plan.config
    used = plan.reported
    aois = [a for d in used for a in d.aoi_ms]
    lpips_values = [e.lpips for e in epochs if e.lpips is not None]
    return EpisodeResult(
        key=key, policy=plan.policy, delay=cfg.delay, seed=plan.seed, epochs=tuple(epochs),
        n_selected=float(np.mean([len(d.cameras) for d in used])) if used else 0.0,
        aoi_used_ms=float(np.mean(aois)) if aois else math.nan,
        mean_aoi_all_ms=_nanmean([d.mean_aoi_all_ms for d in used]),
        drop_ratio=plan.drop_ratio,
        psnr_db=float(np.mean([e.psnr_db for e in epochs])),
        ssim=float(np.mean([e.ssim for e in epochs])),
        lpips=float(np.mean(lpips_values)) if len(lpips_values) == len(epochs) else None,
        reward=float(np.mean([e.reward for e in epochs])),
        psnr_dynamic_db=_mean_or_none([e.psnr_dynamic_db for e in epochs]),
        ssim_dynamic=_mean_or_none([e.ssim_dynamic for e in epochs]),
        dynamic_fraction=float(np.mean([e.dynamic_fraction for e in epochs])),
        train_steps=total_steps(plan) if train_steps is None else train_steps,
        wall_s=wall_s,
        compute_ms=float(np.mean([e.display_ms - e.eval_ms for e in epochs])),
        psnr_display_db=float(np.mean([e.psnr_display_db for e in epochs])),
        ssim_display=float(np.mean([e.ssim_display for e in epochs])),
        lpips_display=(float(np.mean([e.lpips_display for e in epochs]))
                       if all(e.lpips_display is not None for e in epochs) else None),
        reward_display=float(np.mean([e.reward_display for e in epochs])),
        psnr_dynamic_display_db=_mean_or_none([e.psnr_dynamic_display_db for e in epochs]),
        rendered_fraction=rendered_fraction,
    )
