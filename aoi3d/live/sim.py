"""The virtual-clock counterpart of a live sweep: the experiments' engine on the same scene,
channel, carry mode and training budget per rendered decision."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from aoi3d.experiment.config import get_preset
from aoi3d.experiment.episode.plan import check_budget_applies
from aoi3d.experiment.sweep import Job, ResultCache, run_jobs
from aoi3d.live.summary import METRICS
from aoi3d.policy import parse_policy
from aoi3d.stats import mean_ci95

__all__ = ["SimRefused", "budget", "simulate"]


class SimRefused(ValueError):
    """The virtual clock cannot run these policies with the pipeline's settings (a budget
    under the warm carry); the message says why. Nothing was run."""


def budget(carry: str, *, steps_per_decision: int, render_steps: int,
           cold_steps: int) -> dict[str, int]:
    """The episode's budget (``steps_per_epoch``, ``render_steps``) that matches a live
    trainer's carry: ``fresh`` trains ``render_steps`` at each rendered decision; ``stream``
    warm-starts with ``render_steps`` and starts cold with ``cold_steps`` (the episode's
    ``steps_per_epoch``); ``fork`` and ``warm`` train ``steps_per_decision`` in the
    background, ``fork`` ``render_steps`` more on each rendered decision."""
    if carry == "fresh":
        return {"steps_per_epoch": render_steps}
    if carry == "stream":
        return {"steps_per_epoch": cold_steps, "render_steps": render_steps}
    return {"steps_per_epoch": max(1, steps_per_decision),
            "render_steps": render_steps if carry == "fork" else 0}


def simulate(policies: Sequence[str], *, dataset: Path, delay: str, carry: str,
             steps_per_decision: int, render_steps: int, seeds: int, seed_offset: int,
             cache: Path, workers: int | None, cold_steps: int = 100, backend: str = "grid"
             ) -> dict[str, dict[str, Any]]:
    """The experiments' engine on the same scene, channel, carry, budget (:func:`budget`;
    ``cold_steps``: the trainer's ``AOI3D_TRAINER_COLD_STEPS``, for ``stream``) and field
    backend: per policy, ``{metric: {"mean", "ci95", "n"}}`` over ``seeds`` seeds (and
    ``_config``: the episode config run). :class:`SimRefused` when a policy's budget cannot
    run with that carry."""
    base = get_preset("quick").episode
    changes: dict[str, Any] = {"dataset": str(dataset), "delay": delay, "carry": carry,
                               "backend": backend}
    changes.update(budget(carry, steps_per_decision=steps_per_decision,
                          render_steps=render_steps, cold_steps=cold_steps))
    cfg = base.with_(**changes)
    for spec in policies:  # before any episode runs
        policy = parse_policy(spec)
        if policy.budget_steps is not None or getattr(policy, "chooses_budget", False):
            try:
                check_budget_applies(cfg)
            except ValueError as err:
                raise SimRefused(f"{spec}: {err}") from None
    jobs = [Job(p, delay, seed_offset + s) for s in range(seeds) for p in policies]
    outcome = run_jobs(cfg, jobs, cache=ResultCache(cache), workers=workers)
    sim: dict[str, dict[str, Any]] = {}
    for spec in policies:
        rs = [r for r in outcome.results if r.policy == spec]
        sim[spec] = {m: mean_ci95([getattr(r, m, None) for r in rs]).to_dict() for m in METRICS}
        sim[spec]["cameras_used"] = mean_ci95([r.n_selected for r in rs]).to_dict()
    sim["_config"] = cfg.to_dict()
    return sim
