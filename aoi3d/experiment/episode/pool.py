"""The twin of the live pool on the virtual clock (:func:`run_pool_plan`: ``pool_workers`` ≥ 1).

Live, every decision goes to the dispatcher service, which hands the newest one to
a free reconstruction worker and counts the ones no worker took ``superseded``; each worker
keeps one model, and under the ``stream`` carry a job continues the model of that worker's
previous job (the warm chain). The twin runs the same dispatcher (:class:`aoi3d.pool.
Dispatcher`, with ``prefer_warm`` under ``stream`` as the dispatcher sets it) on the virtual
clock, with simulated workers in place of the processes:

- each planned decision is offered at its time (``eval_ms``: a waiting policy's decision is
  published at t + ω), after every job that ended by then has reported and taken the next;
- a job runs at once, on its worker's own model (:class:`aoi3d.field.carry.Reconstruction`
  seeded with the episode's seed, as each live worker's is with the job's), and occupies the
  worker for the config's compute time of the steps it trained
  (:meth:`~aoi3d.experiment.config.EpisodeConfig.compute_ms`: a cold start's 100 steps cost
  more than a warm start's 25); its end is its render's display time;
- a rendered decision of the scored span is scored at its time and at its display time
  (:func:`aoi3d.experiment.episode.scoring.epoch_score`, as the no-pool engine does); the
  decisions the pool left are counted (:class:`PoolOutcome`).

Times go to the dispatcher in wall seconds (scene ms / ``time_scale`` / 1000), as the live
dispatcher's clock gives them. What the twin leaves out: the messaging between the processes
(a job's frames, the Render's way back; a few ms), and the other processes' share of the
cores, which is in the measured compute time.
"""

from __future__ import annotations

import heapq
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from aoi3d.experiment.config import EpisodeConfig
from aoi3d.experiment.episode.plan import EpisodePlan, PlannedDecision, decision_budget
from aoi3d.experiment.episode.result import EpisodeResult, EpochScore, episode_result
from aoi3d.experiment.episode.scoring import Frames, epoch_score
from aoi3d.field import FieldTrainer, field_config
from aoi3d.field.carry import Reconstruction, RenderedDecision, WarmStart
from aoi3d.pool import Assignment, DecisionRef, Dispatcher, Report
from aoi3d.quality import LpipsFn
from aoi3d.scene import SceneDataset

__all__ = ["PoolOutcome", "run_pool_plan"]

_INCARNATION = 1
"""The twin's decisions' incarnation (one scheduler, never restarted)."""


@dataclass(frozen=True)
class PoolOutcome:
    """What the pool did with an episode's decisions: ``offered`` (all of them), ``rendered``
    and ``superseded`` (left for a newer one), each over the whole episode and, ``*_scored``,
    over the scored span; ``warm`` of the rendered ones started from their worker's previous
    model (``stream``)."""

    offered: int
    rendered: int
    superseded: int
    warm: int
    offered_scored: int
    rendered_scored: int

    @property
    def rendered_fraction(self) -> float:
        """Of the scored span's decisions, the share rendered (NaN: none offered)."""
        return self.rendered_scored / self.offered_scored if self.offered_scored else math.nan


class _Worker:
    """A simulated reconstruction worker: its model, made at its first job."""

    def __init__(self, worker_id: str, cfg: EpisodeConfig, dataset: SceneDataset,
                 seed: int) -> None:
        self.worker_id = worker_id
        self._cfg, self._dataset, self._seed = cfg, dataset, seed
        self.rec: Reconstruction | None = None

    def run(self, cfg: EpisodeConfig, d: PlannedDecision, frames: Frames) -> RenderedDecision:
        """Train this worker's model on the decision's frames and render the held-out view."""
        if self.rec is None:
            trainer = FieldTrainer(field_config(cfg.backend, **cfg.field), self._dataset.aabb,
                                   device=cfg.device, seed=self._seed)
            self.rec = Reconstruction(trainer, cfg.carry, decision_budget(cfg, d),
                                      WarmStart(cold_steps=cfg.steps_per_epoch))
        rec = self.rec
        budget = decision_budget(cfg, d)
        if budget != rec.render_steps:
            rec.set_carry(cfg.carry, budget)
        time_aware = rec.trainer.cfg.time_aware
        model_ms = frames.content_ms(d.eval_ms) if time_aware else d.eval_ms
        rec.set_views([frames.view(c, g, d.eval_ms, time_aware)
                       for c, g in zip(d.cameras, d.gen_ms, strict=True)], model_ms)
        heldout = self._dataset.cameras[self._dataset.heldout_id]
        return rec.render_decision(heldout, time_ms=model_ms)


@dataclass
class _Job:
    decision: PlannedDecision
    ref: DecisionRef
    rendered: RenderedDecision
    end_ms: float


