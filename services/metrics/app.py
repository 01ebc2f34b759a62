"""REST API of the metrics service: the quality history of the rendered novel view."""

from __future__ import annotations

import logging
from typing import Annotated

from fastapi import APIRouter, Depends, FastAPI, Query
from pydantic import BaseModel, Field

from aoi3d.clock import SimClock
from aoi3d.lpips import load_lpips_fn, weights_path
from aoi3d.quality import LpipsFn
from services.kit.app import get_worker, include_site_routers, service_app
from services.kit.bus import Bus
from services.metrics.core import QualityRecord, mean_of_present, mean_or_none
from services.metrics.runtime import MetricsRuntime
from services.metrics.settings import Settings

log = logging.getLogger(__name__)

DESCRIPTION = """\
Scores each render of the held-out novel view against the ground-truth frame of the same
time (PSNR, SSIM and, when its weights are cached, LPIPS) and publishes a `Quality` message
per render. `reward_terms` says which metrics the reward was built from.

Sampling: LPIPS runs on `lpips_per_s` renders a wall second on average, a burst of one
second's worth let through (0: every render), so
that scoring keeps up at real time; the others are scored with PSNR and SSIM (and their
dynamic and display-time forms) alone and marked `lpips_skipped`: no LPIPS and no reward
(it needs LPIPS), counted in `aoi3d_quality_lpips_skipped_total`. The means below are over
the entries that have the value.

Pairing: the truth frame generated exactly at the render's time t, else the newest generated
within one generation period before t; otherwise the render is dropped and counted in
`aoi3d_messages_rejected_total{reason="no_truth"}` — after a wait of up to `truth_wait_s` when
its time is past every truth frame received (its truth may still be on its way).

Dynamic region: besides the full-image scores, PSNR and SSIM over the pixels of the view that
move — those whose ground truth changed by more than 8/255 in some channel since the truth
frames one and two generation periods earlier, dilated by one pixel (`aoi3d.quality`) — and
the fraction of the image they cover. Null when those earlier frames are missing
(`no_history`) or nothing moved (`empty_mask`, scores only), counted in
`aoi3d_quality_dynamic_missing_total{reason}`; never 0. The reward uses the full image only.

Decision ledger (`GET /ledger`, `aoi3d_ledger_decisions_total{state,reason}`): every decision
of the site ends in exactly one state — scored, skipped by choice (superseded) or lost with a
reason — or is still open; one open longer than `ledger_open_s` is counted lost (expired).
"""

Metrics = Annotated[MetricsRuntime, Depends(get_worker)]


