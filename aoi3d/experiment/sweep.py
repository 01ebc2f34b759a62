"""Sweeps: many (policy, delay, seed) episodes, cached, run on local cores or a Ray cluster.

A sweep plans every job first (:func:`aoi3d.experiment.episode.plan_episode`, cheap), keys
it (:func:`plan_key`) and looks the key up in the :class:`ResultCache`; only missing keys are
computed, each once even when several jobs share it (two thresholds Γ that select the same
frames). Results are written to the cache as they complete, by this process alone, so an
interrupted sweep resumes where it stopped and a re-run computes only what is missing.

Execution: ``processes=1`` runs in this process; more run in a process pool (``spawn``, each
process with ``threads_per_process`` torch threads, 1 by default: episodes are small and the
pool is the parallelism); ``ray_address`` runs every episode as a Ray task instead
(``pip install .[cluster]``; the dataset must be readable at the same path on every node).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from aoi3d.atomic import write_atomic
from aoi3d.experiment.baselines import baseline_label, parse_trainer
from aoi3d.experiment.config import EpisodeConfig
from aoi3d.experiment.episode import (
    EpisodePlan,
    EpisodeResult,
    plan_episode,
    plan_key,
    set_torch_threads,
)
from aoi3d.experiment.executors import DATASETS, run_pool, run_ray, work
from aoi3d.experiment.oracle import OracleEpisode, OracleSpec, parse_oracle, search_oracle
from aoi3d.lpips import weights_path
from aoi3d.metric import AT_DECISION, AT_DISPLAY
from aoi3d.policy import parse_policy
from aoi3d.scene import SceneDataset, open_dataset
from aoi3d.stats import mean_ci95

__all__ = [
    "METRICS",
    "Job",
    "OracleOutcome",
    "PlansOutcome",
    "ResultCache",
    "SweepOutcome",
    "aggregate",
    "default_processes",
    "lpips_available",
    "run_jobs",
    "run_oracle",
    "run_plans",
]

METRICS = (*AT_DECISION, "dynamic_fraction", "n_selected", "aoi_used_ms", "mean_aoi_all_ms",
           *AT_DISPLAY, "compute_ms")
"""The per-episode numbers :func:`aggregate` summarises (mean and 95% confidence interval),
in the order of the summaries' columns: the scores at the decision's time
(:data:`aoi3d.metric.AT_DECISION`; ``*_dynamic*``: over the dynamic region, see
:mod:`aoi3d.quality`), what the episode selected, the scores at display time (the decision's
time plus its compute, ``compute_ms``)."""

Progress = Callable[[int, int], None]
"""``progress(done, total)`` in episodes to compute (cache hits are not counted)."""


@dataclass(frozen=True)
class Job:
    """One episode to run: a policy spec, a delay spec, a seed, and optionally a trainer
    option (``trainer``: a baseline of :mod:`aoi3d.experiment.baselines`, e.g. ``wsum:60``,
    whose field settings apply to this episode; its result is labelled
    ``<trainer>[@<policy>]``)."""

    policy: str
    delay: str
    seed: int
    trainer: str | None = None


class ResultCache:
    """Episode results on disk: ``<root>/<key[:2]>/<key>.json`` and the last render ``.png``.

    Written atomically (temporary file, then rename; the JSON last), so a result is either
    complete or absent.
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)

    def _path(self, key: str, suffix: str) -> Path:
        if len(key) < 8 or not all(c in "0123456789abcdef" for c in key):
            raise ValueError(f"bad cache key {key!r}")
        return self.root / key[:2] / f"{key}{suffix}"

    def get(self, key: str) -> EpisodeResult | None:
        """The cached result of ``key``, or None (a corrupt entry, or one written before a
        field of :class:`EpisodeResult` existed, counts as missing)."""
        path = self._path(key, ".json")
        try:
            return EpisodeResult.from_dict(json.loads(path.read_text()))
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def render_png(self, key: str) -> bytes | None:
        """The PNG of the last scored render of ``key``'s episode, or None."""
        try:
            data = self._path(key, ".png").read_bytes()
        except OSError:
            return None
        return data or None

    def put(self, result: EpisodeResult, png: bytes = b"") -> None:
        """Store ``result`` (under ``result.key``) and its last render."""
        path = self._path(result.key, ".json")
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path.with_suffix(".png"), png)
        write_atomic(path, json.dumps(result.to_dict()).encode())

    def __contains__(self, key: str) -> bool:
        return self._path(key, ".json").is_file()


