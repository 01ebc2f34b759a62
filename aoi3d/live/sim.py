"""The virtual-clock counterpart of a live sweep: the experiments' engine on the same scene,
channel, carry mode and training budget per rendered decision — and, with :class:`PoolTwin`,
the live run's pool: as many workers, its time scale, and a job charged what the live
workers' own timings say (:func:`job_cost`, from the dispatcher's ``GET /status`` ``job_s``)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from aoi3d.experiment.config import COMPUTE_FIXED_MS, COMPUTE_STEP_MS, get_preset
from aoi3d.experiment.episode.plan import check_budget_applies
from aoi3d.experiment.sweep import Job, ResultCache, run_jobs
from aoi3d.live.summary import METRICS
from aoi3d.policy import parse_policy
from aoi3d.stats import mean_ci95

__all__ = ["MIN_JOBS", "PoolTwin", "SimRefused", "budget", "job_cost", "job_table", "simulate"]


class SimRefused(ValueError):
    """The virtual clock cannot run these policies with the pipeline's settings (a budget
    under the warm carry); the message says why. Nothing was run."""


@dataclass(frozen=True)
class PoolTwin:
    """The live run's pool as the virtual clock's twin runs it: ``workers``, the run's
    ``time_scale`` and a job's wall ms: ``job_ms``'s medians by step count and frames as the
    live workers timed them (:func:`job_table`), else ``fixed_ms`` + ``step_ms`` · steps."""

    workers: int
    time_scale: float
    fixed_ms: float
    step_ms: float
    job_ms: tuple[tuple[int, int, float], ...] = ()
    fresh_fraction: float = 1.0
    """The live dispatcher's: a free worker waits for the next decision rather than take one
    older than this fraction of the period."""

    def changes(self) -> dict[str, Any]:
        """The episode config's settings for it (every decision goes to the pool)."""
        return {"pool_workers": self.workers, "time_scale": self.time_scale,
                "pool_fresh_fraction": self.fresh_fraction,
                "compute_fixed_ms": self.fixed_ms, "compute_step_ms": self.step_ms,
                "job_ms": self.job_ms, "score_every": 1}


MIN_JOBS = 3
"""Jobs a (steps, frames) cell needs to count (a run's first jobs, cold, also build the model
and warm the process up: one of them alone says little)."""


def job_table(job_s: Mapping[str, Mapping[str, float]], backend: str, carry: str
              ) -> tuple[tuple[int, int, float], ...]:
    """(steps, frames, median wall ms) of each cell of ``backend`` and ``carry`` the live
    workers timed at least :data:`MIN_JOBS` times (the dispatcher's ``job_s``,
    ``backend/carry/steps/frames``; an older key without frames: -1, any)."""
    return tuple(sorted((s, v, ms) for s, v, ms, n in _points(job_s, backend, carry)
                        if n >= MIN_JOBS))


def _points(job_s: Mapping[str, Mapping[str, float]], backend: str, carry: str
            ) -> list[tuple[int, int, float, float]]:
    """(steps, frames, median ms, jobs) of each timed cell of ``backend`` and ``carry``."""
    points = []
    for key, stat in job_s.items():
        parts = key.split("/")
        if len(parts) == 3:
            parts.append("-1")
        if len(parts) != 4 or parts[:2] != [backend, carry] or not parts[2].isdigit() \
                or not parts[3].lstrip("-").isdigit():
            continue
        if stat.get("n", 0) > 0 and math.isfinite(stat.get("median_s", math.nan)):
            points.append((int(parts[2]), int(parts[3]), 1000.0 * float(stat["median_s"]),
                           float(stat["n"])))
    return points