class QualityEntry(BaseModel):
    """One scored render."""

    decision_id: int = Field(description="Decision whose selection the model was trained on.",
                             examples=[42])
    time_ms: float = Field(description="The render's time t (the decision epoch), sim ms.",
                           examples=[1260.0])
    truth_time_ms: float = Field(description="Generation time of the ground-truth frame used.",
                                 examples=[1260.0])
    scene_time_ms: float = Field(description="Scene time shown by the ground-truth frame.",
                                 examples=[260.0])
    psnr_db: float = Field(description="PSNR in dB (data range 1; 100 dB for identical images).",
                           examples=[24.3])
    ssim: float = Field(description="Mean SSIM (11x11 Gaussian window, sigma 1.5).",
                        examples=[0.81])
    lpips: float | None = Field(description="LPIPS distance (AlexNet, v0.1); null while LPIPS "
                                            "is unavailable (never 0).", examples=[0.21])
    reward: float | None = Field(description="Weighted sum of the terms in reward_terms; "
                                             "null when lpips_skipped.", examples=[0.891])
    reward_terms: list[str] = Field(description="Metrics the reward was built from (none when "
                                                "lpips_skipped).",
                                    examples=[["psnr", "ssim", "lpips"]])
    lpips_skipped: bool = Field(False, description="LPIPS left out by the sampling "
                                                   "(lpips_per_s): lpips, lpips_display, reward "
                                                   "and reward_display are null.")
    training_step: int = Field(description="Trainer step count when rendered.", examples=[5120])
    n_views: int = Field(description="Frames in the training set when rendered.", examples=[12])
    backend: str = Field(description="Radiance-field backend that rendered.", examples=["grid"])
    lag_ms: float = Field(description="Sim ms between t and the scoring of the render.",
                          examples=[180.0])
    psnr_dynamic_db: float | None = Field(
        description="PSNR in dB over the dynamic region (the pixels whose truth changed over "
                    "the last two generation periods, dilated by 1 px); null when the earlier "
                    "truth frames were missing or nothing moved (never 0).", examples=[17.8])
    ssim_dynamic: float | None = Field(
        description="Mean of the SSIM map over the dynamic region; null likewise.",
        examples=[0.62])
    dynamic_fraction: float | None = Field(
        description="Pixels in the dynamic region / pixels of the image (0 when nothing "
                    "moved); null when the earlier truth frames were missing.",
        examples=[0.148])
    display_time_ms: float | None = Field(
        None, description="Sim time the render was ready (decision time + compute + "
                          "transport): the display scores are against the truth then; null "
                          "when there was no truth frame for it.", examples=[1310.0])
    psnr_display_db: float | None = Field(
        None, description="PSNR in dB against the truth at display time (what a viewer "
                          "sees).", examples=[23.9])
    ssim_display: float | None = Field(None, description="SSIM at display time.",
                                       examples=[0.8])
    lpips_display: float | None = Field(None, description="LPIPS at display time.",
                                        examples=[0.22])
    reward_display: float | None = Field(None, description="Reward at display time.",
                                         examples=[0.87])
    psnr_dynamic_display_db: float | None = Field(
        None, description="Dynamic-region PSNR at display time (the mask of the truth then).",
        examples=[17.1])

    @classmethod
    def of(cls, record: QualityRecord) -> QualityEntry:
        return cls(decision_id=record.decision_id, time_ms=record.time_ms,
                   truth_time_ms=record.truth_time_ms, scene_time_ms=record.scene_time_ms,
                   psnr_db=record.psnr_db, ssim=record.ssim, lpips=record.lpips,
                   reward=record.reward, reward_terms=list(record.reward_terms),
                   training_step=record.training_step, n_views=record.n_views,
                   backend=record.backend, lag_ms=record.lag_ms,
                   psnr_dynamic_db=record.psnr_dynamic_db, ssim_dynamic=record.ssim_dynamic,
                   dynamic_fraction=record.dynamic_fraction,
                   display_time_ms=record.display_time_ms,
                   psnr_display_db=record.psnr_display_db, ssim_display=record.ssim_display,
                   lpips_display=record.lpips_display, reward_display=record.reward_display,
                   psnr_dynamic_display_db=record.psnr_dynamic_display_db,
                   lpips_skipped=record.lpips_skipped)