@dataclass(frozen=True)
class PlansOutcome:
    """Results of planned episodes, in the order of the plans, with their cache keys."""

    results: list[EpisodeResult]
    keys: list[str]
    computed: int
    cached: int
    wall_s: float


@dataclass(frozen=True)
class SweepOutcome:
    """Results in job order, with what was computed and what came from the cache."""

    results: list[EpisodeResult]
    plans: list[EpisodePlan]
    keys: list[str]
    computed: int
    cached: int
    wall_s: float


def default_processes() -> int:
    """All local cores (``os.process_cpu_count`` where known)."""
    count = getattr(os, "process_cpu_count", os.cpu_count)()
    return max(1, count or 1)


def lpips_available(cfg: EpisodeConfig) -> bool:
    """Whether episodes of ``cfg`` will compute LPIPS (asked for, and weights cached)."""
    return cfg.lpips and weights_path("alex").is_file()


# --- the sweep -------------------------------------------------------------------------------
def run_jobs(
    cfg: EpisodeConfig,
    jobs: Sequence[Job],
    *,
    cache: ResultCache | None = None,
    processes: int | None = None,
    threads_per_process: int = 1,
    ray_address: str | None = None,
    progress: Progress | None = None,
    dataset: SceneDataset | None = None,
) -> SweepOutcome:
    """Run ``jobs`` (each ``cfg`` with the job's delay, and its trainer option's field
    settings) and return their results in order.

    ``processes``: processes (None: :func:`default_processes`; 1: this process).
    ``ray_address``: run on Ray (``auto``, ``ray://host:port``, or ``local`` to start a local
    instance) instead of the process pool. ``cache``: where results are kept between runs.
    """
    started = time.perf_counter()
    ds = dataset if dataset is not None else open_dataset(cfg.dataset)
    stepwise = [j for j in jobs if j.trainer is None and parse_policy(j.policy).wants_quality]
    if stepwise:
        return _run_jobs_stepwise(cfg, jobs, stepwise, ds, started, cache=cache,
                                  processes=processes, threads_per_process=threads_per_process,
                                  ray_address=ray_address, progress=progress)
    plans: list[EpisodePlan] = []
    labels: list[str] = []
    for job in jobs:
        job_cfg = cfg.with_(delay=job.delay)
        option = None
        if job.trainer is not None:
            option = parse_trainer(job.trainer)
            job_cfg = job_cfg.with_(field={**cfg.field, **option.field_overrides()})
        plan = plan_episode(job_cfg, ds, job.policy, job.seed)
        plans.append(plan)
        labels.append(plan.policy if option is None else baseline_label(option, plan.policy))
    outcome = run_plans(plans, cache=cache, processes=processes,
                        threads_per_process=threads_per_process, ray_address=ray_address,
                        progress=progress, dataset=ds)
    results = [r.relabel(label, p.config.delay)
               for r, label, p in zip(outcome.results, labels, plans, strict=True)]
    return SweepOutcome(results=results, plans=plans, keys=outcome.keys,
                        computed=outcome.computed, cached=outcome.cached,
                        wall_s=time.perf_counter() - started)


