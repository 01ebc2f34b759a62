"""Scoring a replay (see :mod:`services.recorder.replay`): rebuild a decision's render with the
live worker's code (:class:`services.recon.core.ReconCore`) and score it with the live metrics
code (:class:`services.metrics.core.MetricsCore`); each job's budget; and the scores a replay
compares with the recorded ones (:data:`SCORES`)."""

from __future__ import annotations

import bisect
import math
from typing import TYPE_CHECKING, Any

from aoi3d.metric import AT_DECISION
from aoi3d.quality import DYNAMIC_FRAMES, LpipsFn, RewardWeights
from services.kit.pb import aoi3d_pb2 as pb
from services.recorder.recording import Recorded, SiteRecord

if TYPE_CHECKING:
    from aoi3d.field import FieldConfig

__all__ = ["SCORES", "Scorer", "job_budgets"]

TRUTH_RING = 512
"""Truth frames a replay's scorer holds at once (the live metrics service's ring)."""
SCORES = AT_DECISION
"""The Quality fields compared (each where both have it): the scores at the decision's time,
:data:`aoi3d.metric.AT_DECISION`."""


class Scorer:
    """Rebuilds renders with the live worker's code and scores them with the metrics code.

    The truth frames go into the metrics core's ring as the scored decisions reach them, each
    read from the recording when it goes in (:meth:`Recorded.with_pixels`), at most
    :data:`TRUTH_RING` of them held: memory does not grow with the recording. A render is
    paired with the truth of its time and the :data:`DYNAMIC_FRAMES` before it, as live.

    :meth:`score` rebuilds a render on the scorer's own worker core, whose model no other job
    shares (the ``fresh`` carry: a render that depends on its decision alone, cached by its
    job); a chain of jobs that depends on a worker's history (the ``stream`` carry) runs on
    that worker's core (:mod:`services.recorder.chains`): :meth:`job` and :meth:`quality`.
    ``configs``: field configs by backend that replace the defaults (as
    :class:`services.recon.core.ReconCore` takes them: tests use small ones)."""

    def __init__(self, rec: Recorded, site: str, *, lpips: bool, threads: int,
                 lpips_fn: LpipsFn | None = None,
                 configs: dict[str, FieldConfig] | None = None) -> None:
        from services.metrics.core import MetricsCore
        from services.recon.core import ReconCore

        meta = rec.metadata
        weights = RewardWeights(
            psnr=float(meta.get("reward_psnr", RewardWeights().psnr)),
            ssim=float(meta.get("reward_ssim", RewardWeights().ssim)),
            lpips=float(meta.get("reward_lpips", RewardWeights().lpips)),
            psnr_dynamic=float(meta.get("reward_psnr_dynamic", 0.0)),
            ssim_dynamic=float(meta.get("reward_ssim_dynamic", 0.0)))
        if lpips and lpips_fn is None:
            from aoi3d.lpips import load_lpips_fn

            lpips_fn = load_lpips_fn(meta.get("lpips_net", "alex"))
            if lpips_fn is None:
                raise ValueError("the recorded scores used LPIPS but its weights are not "
                                 "cached here (python -m aoi3d.lpips fetch)")
        self._rec, self._site = rec, site
        self._truth = rec.sites[site].truth  # sorted by generation time
        self._gens = [fr.generation_ms for fr in self._truth]
        self.metrics = MetricsCore(truth_period_ms=float(meta.get("truth_period_ms", 30.0)),
                                   truth_frames=TRUTH_RING, weights=weights,
                                   lpips_fn=lpips_fn if lpips else None, site=site)
        self._fed = (0, 0)  # the truth frames [lo, hi) fed into the ring since it was made
        self.recon = ReconCore(worker_id="replay", device="cpu", num_threads=threads,
                               configs=configs)
        self._cache: dict[tuple[Any, ...], pb.Quality] = {}

    def _feed(self, start_ms: float, end_ms: float) -> None:
        """The ring holds every truth frame generated in [start_ms, end_ms]."""
        from services.metrics.core import TruthRing

        lo = bisect.bisect_left(self._gens, start_ms)
        hi = bisect.bisect_right(self._gens, end_ms)
        fed_lo, fed_hi = self._fed
        if lo < fed_lo or lo < fed_hi - TRUTH_RING or hi - lo > TRUTH_RING:
            self.metrics.ring = TruthRing(TRUTH_RING)  # back in time: fed again from lo
            fed_lo = fed_hi = lo
        for fr in self._truth[max(fed_hi, lo):hi]:
            full = self._rec.with_pixels(self._site, fr)
            if full.image.data:
                self.metrics.on_truth(full.SerializeToString(), math.inf)
        self._fed = (fed_lo, max(fed_hi, hi))

    def score(self, decision: pb.Decision, render: pb.Render, frames: list[pb.Frame],
              steps: int) -> pb.Quality:
        """The Quality of ``decision`` rebuilt from ``frames`` as the job of ``render`` was
        (``steps``: the job's budget; a render of an empty selection says 0);
        :class:`services.recon.core.JobFailed` when the worker's code refuses it."""
        key = (render.backend, render.carry, steps, render.seed,
               decision.time_ms, tuple((f.camera_id, f.generation_ms) for f in frames))
        if key in self._cache:
            out = pb.Quality()
            out.CopyFrom(self._cache[key])
            out.decision_id = decision.decision_id
            return out
        outcome = self.recon.run(self.job(decision, render, frames, steps))
        q = self.quality(outcome.render)
        self._cache[key] = q
        return q

    def job(self, decision: pb.Decision, render: pb.Render, frames: list[pb.Frame], steps: int,
            *, cold_steps: int = 0, max_gap_ms: float = 0.0, model_epoch: int = 0) -> pb.Job:
        """The job of ``render`` again, on ``decision`` and ``frames`` (their pixels read from
        the recording): ``steps`` its budget, the stream carry's cold budget and gap (0: the
        worker's defaults) and the model epoch as the live job had them."""
        job = pb.Job(decision=decision, backend=render.backend, carry=render.carry,
                     render_steps=steps, seed=render.seed, model_epoch=model_epoch,
                     pose=render.pose, intrinsics=render.intrinsics, aabb=list(render.aabb),
                     site=render.site, cold_steps=cold_steps, warm_max_gap_ms=max_gap_ms)
        for f in frames:
            job.frames.add().CopyFrom(self._rec.with_pixels(self._site, f))
        return job

    def quality(self, render: pb.Render) -> pb.Quality:
        """The Quality of a rebuilt render (paired with the truth of its time)."""
        period = self.metrics.period_ms
        self._feed(render.time_ms - (DYNAMIC_FRAMES + 2) * period, render.time_ms + 1.0)
        q: pb.Quality = self.metrics.score(render.SerializeToString(), math.inf).message
        return q


def job_budgets(srec: SiteRecord) -> dict[tuple[int, int], int]:
    """Each rendered decision's job budget (``render_steps``): its Render's, or — for a
    render of an empty selection, which reports 0 — the nearest earlier render's that trained
    (else the nearest later one's)."""
    keys = [(d.incarnation, d.decision_id) for d in srec.decisions
            if (d.incarnation, d.decision_id) in srec.renders]
    steps = [int(srec.renders[k].render_steps) for k in keys]
    out, last = {}, 0
    for k, s in zip(keys, steps, strict=True):
        last = s or last
        out[k] = last
    nxt = 0
    for k, s in zip(reversed(keys), reversed(steps), strict=True):
        nxt = s or nxt
        out[k] = out[k] or nxt or 1
    return out
