"""The metrics service's core: truth frames and renders in, Quality out.

No bus, no threads, no metrics library: the runtime (:mod:`services.metrics.worker`) feeds it
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

import bisect
import math
from dataclasses import dataclass
from typing import cast

import numpy as np

from aoi3d.quality import DYNAMIC_FRAMES, LpipsFn, QualityScore, RewardWeights, score
from aoi3d.scene import HELDOUT_ID  # the held-out novel view: the only camera on the truth key
from services.kit.codec import check_size, decode_frame, decode_image, decode_render
from services.kit.keys import DEFAULT_SITE
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import Rejected, RejectReason

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

_TIME_TOL_MS = 1e-6  # generation times this close to t count as "at t" (float round-off)


@dataclass(frozen=True)
class TruthFrame:
    """A ground-truth frame of the held-out camera, image still encoded."""

    generation_ms: float
    scene_time_ms: float
    image: pb.Image


class TruthRing:
    """The most recent ground-truth frames, by generation time (not thread-safe)."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self._capacity = capacity
        self._times: list[float] = []  # sorted generation times
        self._frames: dict[float, TruthFrame] = {}

    def __len__(self) -> int:
        return len(self._times)

    @property
    def newest_ms(self) -> float | None:
        """Generation time of the newest frame held (None when empty)."""
        return self._times[-1] if self._times else None

    def add(self, frame: TruthFrame) -> None:
        """Keep ``frame`` (a repeat of a generation time replaces it); evict the oldest."""
        if frame.generation_ms not in self._frames:
            bisect.insort(self._times, frame.generation_ms)
        self._frames[frame.generation_ms] = frame
        while len(self._times) > self._capacity:
            del self._frames[self._times.pop(0)]

    def pair(self, time_ms: float, period_ms: float) -> TruthFrame:
        """The frame generated at ``time_ms``, else the newest in [time_ms − period_ms,
        time_ms]; raises ``Rejected(RejectReason.NO_TRUTH)`` when there is none."""
        exact = self._frames.get(time_ms)
        if exact is not None:
            return exact
        i = bisect.bisect_right(self._times, time_ms + _TIME_TOL_MS) - 1
        if i >= 0 and time_ms - self._times[i] <= period_ms + _TIME_TOL_MS:
            return self._frames[self._times[i]]
        held = (f"holding {len(self)} frame(s) generated in [{self._times[0]:g}, "
                f"{self._times[-1]:g}] ms" if self._times else "holding no frame")
        raise Rejected(RejectReason.NO_TRUTH,
                       f"no ground-truth frame generated at t = {time_ms:g} ms or "
                       f"within {period_ms:g} ms before it ({held})")

    def before(self, generation_ms: float, period_ms: float, count: int
               ) -> list[TruthFrame] | None:
        """The frames generated at ``generation_ms`` − k·``period_ms``, k = 1..``count``:
        for each, the newest generated in (that time − period/2, that time + period/2];
        None when any of them is missing."""
        half = period_ms / 2.0
        frames = []
        for k in range(1, count + 1):
            target = generation_ms - k * period_ms
            i = bisect.bisect_right(self._times, target + half) - 1
            if i < 0 or self._times[i] <= target - half:
                return None
            frames.append(self._frames[self._times[i]])
        return frames


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
    reward: float
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
        self.ring = TruthRing(truth_frames)
        self.weights = weights or RewardWeights()
        self.lpips_fn = lpips_fn
        self.skew_ms = float(max_skew_ms)
        self.site = site

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

    def score(self, payload: bytes, now_ms: float) -> Scored:
        """Pair a render with its truth and score it; :class:`Rejected` when it cannot be."""
        render, _camera = decode_render(payload)
        self._ahead("render for", render.time_ms, now_ms)
        truth = self.ring.pair(render.time_ms, self.period_ms)
        check_size(render.image, (truth.image.width, truth.image.height))
        pred = decode_image(render.image)
        gt = decode_image(truth.image)
        if pred.shape != gt.shape:
            raise Rejected(RejectReason.IMAGE_SIZE_MISMATCH,
                           f"render is {pred.shape[1]}x{pred.shape[0]} but the ground truth is "
                           f"{gt.shape[1]}x{gt.shape[0]}")
        previous = self._previous_truth(truth, gt.shape)
        try:
            q = score(pred, gt, self.weights, lpips_fn=self.lpips_fn, previous=previous)
        except ValueError as err:
            raise Rejected(RejectReason.UNSCORABLE, str(err)) from err
        dyn = q.dynamic
        display_ms = render.ready_ms if render.HasField("ready_ms") else now_ms
        shown, shown_truth = self._display_score(pred, display_ms, truth, q)
        msg = pb.Quality(decision_id=render.decision_id,
                         decision_incarnation=render.decision_incarnation,
                         time_ms=render.time_ms,
                         scene_time_ms=truth.scene_time_ms, psnr_db=q.psnr_db, ssim=q.ssim,
                         reward=q.reward, reward_terms=list(q.reward_terms),
                         training_step=render.training_step,
                         truth_time_ms=truth.generation_ms, site=self.site,
                         render_steps=render.render_steps, ready_ms=display_ms)
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
            psnr_db=q.psnr_db, ssim=q.ssim, lpips=q.lpips, reward=q.reward,
            reward_terms=q.reward_terms, training_step=render.training_step,
            n_views=render.n_views, backend=render.backend, lag_ms=now_ms - render.time_ms,
            psnr_dynamic_db=dyn.psnr_db if dyn else None,
            ssim_dynamic=dyn.ssim if dyn else None,
            dynamic_fraction=dyn.fraction if dyn else None,
            **({} if shown is None else dict(
                display_time_ms=display_ms, psnr_display_db=shown.psnr_db,
                ssim_display=shown.ssim, lpips_display=shown.lpips,
                reward_display=shown.reward,
                psnr_dynamic_display_db=shown.dynamic.psnr_db if shown.dynamic else None)))
        missing = ("no_history" if dyn is None else
                   "empty_mask" if dyn.psnr_db is None else None)
        return Scored(msg, record, missing)

    def _display_score(self, pred: np.ndarray, display_ms: float, truth: TruthFrame,
                       at_decision: QualityScore
                       ) -> tuple[QualityScore | None, TruthFrame | None]:
        """The render against the truth at ``display_ms`` (the newest generated in
        [display − C, display]): ``at_decision`` again when that is the decision-time
        pairing's frame (not scored twice). (None, None) when there is none, or it cannot be
        scored."""
        try:
            shown = self.ring.pair(display_ms, self.period_ms)
        except Rejected:
            return None, None
        if shown.generation_ms == truth.generation_ms:
            return at_decision, shown
        try:
            gt = decode_image(shown.image)
            if gt.shape != pred.shape:
                return None, None
            return score(pred, gt, self.weights, lpips_fn=self.lpips_fn,
                         previous=self._previous_truth(shown, gt.shape)), shown
        except (Rejected, ValueError):
            return None, None

    def _previous_truth(self, truth: TruthFrame, shape: tuple[int, ...]
                        ) -> list[np.ndarray] | None:
        """The decoded truth one to K periods before ``truth`` (see :meth:`TruthRing.before`),
        or None when a frame is missing, undecodable or of another size."""
        frames = self.ring.before(truth.generation_ms, self.period_ms, DYNAMIC_FRAMES)
        if frames is None:
            return None
        images = []
        for frame in frames:
            try:
                image = decode_image(frame.image)
            except Rejected:
                return None
            if image.shape != shape:
                return None
            images.append(image)
        return images


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