def _run_jobs_stepwise(cfg: EpisodeConfig, jobs: Sequence[Job], stepwise: Sequence[Job],
                       ds: SceneDataset, started: float, **run: Any) -> SweepOutcome:
    """:func:`run_jobs` with policies rewarded by quality (``adaptive:bandit``): those run
    step by step (:func:`aoi3d.experiment.adaptive.run_stepwise`, every seed of a policy and
    delay together, each scored epoch one cached batch), after the others."""
    from aoi3d.experiment.adaptive import run_stepwise

    rest = [j for j in jobs if j not in stepwise]
    first = run_jobs(cfg, rest, dataset=ds, **run) if rest else None
    counts = {"computed": first.computed if first else 0,
              "cached": first.cached if first else 0}

    def evaluate(plans: Sequence[EpisodePlan]) -> list[EpisodeResult]:
        out = run_plans(plans, dataset=ds, **run)
        counts["computed"] += out.computed
        counts["cached"] += out.cached
        return out.results

    done: dict[tuple[str, str, int], tuple[EpisodeResult, EpisodePlan]] = {}
    groups: dict[tuple[str, str], list[int]] = {}
    for j in stepwise:
        groups.setdefault((j.policy, j.delay), []).append(j.seed)
    for (policy, delay), seeds in groups.items():
        for ep in run_stepwise(cfg.with_(delay=delay), ds, policy, list(dict.fromkeys(seeds)),
                               evaluate):
            done[(policy, delay, ep.plan.seed)] = (ep.result.relabel(ep.plan.policy, delay),
                                                   ep.plan)
    results, plans, keys = [], [], []
    others = iter(zip(first.results, first.plans, first.keys, strict=True)) if first else None
    for j in jobs:
        if j in stepwise:
            result, plan = done[(j.policy, j.delay, j.seed)]
            results.append(result)
            plans.append(plan)
            keys.append(result.key)
        else:
            assert others is not None
            result, plan, key = next(others)
            results.append(result)
            plans.append(plan)
            keys.append(key)
    return SweepOutcome(results=results, plans=plans, keys=keys, computed=counts["computed"],
                        cached=counts["cached"], wall_s=time.perf_counter() - started)


def run_plans(
    plans: Sequence[EpisodePlan],
    *,
    cache: ResultCache | None = None,
    processes: int | None = None,
    threads_per_process: int = 1,
    ray_address: str | None = None,
    progress: Progress | None = None,
    dataset: SceneDataset | None = None,
) -> PlansOutcome:
    """Compute planned episodes (of one dataset) and return their results in order, each
    key once: from ``cache`` where it has them, else in this process, a process pool or on
    Ray (see :func:`run_jobs`). The results carry their plans' own policy names."""
    started = time.perf_counter()
    if threads_per_process < 1:
        raise ValueError(f"threads_per_process must be >= 1, got {threads_per_process}")
    if not plans:
        return PlansOutcome([], [], 0, 0, 0.0)
    root = plans[0].config.dataset
    if any(p.config.dataset != root for p in plans):
        raise ValueError("run_plans takes the plans of one dataset")
    ds = dataset if dataset is not None else open_dataset(root)
    lpips = lpips_available(plans[0].config)
    if any(p.config.lpips != plans[0].config.lpips for p in plans):
        raise ValueError("run_plans takes plans that all compute LPIPS or all do not")
    keys = [plan_key(plan, ds, lpips=lpips) for plan in plans]

    found: dict[str, EpisodeResult] = {}
    todo: dict[str, EpisodePlan] = {}
    for key, plan in zip(keys, plans, strict=True):
        if key in found or key in todo:
            continue
        hit = cache.get(key) if cache is not None else None
        if hit is not None:
            found[key] = hit
        else:
            todo[key] = plan
    cached = len(found)
    # Seed-major order: an interrupted sweep has covered every point with its first seeds.
    position = {k: i for i, k in enumerate(todo)}
    order = sorted(todo, key=lambda k: (todo[k].seed, position[k]))

    def done(result: EpisodeResult, png: bytes) -> None:
        found[result.key] = result
        if cache is not None:
            cache.put(result, png)
        if progress is not None:
            progress(len(found) - cached, len(order))

    if progress is not None:
        progress(0, len(order))
    n_processes = default_processes() if processes is None else processes
    if n_processes < 1:
        raise ValueError(f"processes must be >= 1, got {processes}")
    items = [(todo[k].to_dict(), k) for k in order]
    if items and ray_address is not None:
        run_ray(items, lpips, threads_per_process, ray_address, done)
    elif items and (n_processes == 1 or len(items) == 1):
        previous = torch.get_num_threads()
        set_torch_threads(threads_per_process)
        DATASETS.setdefault(root, ds)
        try:
            for doc, key in items:
                result, png = work(doc, key, lpips)
                done(EpisodeResult.from_dict(result), png)
        finally:
            set_torch_threads(previous)
    elif items:
        run_pool(items, lpips, min(n_processes, len(items)), threads_per_process, done)

    results = [found[k].relabel(p.policy, p.config.delay)
               for k, p in zip(keys, plans, strict=True)]
    return PlansOutcome(results=results, keys=keys, computed=len(order), cached=cached,
                        wall_s=time.perf_counter() - started)