class _Twin:
    """One episode through the pool: the dispatcher, the simulated workers, the jobs running
    (a heap by their end) and the scores of the rendered decisions of the scored span."""

    def __init__(self, plan: EpisodePlan, dataset: SceneDataset, lpips_fn: LpipsFn | None,
                 on_render: Callable[[PlannedDecision, np.ndarray], None] | None) -> None:
        cfg = self.cfg = plan.config
        self.frames = Frames(dataset, plan.scene_offset_ms)
        self.heldout = dataset.cameras[dataset.heldout_id]
        self.lpips_fn, self.on_render = lpips_fn, on_render
        self.pool = Dispatcher(job_timeout_s=math.inf, fresh_fraction=cfg.pool_fresh_fraction)
        self.pool.prefer_warm = cfg.carry == "stream"  # the dispatcher's choice for stream
        self.workers = {f"twin-{i}": _Worker(f"twin-{i}", cfg, dataset, plan.seed)
                        for i in range(cfg.pool_workers)}
        for wid in self.workers:
            self.pool.joined(wid, 0.0)
            self.pool.request(Report(wid, max_wait_s=math.inf), 0.0)
        self.decisions = dict(enumerate(plan.decisions))
        self.running: list[tuple[float, int, str]] = []  # (end ms, decision id, worker id)
        self.held: dict[str, _Job] = {}
        self.epochs: list[EpochScore] = []
        self.last: np.ndarray | None = None
        self.warm = self.rendered = self.steps = 0

    def wall_s(self, ms: float) -> float:
        """Scene ms as the live dispatcher's clock gives them: wall seconds."""
        return ms / self.cfg.time_scale / 1000.0

    def offer(self, i: int) -> None:
        """Decision ``i`` is published: the jobs that ended by then report first."""
        d = self.decisions[i]
        self.finish_until(d.eval_ms)
        got = self.pool.offer(DecisionRef(_INCARNATION, i, float(d.eval_ms)),
                              self.wall_s(d.eval_ms))
        if got is not None:
            self.start(got, float(d.eval_ms))

    def start(self, a: Assignment, now_ms: float) -> None:
        d = self.decisions[a.decision.decision_id]
        worker = self.workers[a.worker_id]
        rendered = worker.run(self.cfg, d, self.frames)
        end_ms = now_ms + self.cfg.compute_ms(rendered.render_steps, rendered.n_views)
        assert worker.rec is not None  # it just ran the job
        worker.rec.ready(self.frames.content_ms(end_ms) if worker.rec.trainer.cfg.time_aware
                         else end_ms)
        self.held[a.worker_id] = _Job(d, a.decision, rendered, end_ms)
        heapq.heappush(self.running, (end_ms, a.decision.decision_id, a.worker_id))

    def finish_until(self, t_ms: float) -> None:
        """Every job ending by ``t_ms`` ends (in order): scored, and its worker asks again."""
        while self.running and self.running[0][0] <= t_ms:
            end_ms, _, wid = heapq.heappop(self.running)
            job = self.held.pop(wid)
            self.rendered += 1
            self.warm += int(job.rendered.warm)
            self.steps += job.rendered.render_steps
            if job.decision.decision_ms >= self.cfg.warmup_ms:
                self._score(wid, job)
            nxt = self.pool.request(Report(wid, done=job.ref.key, rendered=True,
                                           max_wait_s=math.inf), self.wall_s(end_ms))
            if nxt is not None:
                self.start(nxt, end_ms)

    def _score(self, worker_id: str, job: _Job) -> None:
        rec = self.workers[worker_id].rec
        assert rec is not None  # it just ran the job
        self.epochs.append(epoch_score(self.cfg, job.decision, rec, job.rendered, self.frames,
                                       self.heldout, self.lpips_fn, display_ms=job.end_ms,
                                       loss=job.rendered.loss))
        self.last = job.rendered.image
        if self.on_render is not None:
            self.on_render(job.decision, job.rendered.image)

    def outcome(self) -> PoolOutcome:
        in_span = sum(d.decision_ms >= self.cfg.warmup_ms for d in self.decisions.values())
        return PoolOutcome(offered=len(self.decisions), rendered=self.rendered,
                           superseded=self.pool.superseded, warm=self.warm,
                           offered_scored=in_span, rendered_scored=len(self.epochs))


def run_pool_plan(
    plan: EpisodePlan,
    dataset: SceneDataset,
    *,
    key: str = "",
    lpips_fn: LpipsFn | None = None,
    on_render: Callable[[PlannedDecision, np.ndarray], None] | None = None,
) -> tuple[EpisodeResult, PoolOutcome, np.ndarray | None]:
    """Run the plan through the pool's twin (see the module docstring): the result (over the
    scored span's rendered decisions), what the pool did, and the last render's image."""
    if plan.config.pool_workers < 1:
        raise ValueError("run_pool_plan needs a config with pool_workers >= 1")
    started = time.perf_counter()
    twin = _Twin(plan, dataset, lpips_fn, on_render)
    for i in twin.decisions:
        twin.offer(i)
    twin.finish_until(math.inf)  # the jobs running at the end finish, and take what is pending
    outcome = twin.outcome()
    if not twin.epochs:
        raise ValueError(f"the pool's twin rendered none of the {outcome.offered_scored} "
                         "decisions of the scored span: lengthen scored_ms or add workers")
    epochs = sorted(twin.epochs, key=lambda e: e.decision_ms)
    result = episode_result(plan, epochs, key=key, wall_s=time.perf_counter() - started,
                            train_steps=twin.steps,
                            rendered_fraction=outcome.rendered_fraction)
    return result, outcome, twin.last