def job_cost(job_s: Mapping[str, Mapping[str, float]], backend: str, carry: str
             ) -> tuple[float, float] | None:
    """(fixed ms, ms per step) of a job of ``backend`` and ``carry`` from the live workers'
    own timings (the dispatcher's ``job_s``): the line over the steps through the medians of
    the cells timed at least :data:`MIN_JOBS` times, least squares weighted by the jobs (a
    stream run has two step counts: its warm and its cold starts); with one step count, the
    default cost model (:data:`~aoi3d.experiment.config.COMPUTE_FIXED_MS`,
    ``COMPUTE_STEP_MS``) scaled to it. Medians, since a worker's first job also builds its
    model. None: no job of that kind was timed. (The twin charges a timed step count its own
    medians, :func:`job_table`: this line is for the others, a budgeted policy's.)"""
    points = [(st, ms, n) for st, _, ms, n in _points(job_s, backend, carry)]
    if not points:
        return None
    enough = [p for p in points if p[2] >= MIN_JOBS] or [max(points, key=lambda p: p[2])]
    w = sum(n for _, _, n in enough)
    sx = sum(n * s for s, _, n in enough) / w
    sy = sum(n * ms for _, ms, n in enough) / w
    if len({s for s, _, _ in enough}) == 1:
        k = sy / (COMPUTE_FIXED_MS + COMPUTE_STEP_MS * sx)
        return COMPUTE_FIXED_MS * k, COMPUTE_STEP_MS * k
    sxx = sum(n * (s - sx) ** 2 for s, _, n in enough)
    sxy = sum(n * (s - sx) * (ms - sy) for s, ms, n in enough)
    slope = max(0.0, sxy / sxx)
    if sy - slope * sx < 0:  # steps dearer as there are more (a cold start's): through 0
        return 0.0, (sum(n * s * ms for s, ms, n in enough)
                     / sum(n * s * s for s, _, n in enough))
    return sy - slope * sx, slope


def budget(carry: str, *, steps_per_decision: int, render_steps: int,
           cold_steps: int) -> dict[str, int]:
    """The episode's budget (``steps_per_epoch``, ``render_steps``) that matches a live
    dispatcher's carry: ``fresh`` trains ``render_steps`` at each rendered decision; ``stream``
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
             cache: Path, processes: int | None, cold_steps: int = 100, backend: str = "grid",
             pool: PoolTwin | None = None, lpips: bool = True) -> dict[str, dict[str, Any]]:
    """The experiments' engine on the same scene, channel, carry, budget (:func:`budget`;
    ``cold_steps``: the dispatcher's ``AOI3D_DISPATCHER_COLD_STEPS``, for ``stream``) and field
    backend, through the twin of the live pool when ``pool`` says it (else every fifth
    decision rendered, no queue): per policy, ``{metric: {"mean", "ci95", "n"}}`` over
    ``seeds`` seeds, ``rendered_fraction`` with a pool (and ``_config``: the episode config
    run). :class:`SimRefused` when a policy's budget cannot run with that carry. ``processes``:
    the sweep's processes."""
    base = get_preset("quick").episode
    changes: dict[str, Any] = {"dataset": str(dataset), "delay": delay, "carry": carry,
                               "backend": backend}
    changes.update(budget(carry, steps_per_decision=steps_per_decision,
                          render_steps=render_steps, cold_steps=cold_steps))
    if pool is not None:
        changes.update(pool.changes())
    if not lpips:
        changes["lpips"] = False
    try:
        cfg = base.with_(**changes)
    except ValueError as err:
        raise SimRefused(str(err)) from None
    for spec in policies:  # before any episode runs
        policy = parse_policy(spec)
        if policy.budget_steps is not None or getattr(policy, "chooses_budget", False):
            try:
                check_budget_applies(cfg)
            except ValueError as err:
                raise SimRefused(f"{spec}: {err}") from None
    jobs = [Job(p, delay, seed_offset + s) for s in range(seeds) for p in policies]
    outcome = run_jobs(cfg, jobs, cache=ResultCache(cache), processes=processes)
    sim: dict[str, dict[str, Any]] = {}
    for spec in policies:
        rs = [r for r in outcome.results if r.policy == spec]
        sim[spec] = {m: mean_ci95([getattr(r, m, None) for r in rs]).to_dict() for m in METRICS}
        sim[spec]["cameras_used"] = mean_ci95([r.n_selected for r in rs]).to_dict()
        if pool is not None:
            sim[spec]["rendered_fraction"] = mean_ci95(
                [r.rendered_fraction for r in rs]).to_dict()
            sim[spec]["display_lag_ms"] = mean_ci95([r.compute_ms for r in rs]).to_dict()
    sim["_config"] = cfg.to_dict()
    return sim