@dataclass(frozen=True)
class OracleOutcome:
    """The oracle bound's episodes (one per seed, in seed order) and what its search cost:
    ``reconstructions`` tried (each a one-decision episode), of which ``computed`` were run
    now and ``cached`` came from the cache (for the ``budgets`` search: cell episodes, each a
    reconstruction at every scored decision); ``compute_s``: the compute time of all of them
    (the sum of their episodes' ``wall_s``, whenever they were run); ``wall_s``: this call."""

    spec: str
    episodes: list[OracleEpisode]
    computed: int
    cached: int
    wall_s: float

    @property
    def results(self) -> list[EpisodeResult]:
        return [e.result for e in self.episodes]

    @property
    def reconstructions(self) -> int:
        return sum(e.reconstructions for e in self.episodes)

    @property
    def compute_s(self) -> float:
        return float(sum(e.result.wall_s for e in self.episodes))

    def cost(self) -> dict[str, Any]:
        """What the search cost, for ``results.json``."""
        per = [d.candidates for e in self.episodes for d in e.decisions]
        return {
            "decisions": len(per), "reconstructions": self.reconstructions,
            "reconstructions_per_decision": {
                "mean": float(np.mean(per)) if per else math.nan,
                "min": min(per, default=0), "max": max(per, default=0)},
            "computed": self.computed, "cached": self.cached,
            "counted": ("cell episodes" if self.spec.split(":")[1] == "budgets"
                        else "reconstructions"),
            "compute_s": self.compute_s,
            "compute_s_per_reconstruction": (self.compute_s / self.reconstructions
                                             if self.reconstructions else math.nan),
            "wall_s": self.wall_s,
            "searches": [d.to_dict() for e in self.episodes for d in e.decisions],
        }


def run_oracle(
    cfg: EpisodeConfig,
    oracle: OracleSpec | str,
    seeds: Sequence[int],
    *,
    cache: ResultCache | None = None,
    processes: int | None = None,
    threads_per_process: int = 1,
    ray_address: str | None = None,
    progress: Progress | None = None,
    on_round: Callable[[str], None] | None = None,
    dataset: SceneDataset | None = None,
) -> OracleOutcome:
    """The oracle bound (:mod:`aoi3d.experiment.oracle`) for ``seeds`` of ``cfg``: each
    search round's candidates run as one batch by :func:`run_plans` (cached, on local cores
    or Ray, as any sweep); ``on_round(text)`` hears what each round runs."""
    started = time.perf_counter()
    spec = parse_oracle(oracle) if isinstance(oracle, str) else oracle
    ds = dataset if dataset is not None else open_dataset(cfg.dataset)
    counts = {"computed": 0, "cached": 0}

    def evaluate(plans: Sequence[EpisodePlan]) -> list[EpisodeResult]:
        out = run_plans(plans, cache=cache, processes=processes,
                        threads_per_process=threads_per_process, ray_address=ray_address,
                        progress=progress, dataset=ds)
        counts["computed"] += out.computed
        counts["cached"] += out.cached
        return out.results

    episodes = search_oracle(cfg, ds, spec, seeds, evaluate, lpips=lpips_available(cfg),
                             progress=on_round)
    return OracleOutcome(spec=spec.spec, episodes=episodes, computed=counts["computed"],
                         cached=counts["cached"], wall_s=time.perf_counter() - started)


# --- statistics ------------------------------------------------------------------------------
def aggregate(results: Sequence[EpisodeResult],
              by: Sequence[str] = ("policy", "delay")) -> list[dict[str, Any]]:
    """One row per group of ``by``: ``n`` episodes, ``<metric>`` mean and ``<metric>_ci95``
    half-width for each of :data:`METRICS`, in first-seen order of the groups."""
    groups: dict[tuple[Any, ...], list[EpisodeResult]] = {}
    for r in results:
        groups.setdefault(tuple(getattr(r, b) for b in by), []).append(r)
    rows = []
    for group, members in groups.items():
        row: dict[str, Any] = dict(zip(by, group, strict=True))
        row["n"] = len(members)
        for metric in METRICS:
            mean, half, _ = mean_ci95(getattr(r, metric) for r in members)
            row[metric] = mean
            row[f"{metric}_ci95"] = half
        rows.append(row)
    return rows
