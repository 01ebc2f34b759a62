"""Episodes decided step by step on the virtual clock: for policies rewarded by quality.

:func:`aoi3d.experiment.plan_episode` plans a whole episode before training, which a policy
that learns from the quality of its renders (``adaptive:bandit``, :mod:`aoi3d.policy.adaptive`)
does not allow: its decision at t depends on the scores of its earlier decisions.
:func:`run_stepwise` runs such episodes — and any other policy, with the same numbers as the
planned episode — decision by decision: at each epoch the policy is told the frames delivered
since its last decision and decides (:func:`aoi3d.policy.decide.decide`, the links'
``delivery_feed``); at each scored decision the one-decision plan that trains on its selection
is run (the oracle's candidate plan, :mod:`aoi3d.experiment.oracle`: the same cache key for
the same selection), and its scores are handed to the policy (``observe_quality``) before
its next decision. Every seed advances in lockstep, so each scored epoch is one batch for
``evaluate`` (the sweep's cached ``run_plans``: local cores or Ray).

It needs the ``fresh`` carry, where a scored decision's render depends on its own frames and
the seed alone — then the stepwise episode's numbers equal the planned episode's, and a
bandit, the fixed rules and the oracle bound share every reconstruction through the cache.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

from aoi3d.experiment.config import EpisodeConfig
from aoi3d.experiment.episode import (
    EpisodeLinks,
    EpisodePlan,
    EpisodeResult,
    EpochScore,
    PlannedDecision,
    display_lag,
    episode_links,
    episode_result,
    planned_decision,
)
from aoi3d.policy import Policy, decide, parse_policy
from aoi3d.policy.adaptive import QUALITY_METRICS
from aoi3d.scene import SceneDataset

__all__ = ["StepwiseEpisode", "run_stepwise"]

Evaluate = Callable[[Sequence[EpisodePlan]], Sequence[EpisodeResult]]


@dataclass(frozen=True)
class StepwiseEpisode:
    """One seed's stepwise episode: its ``result`` (the policy's label), its ``plan`` (every
    decision as taken) and the Γ in force at each decision (None: the policy has no Γ)."""

    result: EpisodeResult
    plan: EpisodePlan
    gamma_ms: tuple[float | None, ...]

    def to_dict(self) -> dict[str, Any]:
        return {"seed": self.plan.seed, "policy": self.plan.policy,
                "decision_ms": [d.decision_ms for d in self.plan.decisions],
                "gamma_ms": list(self.gamma_ms)}


@dataclass
class _Run:
    seed: int
    policy: Policy
    links: EpisodeLinks
    feed: Callable[[int], list[tuple[int, float, float]]]
    base: EpisodePlan
    decisions: list[PlannedDecision]
    gammas: list[float | None]
    epochs: list[EpochScore]
    wall_s: float = 0.0


def _one_decision(base: EpisodePlan, decision: PlannedDecision) -> EpisodePlan:
    return replace(base, decisions=(replace(decision, train=True, scored=True),))


def run_stepwise(cfg: EpisodeConfig, dataset: SceneDataset, policy: str | Policy,
                 seeds: Sequence[int], evaluate: Evaluate, *,
                 label: str | None = None) -> list[StepwiseEpisode]:
    """The policy's episodes for ``seeds``, decided step by step (see the module).

    ``evaluate`` runs one-decision plans (one call per scored epoch, every seed together);
    each scored render's scores go to ``observe_quality``; ``label``: the results' policy name
    (default: the policy's spec)."""
    if cfg.carry != "fresh":
        raise ValueError(f"a stepwise episode scores each decision on its own, which needs "
                         f"carry 'fresh', not {cfg.carry!r}")
    spec = parse_policy(policy).spec
    runs: list[_Run] = []
    for seed in seeds:
        pol = parse_policy(spec)  # a fresh policy (and state) per seed
        pol.reset()
        links = episode_links(cfg, dataset, seed, wait_ms=pol.wait_ms)
        base = EpisodePlan(config=cfg, policy=label or spec, seed=links.seed,
                           wait_ms=pol.wait_ms, scene_offset_ms=links.scene_offset_ms,
                           phase_ms=links.phase_ms, decisions=(), drop_ratio=links.drop_ratio)
        runs.append(_Run(seed, pol, links, links.delivery_feed(), base, [], [], []))
    lag = display_lag(cfg)
    times = cfg.decision_times_ms()
    first_scored = next(i for i, t in enumerate(times) if t >= cfg.warmup_ms)
    for i, t in enumerate(times):
        scored = i >= first_scored and (i - first_scored) % cfg.score_every == 0
        plans = []
        for r in runs:
            sel = decide(r.policy, t, r.links.newest_ms, deliveries=r.feed, lag=lag)
            d = planned_decision(sel, r.links.camera_ids, train=scored, scored=scored)
            r.decisions.append(d)
            r.gammas.append(r.policy.gamma_ms)
            if scored:
                plans.append(_one_decision(r.base, d))
        if not plans:
            continue
        results = list(evaluate(plans))
        if len(results) != len(plans):
            raise RuntimeError(f"evaluate returned {len(results)} results for {len(plans)} "
                               "plans")
        for r, res in zip(runs, results, strict=True):
            epoch = res.epochs[0]
            r.epochs.append(epoch)
            r.wall_s += res.wall_s
            r.policy.observe_quality(float(epoch.eval_ms),
                                     {m: getattr(epoch, m) for m in QUALITY_METRICS})
    out = []
    for r in runs:
        plan = replace(r.base, decisions=tuple(r.decisions))
        result = episode_result(plan, r.epochs, key=f"stepwise:{plan.policy}:{r.seed}",
                                wall_s=r.wall_s)
        out.append(StepwiseEpisode(result=result, plan=plan, gamma_ms=tuple(r.gammas)))
    return out
