"""Scoring policies — a trained agent's deterministic one among them — on held-out seeds."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from aoi3d.experiment import EpisodeConfig, mean_ci95
from aoi3d.metric import LPIPS, PSNR, REWARD, SSIM
from aoi3d.policy import Policy, parse_policy
from aoi3d.rl.env import FrameSelectionEnv
from aoi3d.rl.runner import EpisodeRunner
from aoi3d.scene import SceneDataset, open_dataset

__all__ = ["EVAL_METRICS", "EVAL_SCORES", "EvalOutcome", "evaluate"]

EVAL_SCORES = tuple(m.short for m in (REWARD, PSNR, SSIM, LPIPS))
"""``reward, psnr, ssim, lpips``: the scores of a PPO episode, under the names the env reports
them (:attr:`aoi3d.metric.Metric.short`), the reward first."""
EVAL_METRICS = (*EVAL_SCORES, "n_selected", "aoi_used_ms")


@dataclass
class EvalOutcome:
    """Per-episode rows and per-policy summaries (mean and 95% half-width per metric; for
    every policy after the first, the paired difference of its reward to the first's)."""

    rows: list[dict[str, Any]]
    summary: list[dict[str, Any]]
    seeds: list[int]
    wall_s: float


def evaluate(
    policies: Sequence[Policy | str],
    episode: EpisodeConfig,
    seeds: Sequence[int],
    *,
    aoi_scale_ms: float = 300.0,
    dataset: SceneDataset | None = None,
    processes: int | None = None,
    threads: int = 1,
    cache: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> EvalOutcome:
    """Score ``policies`` (a ``ppo:`` policy acts deterministically) on the one-decision
    episodes of ``seeds``: each policy sees the same AoI vector and its frames train the same
    fresh model. Policies that wait (``wait:<ms>``) are refused: the environment decides at
    the epoch."""
    started = time.perf_counter()
    pols = [parse_policy(p) for p in policies]
    if not pols:
        raise ValueError("no policy to evaluate")
    ds = dataset if dataset is not None else open_dataset(episode.dataset)
    env = FrameSelectionEnv(episode, ds, aoi_scale_ms=aoi_scale_ms)
    for p in pols:
        env.check_policy(p)  # fits N, decides at the epoch
    items: list[tuple[int, np.ndarray]] = []
    labels: list[str] = []
    for seed in seeds:
        env.reset(seed=int(seed))
        for p in pols:
            p.reset()
            items.append((int(seed), env.policy_action(p).astype(np.int8)))
            labels.append(p.spec)
    rows: list[dict[str, Any]] = [{} for _ in items]
    done = 0
    with EpisodeRunner(env.config, aoi_scale_ms=aoi_scale_ms, cache=cache, processes=processes,
                 threads=threads) as pool:
        for i, outcome in pool.run(items):
            rows[i] = {"policy": labels[i], **outcome}
            done += 1
            if progress is not None:
                progress(done, len(items))
    summary = []
    first = pols[0].spec
    by_seed = {(r["policy"], r["seed"]): r for r in rows}
    for p in pols:
        mine = [r for r in rows if r["policy"] == p.spec]
        row: dict[str, Any] = {"policy": p.spec, "n": len(mine)}
        for metric in EVAL_METRICS:
            mean, half, _ = mean_ci95(r[metric] for r in mine)
            row[metric] = mean
            row[f"{metric}_ci95"] = half
        if p.spec != first:
            diff = [by_seed[(first, r["seed"])]["reward"] - r["reward"] for r in mine]
            mean, half, _ = mean_ci95(diff)
            row["first_minus_this_reward"] = mean
            row["first_minus_this_reward_ci95"] = half
        summary.append(row)
    return EvalOutcome(rows=rows, summary=summary, seeds=[int(s) for s in seeds],
                       wall_s=time.perf_counter() - started)