class QualitySummary(BaseModel):
    """Totals since start and means over the returned history."""

    scored_total: int = Field(description="Renders scored since the service started.",
                              examples=[310])
    rejected_no_truth_total: int = Field(
        description="Renders dropped because no ground-truth frame matched their time.",
        examples=[2])
    window: int = Field(description="Entries the means are taken over (the history returned).",
                        examples=[50])
    lpips_available: bool = Field(description="Whether LPIPS is computed (its weights are "
                                              "cached and the lpips setting is on).",
                                  examples=[True])
    reward_terms: list[str] = Field(description="Metrics the reward is built from now.",
                                    examples=[["psnr", "ssim"]])
    mean_psnr_db: float | None = Field(description="Mean PSNR over the window; null if empty.",
                                       examples=[24.1])
    mean_ssim: float | None = Field(description="Mean SSIM over the window; null if empty.",
                                    examples=[0.8])
    mean_lpips: float | None = Field(
        description="Mean LPIPS over the window's entries that have one; null if none (LPIPS "
                    "unavailable, or every entry lpips_skipped).", examples=[None])
    mean_reward: float | None = Field(description="Mean reward over the window's entries that "
                                                  "have one; null if none.", examples=[0.88])
    lpips_skipped_window: int = Field(0, description="Entries of the window scored without "
                                                     "LPIPS (lpips_skipped).", examples=[35])
    dynamic_window: int = Field(
        description="Entries of the window with a dynamic-region PSNR (the dynamic means are "
                    "taken over these).", examples=[48])
    mean_psnr_dynamic_db: float | None = Field(
        description="Mean dynamic-region PSNR over dynamic_window; null if it is empty.",
        examples=[17.5])
    mean_ssim_dynamic: float | None = Field(
        description="Mean dynamic-region SSIM over dynamic_window; null if it is empty.",
        examples=[0.6])
    mean_dynamic_fraction: float | None = Field(
        description="Mean pixel fraction of the dynamic mask over the window's entries that "
                    "have one; null if none.", examples=[0.15])
    mean_psnr_display_db: float | None = Field(
        None, description="Mean PSNR at display time over the window's entries that have "
                          "one; null if none.", examples=[23.8])
    mean_reward_display: float | None = Field(
        None, description="Mean reward at display time, likewise.", examples=[0.86])
    dynamic_no_history_total: int = Field(
        description="Renders scored since start without a dynamic score because the truth "
                    "frames one and two periods earlier were missing.", examples=[2])
    dynamic_empty_mask_total: int = Field(
        description="Renders scored since start whose dynamic mask was empty (nothing moved).",
        examples=[0])


class QualityResponse(BaseModel):
    summary: QualitySummary
    history: list[QualityEntry] = Field(description="Most recent results, oldest first.")


quality_router = APIRouter(prefix="/quality", tags=["quality"])


@quality_router.get("", summary="Recent quality of the novel view, with a summary.")
def get_quality(
    worker: Metrics,
    limit: Annotated[int, Query(ge=1, le=1_000_000,
                                description="How many of the most recent results to return.")
                     ] = 50,
) -> QualityResponse:
    records = worker.history(limit)
    summary = QualitySummary(
        scored_total=worker.scored_total,
        rejected_no_truth_total=int(worker.rejections.total("no_truth")),
        window=len(records),
        lpips_available=worker.lpips_available,
        reward_terms=list(worker.reward_terms),
        mean_psnr_db=mean_or_none([r.psnr_db for r in records]),
        mean_ssim=mean_or_none([r.ssim for r in records]),
        mean_lpips=mean_of_present([r.lpips for r in records]),
        mean_reward=mean_of_present([r.reward for r in records]),
        lpips_skipped_window=sum(r.lpips_skipped for r in records),
        dynamic_window=sum(r.psnr_dynamic_db is not None for r in records),
        mean_psnr_dynamic_db=mean_of_present([r.psnr_dynamic_db for r in records]),
        mean_ssim_dynamic=mean_of_present([r.ssim_dynamic for r in records]),
        mean_dynamic_fraction=mean_of_present([r.dynamic_fraction for r in records]),
        mean_psnr_display_db=mean_of_present([r.psnr_display_db for r in records]),
        mean_reward_display=mean_of_present([r.reward_display for r in records]),
        dynamic_no_history_total=worker.dynamic_missing("no_history"),
        dynamic_empty_mask_total=worker.dynamic_missing("empty_mask"),
    )
    return QualityResponse(summary=summary, history=[QualityEntry.of(r) for r in records])


