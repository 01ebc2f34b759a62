"""Stage 1 of an episode: its plan (:func:`plan_episode`) — every decision of the policy on
the episode's links — and the cache key of the plan's numbers (:func:`plan_key`)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from aoi3d.experiment.config import EpisodeConfig
from aoi3d.experiment.episode.links import EpisodeLinks, episode_links
from aoi3d.field import field_config
from aoi3d.field.carry import BACKGROUND_MODES, FINETUNE_MODES
from aoi3d.policy import DisplayLag, Policy, Selection, decide, parse_policy
from aoi3d.scene import SceneDataset

ENGINE_VERSION = 1
"""Bump when the numbers of an unchanged plan would change (invalidates cached results)."""


@dataclass(frozen=True)
class PlannedDecision:
    """One decision: taken at ``decision_ms``, selecting at (and rendered for) ``eval_ms``.

    ``cameras``: the selected camera ids; ``gen_ms``: the generation slot U_n(eval_ms) of each
    one's newest delivered frame; ``aoi_ms``: their AoI at ``eval_ms``. ``n_known``: cameras
    with some delivered frame. ``train``: the model trains on this selection; ``scored``: the
    novel view is rendered and scored after it. ``budget_steps``: the decision's budget
    (:mod:`aoi3d.policy.budget`; None: the config's, :func:`render_budget`).
    """

    decision_ms: int
    eval_ms: int
    cameras: tuple[int, ...]
    gen_ms: tuple[int, ...]
    aoi_ms: tuple[float, ...]
    n_known: int
    mean_aoi_all_ms: float
    train: bool
    scored: bool
    budget_steps: int | None = None

    def to_dict(self) -> dict[str, Any]:
        doc: dict[str, Any] = {
            "decision_ms": self.decision_ms, "eval_ms": self.eval_ms,
            "cameras": list(self.cameras), "gen_ms": list(self.gen_ms),
            "aoi_ms": list(self.aoi_ms), "n_known": self.n_known,
            "mean_aoi_all_ms": self.mean_aoi_all_ms, "train": self.train, "scored": self.scored,
        }
        if self.budget_steps is not None:  # absent: the config's (older plans read the same)
            doc["budget_steps"] = self.budget_steps
        return doc

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PlannedDecision:
        return cls(
            decision_ms=int(d["decision_ms"]), eval_ms=int(d["eval_ms"]),
            cameras=tuple(int(c) for c in d["cameras"]), gen_ms=tuple(int(g) for g in d["gen_ms"]),
            aoi_ms=tuple(float(a) for a in d["aoi_ms"]), n_known=int(d["n_known"]),
            mean_aoi_all_ms=float(d["mean_aoi_all_ms"]), train=bool(d["train"]),
            scored=bool(d["scored"]),
            budget_steps=None if d.get("budget_steps") is None else int(d["budget_steps"]),
        )


@dataclass(frozen=True)
class EpisodePlan:
    """What an episode will train on and when it is scored (see :func:`plan_episode`)."""

    config: EpisodeConfig
    policy: str
    seed: int
    wait_ms: int
    scene_offset_ms: int
    phase_ms: tuple[int, ...]
    decisions: tuple[PlannedDecision, ...]
    drop_ratio: float

    @property
    def reported(self) -> list[PlannedDecision]:
        """Decisions of the scored span that train the model (their frames are 'used')."""
        return [d for d in self.decisions if d.train and d.decision_ms >= self.config.warmup_ms]

    def to_dict(self) -> dict[str, Any]:
        return {
            "config": self.config.to_dict(), "policy": self.policy, "seed": self.seed,
            "wait_ms": self.wait_ms, "scene_offset_ms": self.scene_offset_ms,
            "phase_ms": list(self.phase_ms), "drop_ratio": self.drop_ratio,
            "decisions": [d.to_dict() for d in self.decisions],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EpisodePlan:
        return cls(
            config=EpisodeConfig.from_dict(d["config"]), policy=str(d["policy"]),
            seed=int(d["seed"]), wait_ms=int(d["wait_ms"]),
            scene_offset_ms=int(d["scene_offset_ms"]),
            phase_ms=tuple(int(p) for p in d["phase_ms"]), drop_ratio=float(d["drop_ratio"]),
            decisions=tuple(PlannedDecision.from_dict(x) for x in d["decisions"]),
        )


def planned_decision(sel: Selection, camera_ids: Sequence[int], *, train: bool,
                     scored: bool) -> PlannedDecision:
    """The plan's record of one decision step's :class:`~aoi3d.policy.decide.Selection`."""
    return PlannedDecision(
        decision_ms=int(sel.decision_ms), eval_ms=int(sel.eval_ms),
        cameras=sel.cameras(camera_ids),
        gen_ms=tuple(int(g) for g in sel.gen_ms),
        aoi_ms=tuple(float(a) for a in sel.selected_aoi_ms),
        n_known=int(sel.known.sum()), mean_aoi_all_ms=sel.mean_aoi_all_ms,
        train=train, scored=scored, budget_steps=sel.budget_steps,
    )


def plan_episode(
    cfg: EpisodeConfig, dataset: SceneDataset, policy: Policy | str, seed: int, *,
    links: EpisodeLinks | None = None,
) -> EpisodePlan:
    """Simulate the links for ``seed`` and take the policy's decision at every epoch
    (:func:`aoi3d.policy.decide.decide`; a waiting policy decides at t + ω). ``links``:
    the episode's links when the caller has them already (:func:`episode_links` of the same
    config, dataset and seed, simulated far enough for the policy's wait)."""
    pol = parse_policy(policy)
    if pol.wants_quality:
        raise ValueError(f"policy {pol.spec!r} is rewarded by the quality of its renders, so "
                         "its decisions cannot be planned before the episode is scored: run "
                         "it with aoi3d.experiment.adaptive.run_stepwise")
    pol.reset()
    wait = pol.wait_ms
    if links is None:
        links = episode_links(cfg, dataset, seed, wait_ms=wait)
    elif links.seed != seed:
        raise ValueError(f"links of seed {links.seed} given for episode seed {seed}")
    if pol.budget_steps is not None or getattr(pol, "chooses_budget", False):
        check_budget_applies(cfg)
    lag = display_lag(cfg)
    times = cfg.decision_times_ms()
    first_scored = next(i for i, t in enumerate(times) if t >= cfg.warmup_ms)
    decisions = []
    feed = links.delivery_feed()
    for i, t in enumerate(times):
        scored = i >= first_scored and (i - first_scored) % cfg.score_every == 0
        train = scored or cfg.carry in BACKGROUND_MODES  # they train at every decision
        sel = decide(pol, t, links.newest_ms, deliveries=feed, lag=lag)
        decisions.append(planned_decision(sel, links.camera_ids, train=train, scored=scored))
    return EpisodePlan(
        config=cfg, policy=pol.spec, seed=links.seed, wait_ms=wait,
        scene_offset_ms=links.scene_offset_ms, phase_ms=links.phase_ms,
        decisions=tuple(decisions), drop_ratio=links.drop_ratio,
    )


def dataset_fingerprint(dataset: SceneDataset) -> dict[str, Any]:
    """What identifies a dataset's content for the result cache."""
    return {
        "root": str(dataset.root), "layout": dataset.layout, "config_hash": dataset.config_hash,
        "fps": dataset.fps, "n_frames": dataset.n_frames, "size": [dataset.width, dataset.height],
        "cameras": len(dataset.cameras), "heldout_id": dataset.heldout_id,
        "aabb": np.asarray(dataset.aabb).tolist(),
    }


def plan_key(plan: EpisodePlan, dataset: SceneDataset, *, lpips: bool) -> str:
    """The cache key of a plan's numbers: everything they depend on, the policy's name not
    (two policies with the same selections share one result). ``lpips``: whether LPIPS will
    be computed (its weights are available and the config asks for it)."""
    cfg = plan.config
    doc = {
        "engine": ENGINE_VERSION,
        "dataset": dataset_fingerprint(dataset),
        "field": _field_dict(cfg),
        "steps_per_epoch": cfg.steps_per_epoch, "carry": cfg.carry, "device": cfg.device,
        **({"render_steps": cfg.render_steps} if cfg.carry in FINETUNE_MODES else {}),
        # the stream carry's gap leaves out the job's own time (Reconstruction.ready)
        **({"warm_gap": "less_job"} if cfg.carry == "stream" else {}),
        "compute": [cfg.time_scale, cfg.compute_fixed_ms, cfg.compute_step_ms],
        **({"pool_workers": cfg.pool_workers} if cfg.pool_workers else {}),
        **({"job_ms": [list(x) for x in cfg.job_ms]} if cfg.job_ms else {}),
        "lpips": lpips, "reward": [cfg.reward.psnr, cfg.reward.ssim, cfg.reward.lpips,
                                       *([cfg.reward.psnr_dynamic, cfg.reward.ssim_dynamic]
                                         if cfg.reward.dynamic else [])],
        "seed": plan.seed, "scene_offset_ms": plan.scene_offset_ms,
        "decisions": [
            [d.eval_ms, d.cameras, d.gen_ms, d.train, d.scored,
             *([] if d.budget_steps is None else [d.budget_steps])]
            for d in plan.decisions if d.train or d.scored
        ],
    }
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


_OFF_WHEN = {"age_weight_tau_ms": None, "age_features": 0}
"""Field settings that change no number at these values, left out of the cache key (a key
made before they existed stays valid); ``age_scale_ms`` goes with ``age_features`` = 0."""


def _field_dict(cfg: EpisodeConfig) -> dict[str, Any]:
    fc = field_config(cfg.backend, **cfg.field)
    out = {k: v for k, v in vars(fc).items() if k != "num_threads"
           and not (k in _OFF_WHEN and v == _OFF_WHEN[k])}
    if "age_features" not in out:
        out.pop("age_scale_ms", None)
    return {"backend": cfg.backend, "type": type(fc).__name__, **out}


def display_lag(cfg: EpisodeConfig) -> DisplayLag:
    """The virtual clock's lag from a decision to its display: the cost model of the config
    (:meth:`EpisodeConfig.compute_ms`: fixed + per step, at its time scale), no queue; the
    default budget :func:`render_budget`."""
    scale = cfg.time_scale
    return DisplayLag(fixed_ms=cfg.compute_fixed_ms * scale, step_ms=cfg.compute_step_ms * scale,
                      default_steps=render_budget(cfg))


def check_budget_applies(cfg: EpisodeConfig) -> None:
    """``ValueError`` unless the config's carry spends a budget per rendered decision (the
    ``warm`` carry renders its continuously trained model as it is)."""
    if cfg.carry == "warm":
        raise ValueError("a decision's budget ('@<steps>') applies to the fresh, stream and "
                         "fork carries; the warm carry renders its model as it is")


def decision_budget(cfg: EpisodeConfig, d: PlannedDecision) -> int:
    """The steps spent on a scored decision's own frames: its own budget, else the
    config's (:func:`render_budget`)."""
    return render_budget(cfg) if d.budget_steps is None else d.budget_steps


def render_budget(cfg: EpisodeConfig) -> int:
    """Steps spent on a scored decision's own frames: ``fresh`` trains each scored decision
    ``steps_per_epoch`` steps from scratch, ``fork`` a copy of the warm model
    ``render_steps`` steps, ``stream`` ``render_steps`` from the previous one's model (its
    cold starts ``steps_per_epoch``), ``warm`` none."""
    return {"fresh": cfg.steps_per_epoch, "fork": cfg.render_steps, "stream": cfg.render_steps,
            "warm": 0}[cfg.carry]


def total_steps(plan: EpisodePlan) -> int:
    """Training steps an episode takes (background and per scored decision)."""
    cfg = plan.config
    background = cfg.steps_per_epoch if cfg.carry in BACKGROUND_MODES else 0
    total = sum((background if d.train else 0) + (decision_budget(cfg, d) if d.scored else 0)
                for d in plan.decisions if d.cameras)
    if cfg.carry == "stream" and any(d.scored and d.cameras for d in plan.decisions):
        total += cfg.steps_per_epoch - cfg.render_steps  # the first, cold, start (at least)
    return total
