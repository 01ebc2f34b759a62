"""The metrics service's core: truth frames and renders in, Quality out.

No bus, no threads, no metrics library: the runtime (:mod:`services.metrics.runtime`) feeds it
from its scoring thread and publishes what it returns; tests drive it directly.

Pairing rule: a render at decision time t is compared with the ground-truth frame generated
exactly at t; failing that, with the newest one generated in [t − C, t] (C =
``truth_period_ms``); failing that the render is rejected with reason ``no_truth`` — the
runtime first holds a render whose t is past every truth frame received (its truth may still
be on its way) for up to ``truth_wait_s`` and tries again as truth frames arrive.

Dynamic region: the truth frame paired with a render, generated at t', is compared with the
truth frames generated at t' − C and t' − 2C (each the newest generated within half a period
of that time) to build the mask of :func:`aoi3d.quality.dynamic_mask`; the render's PSNR and
SSIM over it and its pixel fraction go into the Quality message. When those earlier frames are
missing (the first two periods, a gap, a size change) the dynamic fields are absent
(``no_history``); an empty mask (nothing moved) leaves the two scores absent (``empty_mask``).
The full-image scores and the reward do not depend on either.

Display time (issue 33): the same render is scored a second time against what it is shown
beside — the truth at the time it was ready (``Render.ready_ms``, stamped by the worker when
it publishes; the time it is scored when absent), paired by the same rule. PSNR, SSIM, LPIPS,
the reward and the dynamic-region PSNR then go into the ``*_display`` fields; they are absent
when no truth frame was generated in [display − C, display].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import cast

import numpy as np

from aoi3d.quality import (
    LpipsFn,
    QualityScore,
    RewardWeights,
    Truth,
    score_many,
)
from aoi3d.scene import HELDOUT_ID  # the held-out novel view: the only camera on the truth key
from services.kit.codec import check_size, decode_frame, decode_image, decode_render
from services.kit.keys import DEFAULT_SITE
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import Rejected, RejectReason
from services.metrics.truth import TruthFrame, TruthImages, TruthRing

__all__ = [
    "MetricsCore",
    "QualityRecord",
    "Scored",
    "TruthFrame",
    "TruthRing",
    "mean_of_present",
    "mean_or_none",
    "or_nan",
]



@dataclass(frozen=True)
class QualityRecord:
    """One scored render (the published Quality plus the render's context)."""

    decision_id: int
    time_ms: float
    truth_time_ms: float
    scene_time_ms: float
    psnr_db: float
    ssim: float
    lpips: float | None
    reward: float | None
    """None when LPIPS was skipped (``lpips_skipped``): the reward needs it."""
    reward_terms: tuple[str, ...]
    training_step: int
    n_views: int
    backend: str
    lag_ms: float
    """Sim ms between the render's time t and its scoring."""
    psnr_dynamic_db: float | None = None
    """PSNR over the dynamic region; None when its mask is empty or could not be built."""
    ssim_dynamic: float | None = None
    """SSIM over the dynamic region; None likewise."""
    dynamic_fraction: float | None = None
    """Pixel fraction of the dynamic mask; None when the earlier truth frames were missing."""
    display_time_ms: float | None = None
    """Sim time the render was ready (its ``ready_ms``, else the time it was scored): the
    display scores below are against the truth then; None for all of them when no truth
    frame was generated in [display − C, display]."""
    psnr_display_db: float | None = None
    ssim_display: float | None = None
    lpips_display: float | None = None
    reward_display: float | None = None
    psnr_dynamic_display_db: float | None = None
    lpips_skipped: bool = False
    """LPIPS left out by the metrics service's sampling: ``lpips``, ``lpips_display``,
    ``reward`` and ``reward_display`` are None, ``reward_terms`` empty."""


@dataclass(frozen=True)
class Scored:
    """What scoring one render yields: the message to publish, the history record and, when
    the dynamic scores are absent, why (``no_history`` or ``empty_mask``)."""

    message: pb.Quality
    record: QualityRecord
    dynamic_missing: str | None


class MetricsCore:
    """One site's truth frames and scoring. Not thread-safe: one thread calls it."""

    def __init__(self, *, truth_period_ms: float = 30.0, truth_frames: int = 512,
                 weights: RewardWeights | None = None, lpips_fn: LpipsFn | None = None,
                 max_skew_ms: float = 50.0, site: str = DEFAULT_SITE) -> None:
        if not (math.isfinite(truth_period_ms) and truth_period_ms > 0):
            raise ValueError(f"truth_period_ms must be > 0, got {truth_period_ms}")
        self.period_ms = float(truth_period_ms)
        self.ring = TruthRing(truth_frames)  # (its setter keeps the decoded images beside it)
        self.weights = weights or RewardWeights()
        self.lpips_fn = lpips_fn
        self.skew_ms = float(max_skew_ms)
        self.site = site

    @property
    def ring(self) -> TruthRing:
        """The truth frames held; set a new one to start again (the replay does, going back
        in time), the decoded images and masks of the old one are dropped with it."""
        return self._ring

    @ring.setter
    def ring(self, ring: TruthRing) -> None:
        self._ring = ring
        self._truth = TruthImages(ring, self.period_ms)

    def _ahead(self, what: str, time_ms: float, now_ms: float) -> None:
        """Reject a message stamped ahead of this clock by more than the skew: 512 truth
        frames from the future would otherwise push every real one out of the ring."""
        if time_ms > now_ms + self.skew_ms:
            raise Rejected(RejectReason.CLOCK_SKEW, f"{what} at {time_ms:g} ms but this clock says "
                                                    f"{now_ms:g} ms")

    def on_truth(self, payload: bytes, now_ms: float) -> TruthFrame:
        """Keep a truth frame; :class:`Rejected` when it is invalid or from the future."""
        frame = decode_frame(payload, camera_ids={HELDOUT_ID})
        self._ahead("truth frame generated", frame.generation_ms, now_ms)
        truth = TruthFrame(generation_ms=frame.generation_ms,
                           scene_time_ms=frame.scene_time_ms, image=frame.image)
        self.ring.add(truth)
        return truth

    def score(self, payload: bytes, now_ms: float, *, lpips: bool = True) -> Scored:
        """Pair a render with its truth and score it; :class:`Rejected` when it cannot be.
        ``lpips`` False (the service's sampling): no LPIPS for this render, so no reward
        either; the Quality says so (``lpips_skipped``) when LPIPS is available at all."""
        render, _camera = decode_render(payload)
        self._ahead("render for", render.time_ms, now_ms)
        truth = self.ring.pair(render.time_ms, self.period_ms)
        check_size(render.image, (truth.image.width, truth.image.height))
        pred = decode_image(render.image)
        gt = self._truth.decoded(truth)
        if pred.shape != gt.shape:
            raise Rejected(RejectReason.IMAGE_SIZE_MISMATCH,
                           f"render is {pred.shape[1]}x{pred.shape[0]} but the ground truth is "
                           f"{gt.shape[1]}x{gt.shape[0]}")
        display_ms = render.ready_ms if render.HasField("ready_ms") else now_ms
        skipped = not lpips and self.lpips_fn is not None
        q, shown, shown_truth = self._score_both(pred, truth, display_ms,
                                                 None if skipped else self.lpips_fn)
        if skipped:  # PSNR and SSIM alone are not the reward: none rather than another one
            q = replace(q, reward=math.nan, reward_terms=())
            shown = None if shown is None else replace(shown, reward=math.nan)
        dyn = q.dynamic
        msg = pb.Quality(decision_id=render.decision_id,
                         decision_incarnation=render.decision_incarnation,
                         time_ms=render.time_ms,
                         scene_time_ms=truth.scene_time_ms, psnr_db=q.psnr_db, ssim=q.ssim,
                         reward=q.reward, reward_terms=list(q.reward_terms),
                         training_step=render.training_step,
                         truth_time_ms=truth.generation_ms, site=self.site,
                         render_steps=render.render_steps, ready_ms=display_ms,
                         lpips_skipped=skipped)
        if q.lpips is not None:
            msg.lpips = q.lpips  # proto3 optional: left unset (absent) when unavailable
        if dyn is not None:
            msg.dynamic_fraction = dyn.fraction
            if dyn.psnr_db is not None:
                msg.psnr_dynamic_db = dyn.psnr_db
            if dyn.ssim is not None:
                msg.ssim_dynamic = dyn.ssim
        if shown is not None and shown_truth is not None:
            msg.display_time_ms = display_ms
            msg.display_truth_time_ms = shown_truth.generation_ms
            msg.psnr_display_db = shown.psnr_db
            msg.ssim_display = shown.ssim
            msg.reward_display = shown.reward
            if shown.lpips is not None:
                msg.lpips_display = shown.lpips
            if shown.dynamic is not None and shown.dynamic.psnr_db is not None:
                msg.psnr_dynamic_display_db = shown.dynamic.psnr_db
        record = QualityRecord(
            decision_id=render.decision_id, time_ms=render.time_ms,
            truth_time_ms=truth.generation_ms, scene_time_ms=truth.scene_time_ms,
            psnr_db=q.psnr_db, ssim=q.ssim, lpips=q.lpips,
            reward=None if skipped else q.reward, lpips_skipped=skipped,
            reward_terms=q.reward_terms, training_step=render.training_step,
            n_views=render.n_views, backend=render.backend, lag_ms=now_ms - render.time_ms,
            psnr_dynamic_db=dyn.psnr_db if dyn else None,
            ssim_dynamic=dyn.ssim if dyn else None,
            dynamic_fraction=dyn.fraction if dyn else None,
            **({} if shown is None else dict(
                display_time_ms=display_ms, psnr_display_db=shown.psnr_db,
                ssim_display=shown.ssim, lpips_display=shown.lpips,
                reward_display=None if skipped else shown.reward,
                psnr_dynamic_display_db=shown.dynamic.psnr_db if shown.dynamic else None)))
        missing = ("no_history" if dyn is None else
                   "empty_mask" if dyn.psnr_db is None else None)
        return Scored(msg, record, missing)

    def _score_both(self, pred: np.ndarray, truth: TruthFrame, display_ms: float,
                    lpips_fn: LpipsFn | None
                    ) -> tuple[QualityScore, QualityScore | None, TruthFrame | None]:
        """The render against the truth at its decision time and against the truth at
        ``display_ms`` (the newest generated in [display − C, display]), in one
        :func:`score_many` call: (at decision, at display, the display's truth frame). The
        display score is the decision's when both pair the same frame (not scored twice), and
        None (with its frame) when there is no such frame, or it cannot be decoded or scored:
        the decision's score stands alone then."""
        truths = [Truth(self._truth.decoded(truth), mask=self._truth.mask(truth))]
        try:
            shown = self.ring.pair(display_ms, self.period_ms)
        except Rejected:
            shown = None
        if shown is not None and shown.generation_ms != truth.generation_ms:
            try:
                image = self._truth.decoded(shown)
            except Rejected:
                image = None
            if image is not None and image.shape == pred.shape:
                truths.append(Truth(image, mask=self._truth.mask(shown)))
            else:
                shown = None
        try:
            scores = score_many(pred, truths, self.weights, lpips_fn=lpips_fn)
        except ValueError as err:
            if len(truths) == 1:
                raise Rejected(RejectReason.UNSCORABLE, str(err)) from err
            try:  # the display's truth could not be scored: the decision's alone
                return score_many(pred, truths[:1], self.weights, lpips_fn)[0], None, None
            except ValueError as err1:
                raise Rejected(RejectReason.UNSCORABLE, str(err1)) from err1
        if shown is None:
            return scores[0], None, None
        return scores[0], scores[-1], shown

def or_nan(value: float | None) -> float:
    return math.nan if value is None else value


def mean_of_present(values: list[float | None]) -> float | None:
    """The mean of the values that are not None, or None when there are none."""
    present = [v for v in values if v is not None]
    return float(np.mean(present)) if present else None


def mean_or_none(values: list[float | None]) -> float | None:
    """The mean of ``values``, or None when empty or when any value is None."""
    if not values or any(v is None for v in values):
        return None
    return float(np.mean(cast("list[float]", values)))  # no None in it (above)