class LedgerResponse(BaseModel):
    """The site's decision ledger: every decision seen ends in exactly one state."""

    decisions: int = Field(description="Decisions counted: scored + skipped + lost + open. "
                                       "Every id of a scheduler incarnation up to the highest "
                                       "seen is counted once.", examples=[1200])
    scored: int = Field(description="Rendered, paired with their truth frame and scored.",
                        examples=[150])
    skipped: dict[str, int] = Field(
        description="Skipped by choice, by reason: superseded (a newer decision of the site "
                    "was taken before a worker was free).", examples=[{"superseded": 1040}])
    lost: dict[str, int] = Field(
        description="Lost, by reason: worker_died, timeout, not_delivered, render_failed, "
                    "refused, not_received (from the dispatcher), truth_missing, render_rejected "
                    "(from scoring), "
                    "unseen (never seen: made while this service was down or lost in transit), "
                    "expired (open longer than open_bound_s).",
        examples=[{"worker_died": 1, "unseen": 4}])
    lost_total: int = Field(description="The sum of lost.", examples=[5])
    open: int = Field(description="Seen, not ended yet.", examples=[5])
    oldest_open_s: float | None = Field(
        description="Wall seconds the oldest open decision has waited; null when none.",
        examples=[1.2])
    open_bound_s: float = Field(description="An open decision older than this is counted lost "
                                            "(expired).", examples=[150.0])
    after_close: int = Field(description="Events for a decision that had already ended (a late "
                                         "render, a repeated message).", examples=[0])
    incarnations: int = Field(description="Scheduler incarnations seen.", examples=[1])
    persisted: bool = Field(description="Whether the ledger is saved to the state folder (and "
                                        "so survives a restart of this service).",
                            examples=[True])


ledger_router = APIRouter(prefix="/ledger", tags=["ledger"])


@ledger_router.get("", summary="The decision ledger: how every decision of the site ended.")
def get_ledger(worker: Metrics) -> LedgerResponse:
    s = worker.ledger.summary()
    return LedgerResponse(
        decisions=s.decisions, scored=s.scored, skipped=s.skipped, lost=s.lost,
        lost_total=sum(s.lost.values()), open=s.open, oldest_open_s=s.oldest_open_s,
        open_bound_s=worker.ledger.ledger.open_bound_s, after_close=s.after_close,
        incarnations=s.incarnations, persisted=worker.ledger.path is not None)


def resolve_lpips_fn(settings: Settings, lpips_fn: LpipsFn | None = None) -> LpipsFn | None:
    """The LPIPS function the worker uses: ``lpips_fn`` when given; else, with
    ``settings.lpips`` on, the cached pretrained ``settings.lpips_net`` (None when not cached)."""
    if lpips_fn is not None or not settings.lpips:
        return lpips_fn
    fn = load_lpips_fn(settings.lpips_net)
    if fn is None:
        log.warning("LPIPS unavailable: no %s weights at %s (run `python -m aoi3d.lpips "
                    "fetch`); the reward uses PSNR and SSIM only", settings.lpips_net,
                    weights_path(settings.lpips_net))
    else:
        log.info("LPIPS on (%s, v0.1)", settings.lpips_net)
    return fn


def create_app(settings: Settings | None = None, *, bus: Bus | None = None,
               clock: SimClock | None = None, lpips_fn: LpipsFn | None = None) -> FastAPI:
    """The metrics service; ``bus``/``clock`` default to Zenoh and the shared clock.

    LPIPS: ``lpips_fn`` when given, else the cached pretrained weights when ``settings.lpips``
    is on (loaded when the service starts, see :func:`resolve_lpips_fn`).
    """
    settings = settings or Settings()
    common = settings.common
    clock = clock or SimClock(epoch_s=common.epoch_s, time_scale=common.time_scale)

    lpips: list[LpipsFn | None] = []  # one network for every site, loaded once

    def build_worker(the_bus: Bus, registry, site: str) -> MetricsRuntime:
        if not lpips:
            lpips.append(resolve_lpips_fn(settings, lpips_fn))
        return MetricsRuntime(
            the_bus, registry, run_id=common.run_id, site=site, clock=clock,
            truth_period_ms=settings.truth_period_ms, truth_frames=settings.truth_frames,
            history=settings.history, inbox_size=settings.inbox_size,
            weights=settings.reward_weights(), lpips_fn=lpips[0],
            max_skew_ms=common.skew_ms, stall_s=common.stall_s,
            ledger_open_s=settings.ledger_open_s, state_dir=settings.state_dir,
            truth_wait_s=settings.truth_wait_s, lpips_per_s=settings.lpips_per_s)

    app = service_app(title="aoi3d metrics", description=DESCRIPTION, settings=settings,
                      build_worker=build_worker, bus=bus, per_site=True)
    include_site_routers(app, quality_router, ledger_router)
    return app
