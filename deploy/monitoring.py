"""The aoi3d monitoring, from one source: the Grafana dashboard's panels, the Prometheus
recording rules and the alerts are all written here, and generated from here.

    python deploy/monitoring.py           writes deploy/grafana/dashboards/aoi3d.json and
                                          deploy/prometheus/rules/aoi3d.rules.yml
    python deploy/monitoring.py --check   exits 1 if either file differs from what this
                                          source makes (tests/deploy/test_monitoring.py)

``make monitoring`` runs the first. The dashboard is built with Grafana Labs'
``grafana-foundation-sdk`` (the build for Grafana 11.6's schema; pyproject's dev extra pins
it): its types are generated from Grafana's own schema, where grafanalib's are written by hand
and its last release (0.7.1, January 2024) predates schema 39.

One source means: an expression that a panel and an alert (or a recording rule) both show is
one Python function here, called with the panel's window (``$__rate_interval``) or the
alert's; the dashboard's variables (``$site``, ``$worker``, ``$camera``) are selectors of the
same functions. A query that can be empty on a pipeline at rest (a fixed policy, nothing
learning) says why in its ``empty_at_rest``, and the panel's description carries that reason;
tests/monitoring/test_prometheus_live.py runs every query on a live pipeline and accepts an
empty answer from those queries only.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
DASHBOARD_FILE = ROOT / "deploy" / "grafana" / "dashboards" / "aoi3d.json"
RULES_FILE = ROOT / "deploy" / "prometheus" / "rules" / "aoi3d.rules.yml"
DATASOURCE_UID = "aoi3d-prometheus"
"""The provisioned datasource's uid (deploy/grafana/provisioning/datasources/)."""

# ------------------------------------------------------------------------------ selectors
SITE = 'site=~"$site"'
"""Series of the per-site services (camera, network, scheduler, metrics) and the dispatcher's
per-site series carry ``site``; the pool's and the process-wide ones do not."""
WORKER = 'worker=~"$worker"'
CAMERA = 'camera=~"$camera"'
RATE = "$__rate_interval"

PPO_EMPTY = ("a ppo policy learning online (PUT /policy with learn: true) fills it; empty "
             "with a fixed policy such as the default mat:70")
RIG_EMPTY = ("real cameras (aoi3d up --rig: the ingest in the camera emulator's place) fill "
             "it; empty with the emulated cameras")
GRAPH_EMPTY = ("ROS 2 cameras on rmw_zenoh keys fill it (the ROS graph's liveliness tokens); "
               "empty with the emulated cameras and with zenoh-bridge-ros2dds keys")


def sel(*matchers: str) -> str:
    return "{" + ", ".join(matchers) + "}"


# --------------------------------------------------------- expressions shared with rules
def mean_of(summary: str, window: str, selector: str = "", offset: str = "") -> str:
    """Mean of every observation of a histogram or summary over ``window`` (its sum and
    count), not the last value a scrape happens to see."""
    off = f" offset {offset}" if offset else ""
    return (f"rate({summary}_sum{selector}[{window}]{off}) / "
            f"rate({summary}_count{selector}[{window}]{off})")


def increase_zero(counter: str, window: str) -> str:
    return f"increase({counter}[{window}]) == 0"


def ledger_ended(window: str, state: str | None = None, by: str = "service, site",
                 selector: str = "") -> str:
    inner = [m for m in (f'state="{state}"' if state else "", selector) if m]
    return (f"sum by ({by}) (increase(aoi3d_ledger_decisions_total"
            f"{sel(*inner) if inner else ''}[{window}]))")


def workers_wanted() -> str:
    """Reconstruction workers the pool would need: the workers' summed busy fraction over the
    share of decisions rendered. A pool that renders everything needs what it is busy with; one
    that renders a fraction f of the decisions (the rest superseded while every worker was
    busy) needs 1/f times its busy workers. The autoscaler's signal (deploy/k8s/)."""
    return ("sum without (worker) (aoi3d_pool_worker_busy_ratio) "
            "/ clamp_min(aoi3d_pool_rendered_fraction >= 0, 0.1)")


# ------------------------------------------------------------------- recording rules
@dataclass(frozen=True)
class Record:
    record: str
    expr: str
    comment: str


RECORDS = [
    Record("aoi3d:pool_workers_wanted", workers_wanted(),
           "workers the pool would need (deploy/k8s/: the recon autoscaler's signal)"),
    Record("aoi3d:ledger_lost_share:5m",
           f"{ledger_ended('5m', 'lost')} / {ledger_ended('5m')}",
           "share of the decisions ended in the last 5 minutes that were lost"),
]
RECORDED = {r.record: r for r in RECORDS}

# ----------------------------------------------------------------------------- alerts
ALERTS: list[dict] = [
    dict(alert="AoI3DServiceDown", expr='up{job="aoi3d"} == 0', **{"for": "30s"},
         labels={"severity": "critical"},
         annotations={"summary": "{{ $labels.service }} does not answer /metrics",
                      "description": "Prometheus could not scrape {{ $labels.instance }} for "
                                     "30 s."}),
    # the counter counts every scored render, so a 30 s window misses none between scrapes
    dict(alert="AoI3DNoQuality", expr=increase_zero("aoi3d_quality_total", "30s"),
         **{"for": "0s"}, labels={"severity": "critical"},
         annotations={"summary": "No render was scored for 30 s",
                      "description": "The metrics service published no Quality: no renders, "
                                     "or none with a truth frame of their time."}),
    # the last minute's mean PSNR against the 10 minutes before it (every render counts)
    dict(alert="AoI3DPSNRDrop",
         expr=f"({mean_of('aoi3d_quality_psnr_db', '1m')})\n  < "
              f"({mean_of('aoi3d_quality_psnr_db', '10m', offset='1m')}) - 3",
         **{"for": "1m"}, labels={"severity": "warning"},
         annotations={"summary": "PSNR of the novel view dropped by more than 3 dB",
                      "description": "Mean PSNR over the last minute is {{ $value | printf "
                                     "\"%.1f\" }} dB, over 3 dB below the 10 minutes before."}),
    # cameras selected summed over every decision (a gauge would miss decisions between
    # scrapes)
    dict(alert="AoI3DNoCameraSelected",
         expr=increase_zero("aoi3d_camera_selections_total", "30s"), **{"for": "0s"},
         labels={"severity": "warning"},
         annotations={"summary": "The scheduler selected no camera for 30 s",
                      "description": "No decision of the last 30 s selected a camera (MAT "
                                     "below the smallest AoI, no frame delivered, or no "
                                     "decision at all)."}),
    dict(alert="AoI3DTrainerStalled",
         expr="rate(aoi3d_dispatcher_steps_total[1m]) == 0 and "
              "rate(aoi3d_dispatcher_decisions_total[1m]) > 0",
         **{"for": "30s"}, labels={"severity": "critical"},
         annotations={"summary": "Decisions arrive but the pool renders nothing",
                      "description": "aoi3d_dispatcher_steps_total (the steps of the pool's "
                                     "renders) did not grow for a minute while decisions were "
                                     "taken."}),
    dict(alert="AoI3DPoolEmpty", expr="aoi3d_pool_workers == 0", **{"for": "30s"},
         labels={"severity": "critical"},
         annotations={"summary": "No reconstruction worker in the pool",
                      "description": "The dispatcher sees no worker's liveliness token: "
                                     "decisions are taken but none can be rendered. Start one "
                                     "(python -m services.recon, or docker compose up --scale "
                                     "recon=N)."}),
    dict(alert="AoI3DRejectedMessagesRising",
         expr="sum by (service, reason) (rate(aoi3d_messages_rejected_total[5m])) > 1",
         **{"for": "1m"}, labels={"severity": "warning"},
         annotations={"summary": "{{ $labels.service }} rejects {{ $labels.reason }} messages",
                      "description": "More than one bus message per second rejected ({{ "
                                     "$labels.reason }}) for a minute: a misconfigured or "
                                     "hostile sender."}),
    # real cameras on rmw_zenoh keys: a subscribed topic nobody publishes with the rig's type
    dict(alert="AoI3DCameraTopicUnpublished", expr="aoi3d_ingest_ros_publishers == 0",
         **{"for": "1m"}, labels={"severity": "warning"},
         annotations={"summary": "No publisher of the rig's type on {{ $labels.topic }}",
                      "description": "The ROS graph (rmw_zenoh's liveliness tokens) has had "
                                     "no live publisher of the type the rig file names on "
                                     "{{ $labels.topic }} for a minute: the robot is gone, or "
                                     "publishes another topic or type (GET /status on the "
                                     "ingest lists what is published there)."}),
    # the recorder stopped on a write error (a full disk): the pipeline goes on, unrecorded
    dict(alert="AoI3DRecordingFailed", expr="aoi3d_recorder_failed > 0", **{"for": "0s"},
         labels={"severity": "warning"},
         annotations={"summary": "The recording stopped: {{ $labels.instance }} could not "
                                 "write",
                      "description": "The recorder's latest recording ended on a write error "
                                     "(a full disk); the pipeline runs on unrecorded. GET "
                                     "/status on the recorder says which file, why, and "
                                     "whether it was finished whole (docs/recording.md)."}),
    # the decision ledger: more than 5 % of the decisions that ended in the last 5 minutes
    # were lost, for 2 minutes; skipped-by-choice ones are not losses
    dict(alert="AoI3DDecisionsLost",
         expr=f"{ledger_ended('5m', 'lost')}\n  > 0.05 * {ledger_ended('5m')}",
         **{"for": "2m"}, labels={"severity": "warning"},
         annotations={"summary": "Decisions of {{ $labels.site }} are being lost",
                      "description": "Over 5 % of the decisions that ended in the last 5 "
                                     "minutes were lost (GET /ledger on the metrics service "
                                     "says why: worker_died, timeout, truth_missing, unseen, "
                                     "expired …)."}),
]


# ----------------------------------------------------------------------------- panels
@dataclass(frozen=True)
class Q:
    expr: str
    legend: str = "__auto"
    empty_at_rest: str | None = None
    """Why this query may return nothing on a live pipeline at rest (None: it must not)."""


@dataclass(frozen=True)
class Row:
    title: str


@dataclass(frozen=True)
class Panel:
    kind: str  # "stat" or "timeseries"
    title: str
    targets: list[Q]
    w: int = 12
    h: int = 8
    unit: str | None = None
    min: float | None = None
    max: float | None = None
    description: str = ""
    log_scale: bool = False
    extra: dict = field(default_factory=dict)

    def full_description(self) -> str:
        reasons = sorted({q.empty_at_rest for q in self.targets if q.empty_at_rest})
        if not reasons:
            return self.description
        return (self.description + " Empty at rest: " + "; ".join(reasons) + ".").strip()


S = sel(SITE)
SC = sel(SITE, CAMERA)


def rate(name: str, selector: str = S) -> str:
    return f"rate({name}{selector}[{RATE}])"


def quantiles(histogram: str, qs: tuple[float, ...],
              empty_at_rest: str | None = None) -> list[Q]:
    """The ``qs`` quantiles of a histogram over every series shown, legends p50, p99 …"""
    return [Q(f"histogram_quantile({q}, sum by (le) ({rate(histogram + '_bucket')}))",
              f"p{round(q * 100)}", empty_at_rest=empty_at_rest) for q in qs]


PANELS: list[Row | Panel] = [
    Row("Novel view: quality"),
    Panel("stat", "PSNR", [Q(f"aoi3d_render_psnr_db{S}")], w=3, h=4, unit="dB",
          description="Latest scored render of the held-out camera against its ground truth."),
    Panel("stat", "Dynamic PSNR", [Q(f"aoi3d_render_psnr_dynamic_db{S}")], w=3, h=4, unit="dB",
          description="Latest scored render, PSNR over the dynamic region only: the pixels "
                      "whose ground truth changed by more than 8/255 over the last two frame "
                      "periods, dilated by 1 px (the moving blades). Empty when the render has "
                      "none (earlier truth frames missing, or nothing moved)."),
    Panel("stat", "SSIM", [Q(f"aoi3d_render_ssim{S}")], w=3, h=4, unit="short",
          description="Latest scored render (11×11 Gaussian window, σ = 1.5)."),
    Panel("stat", "Reward", [Q(f"aoi3d_reward{S}")], w=3, h=4, unit="short",
          description="Reward of the latest scored render (weights of the metrics service)."),
    Panel("stat", "Renders scored / min", [Q(f"60 * sum({rate('aoi3d_quality_total')})")],
          w=4, h=4, unit="short",
          description="Rate at which the metrics service scores renders."),
    Panel("stat", "Cameras selected", [Q(f"aoi3d_cameras_selected{S}")], w=4, h=4,
          unit="short",
          description="Training cameras the scheduler selected at its latest decision."),
    Panel("stat", "Services up", [Q('sum(up{job="aoi3d"})')], w=4, h=4, unit="short",
          description="Services whose /metrics Prometheus scraped successfully (of 5)."),
    Panel("timeseries", "PSNR over time: full image and dynamic region",
          [Q(f"aoi3d_render_psnr_db{S}", "{{site}} full image"),
           Q(f"aoi3d_render_psnr_dynamic_db{S}", "{{site}} dynamic region")],
          w=8, h=8, unit="dB",
          description="PSNR of each scored render (dB): over the whole image, and over the "
                      "dynamic region (the pixels that moved over the last two frame periods; "
                      "gaps where a render has none)."),
    Panel("timeseries", "SSIM over time", [Q(f"aoi3d_render_ssim{S}", "{{site}}")], w=8, h=8,
          unit="none", max=1, description="SSIM of each scored render."),
    Panel("timeseries", "Reward over time", [Q(f"aoi3d_reward{S}", "{{site}}")], w=8, h=8,
          unit="none", description="Reward of each scored render."),

    Row("Freshness (AoI) and selection"),
    Panel("timeseries", "AoI per camera", [Q(f"aoi3d_aoi_seconds{SC}", "{{site}} cam {{camera}}")],
          w=16, h=9, unit="s", min=0,
          description="Age of information of each training camera at the latest decision, "
                      "in simulation seconds (cameras that have delivered nothing yet are not "
                      "exported)."),
    Panel("timeseries", "Cameras selected (latest and mean per decision) and training views",
          [Q(f"aoi3d_cameras_selected{S}", "{{site}} selected"),
           Q(f"aoi3d_dispatcher_views{S}", "{{site}} dispatcher views"),
           Q(f"{rate('aoi3d_camera_selections_total')} / {rate('aoi3d_decisions_total')}",
             "{{site}} mean selected per decision")],
          w=8, h=9, unit="none", min=0,
          description="Cameras selected per decision and frames in the dispatcher's current "
                      "training set."),
    Panel("timeseries", "Decisions / s",
          [Q(rate("aoi3d_decisions_total"), "{{site}} decisions"),
           Q(rate("aoi3d_decisions_skipped_total"), "{{site}} skipped")],
          unit="short", min=0,
          description="Decisions published, and decision epochs skipped because the decision "
                      "thread fell behind the clock (per wall second)."),
    Panel("timeseries", "Mean AoI over cameras",
          [Q(f"avg(aoi3d_aoi_seconds{SC})", "mean"), Q(f"max(aoi3d_aoi_seconds{SC})", "max"),
           Q(f"min(aoi3d_aoi_seconds{SC})", "min")],
          unit="s", min=0,
          description="Mean, min and max AoI over the cameras shown (sim seconds)."),

    Row("Camera links (D/G/1/0)"),
    Panel("timeseries", "Frames offered / dropped / delivered",
          [Q(f"sum({rate('aoi3d_frames_offered_total', SC)})", "offered"),
           Q(f"sum({rate('aoi3d_frames_dropped_total', SC)})", "dropped"),
           Q(f"sum({rate('aoi3d_frames_delivered_total', SC)})", "delivered")],
          unit="short", min=0,
          description="Summed over the cameras shown, per wall second. A frame is dropped "
                      "when the camera's previous frame is still in flight."),
    Panel("timeseries", "Drop ratio per camera",
          [Q(f"sum by (site, camera) ({rate('aoi3d_frames_dropped_total', SC)}) / "
             f"sum by (site, camera) ({rate('aoi3d_frames_offered_total', SC)})",
             "{{site}} cam {{camera}}")],
          unit="percentunit", min=0, max=1, description="dropped / offered per camera."),
    Panel("timeseries", "Link delay quantiles",
          [*quantiles("aoi3d_link_delay_seconds", (0.5, 0.9, 0.99)),
           Q(f"sum({rate('aoi3d_link_delay_seconds_sum')}) / "
             f"sum({rate('aoi3d_link_delay_seconds_count')})", "mean")],
          unit="s", min=0,
          description="Delay of delivered frames (delivery − generation), simulation seconds, "
                      "over all links."),
    Panel("timeseries", "Frames generated / ticks skipped",
          [Q(f"sum({rate('aoi3d_frames_generated_total')})", "generated"),
           Q(rate("aoi3d_camera_ticks_skipped_total"), "{{site}} ticks skipped")],
          unit="short", min=0,
          description="Frames the camera rig published per wall second (camera 0 is the "
                      "held-out ground truth) and generation ticks skipped because the loop "
                      "fell behind the clock."),

    Row("Dispatcher: the reconstruction pool"),
    Panel("timeseries", "Training steps / s",
          [Q("aoi3d_dispatcher_steps_per_second", "steps/s (dispatcher)"),
           Q(f"sum({rate('aoi3d_dispatcher_steps_total')})", "steps/s (counter rate)")],
          w=6, unit="short", min=0,
          description="The dispatcher's own estimate (the whole pool) and the rate of its step "
                      "counter (the sites shown)."),
    Panel("timeseries", "Training loss", [Q(f"aoi3d_dispatcher_loss{S}", "{{site}} loss")], w=6,
          unit="none", log_scale=True,
          description="Photometric loss of the latest render's last step (log scale)."),
    Panel("timeseries", "Renders and missing frames / s",
          [Q(rate("aoi3d_renders_total"), "{{site}} renders"),
           Q(rate("aoi3d_dispatcher_decisions_total"), "{{site}} decisions applied"),
           Q(rate("aoi3d_dispatcher_frames_missing_total"), "{{site}} frames missing")],
          w=6, unit="short", min=0,
          description="Novel-view renders published, decisions applied and selected frames "
                      "the dispatcher never received, per wall second."),
    Panel("timeseries", "Render lag",
          quantiles("aoi3d_render_lag_seconds", (0.5, 0.9, 0.99)),
          w=6, unit="s", min=0,
          description="Simulation seconds from a render's decision time t to its scoring by "
                      "the metrics service: how stale the novel view is when it is judged."),
    Panel("timeseries", "Pool: workers, wanted and in flight",
          [Q("aoi3d_pool_workers", "workers"),
           Q("aoi3d:pool_workers_wanted", "wanted (autoscaler signal)"),
           Q("aoi3d_pool_in_flight", "in flight")],
          w=6, unit="none", min=0,
          description="Workers in the pool (liveliness tokens), the workers it would need "
                      "(recording rule aoi3d:pool_workers_wanted: busy fraction summed over "
                      "the workers, over the share of decisions rendered; deploy/k8s scales "
                      "the workers on it) and decisions being reconstructed now."),
    Panel("timeseries", "Pool: renders / s and fraction of decisions rendered",
          [Q("aoi3d_pool_renders_per_second", "renders / s"),
           Q("aoi3d_pool_rendered_fraction", "fraction rendered")],
          w=6, unit="none", min=0,
          description="The pool's renders per wall second and the share of its decisions "
                      "rendered (the rest superseded while every worker was busy, or lost)."),
    Panel("timeseries", "Pool: wait to start and render age",
          [Q(mean_of("aoi3d_pool_wait_seconds", RATE), "wait (decision → worker)"),
           Q(mean_of("aoi3d_pool_render_age_seconds", RATE), "render age"),
           Q(f"aoi3d_render_age_seconds{S}", "{{site}} latest render age")],
          w=6, unit="s", min=0,
          description="Wall seconds from a decision reaching the dispatcher to its hand-out, and "
                      "to its render's report; the latest render's age per site."),
    Panel("timeseries", "Pool: busy fraction per worker, decisions lost",
          [Q(f"aoi3d_pool_worker_busy_ratio{sel(WORKER)}", "{{worker}}"),
           Q(f"sum by (reason) (rate(aoi3d_pool_decisions_lost_total[{RATE}]))",
             "lost: {{reason}}")],
          w=6, unit="none", min=0,
          description="Share of the last 30 s each worker spent reconstructing, and "
                      "handed-out decisions that ended without a render, by reason."),
    Panel("timeseries", "Pool: renders per worker",
          [Q(f"aoi3d_pool_worker_renders{sel(WORKER)}", "{{worker}}")],
          w=24, h=6, unit="short", min=0,
          description="Renders of each live worker since it joined the pool (a worker that "
                      "left is gone from the list)."),

    Row("Health"),
    Panel("timeseries", "Rejected messages by reason",
          [Q(f"sum by (service, reason) (rate(aoi3d_messages_rejected_total[{RATE}]))",
             "{{service}}: {{reason}}")],
          unit="short", min=0,
          description="Messages dropped as invalid (malformed, size mismatch, bad pose, "
                      "unknown camera, no ground truth …) per wall second, every site."),
    Panel("timeseries", "Queue overflows",
          [Q(f"sum by (service) (rate(aoi3d_inbox_dropped_total[{RATE}]))", "{{service}}"),
           Q(rate("aoi3d_network_inbox_overflow_total"), "{{site}} network")],
          unit="short", min=0,
          description="Messages dropped because a worker thread fell behind its inbox."),

    Row("Real cameras (the ROS 2 ingest)"),
    Panel("timeseries", "Frames in, refused and lost per camera",
          [Q(f"sum by (site, camera) ({rate('aoi3d_ingest_frames_total')})",
             "{{site}} {{camera}} published", empty_at_rest=RIG_EMPTY),
           Q(f"sum by (site, camera, reason) ({rate('aoi3d_ingest_rejected_total')})",
             "{{site}} {{camera}} refused: {{reason}}", empty_at_rest=RIG_EMPTY),
           Q(f"sum by (site, camera) ({rate('aoi3d_ingest_frames_lost_total')})",
             "{{site}} {{camera}} lost", empty_at_rest=RIG_EMPTY)],
          w=8, unit="short", min=0,
          description="Per wall second: frames the ingest published to the pipeline, samples "
                      "it refused (by reason: docs/real-cameras.md), and images never "
                      "received (gaps in rmw_zenoh's sequence numbers)."),
    Panel("timeseries", "Age at receipt",
          quantiles("aoi3d_ingest_frame_age_seconds", (0.5, 0.99), RIG_EMPTY),
          w=8, unit="s", min=0,
          description="Receipt at the edge − the image's stamp (wall seconds, after the clock "
                      "offset in force): the real link's delay and the robot's own latency."),
    Panel("timeseries", "Robot clock offset per camera",
          [Q(f"aoi3d_ingest_clock_offset_seconds{S}", "{{site}} {{camera}} measured",
             empty_at_rest=RIG_EMPTY),
           Q(f"aoi3d_ingest_clock_offset_in_force_seconds{S}", "{{site}} {{camera}} in force",
             empty_at_rest=RIG_EMPTY)],
          w=8, unit="s",
          description="Robot clock − edge clock as measured from the samples, and the offset "
                      "subtracted from the stamps (the rig's clock.offset_s: 0, a number, or "
                      "auto)."),
    Panel("timeseries", "ROS publishers per topic",
          [Q(f"aoi3d_ingest_ros_publishers{S}", "{{site}} {{topic}}",
             empty_at_rest=GRAPH_EMPTY)],
          w=24, h=6, unit="short", min=0,
          description="Live publishers of the rig's type on each topic the ingest subscribes "
                      "to, from the ROS graph. Alert AoI3DCameraTopicUnpublished when one has "
                      "none for a minute."),

    Row("Online learning (PPO)"),
    Panel("timeseries", "Episodes learned / min",
          [Q(f"60 * {rate('aoi3d_ppo_episodes_learned_total')}", "{{site}} episodes / min"),
           Q(f"60 * {rate('aoi3d_ppo_updates_total')}", "{{site}} updates / min")],
          w=8, unit="short", min=0,
          description="Decisions whose Quality reward went into an online PPO update, and the "
                      "updates, per minute (a ppo policy PUT with learn: true)."),
    Panel("timeseries", "Online mean reward",
          [Q(f"aoi3d_ppo_mean_reward{S}", "{{site}} mean reward (update batch)",
             empty_at_rest=PPO_EMPTY),
           Q(f"aoi3d_reward{S}", "{{site}} reward (latest render)")],
          w=8, unit="short",
          description="Mean reward of the latest update's batch, next to the reward of the "
                      "latest scored render."),
    Panel("timeseries", "Policy entropy",
          [Q(f"aoi3d_ppo_policy_entropy{S}", "{{site}} entropy (nats)",
             empty_at_rest=PPO_EMPTY)],
          w=8, unit="short", min=0,
          description="Entropy of the learning policy at the latest decision (nats, summed "
                      "over the camera bits); it falls as the policy grows sure."),
    Panel("timeseries", "Rewards: pending, expired, unscored, ignored",
          [Q(f"aoi3d_ppo_pending_rewards{S}", "{{site}} pending"),
           Q(rate("aoi3d_ppo_rewards_expired_total"), "{{site}} expired / s"),
           Q(rate("aoi3d_ppo_decisions_unscored_total"), "{{site}} unscored / s"),
           Q(f"sum by (site, reason) ({rate('aoi3d_ppo_rewards_ignored_total')})",
             "{{site}} ignored / s ({{reason}})",
             empty_at_rest="a reward is ignored only while a ppo policy learns online; before "
                           "the first, the counter has no labelled series")],
          unit="short", min=0,
          description="Learn-mode decisions waiting for their reward; per second: rewards "
                      "that never came (expired), decisions no render represented "
                      "(unscored), Quality messages ignored (by reason)."),
    Panel("timeseries", "PPO update time",
          quantiles("aoi3d_ppo_update_seconds", (0.5, 0.99), PPO_EMPTY),
          unit="s", min=0,
          description="Wall time of one online PPO update (the decision thread acts with its "
                      "own copy of the agent, so updates do not delay decisions)."),

    Row("Every render, and the policy in force"),
    Panel("timeseries", "Mean PSNR over every render",
          [Q(mean_of("aoi3d_quality_psnr_db", RATE, S), "{{site}} PSNR"),
           Q(mean_of("aoi3d_quality_psnr_dynamic_db", RATE, S), "{{site}} dynamic-region PSNR")],
          w=8, unit="dB",
          description="From the histograms (every scored render counts, not the last value a "
                      "scrape happens to see): full image and dynamic region. The alert "
                      "AoI3DPSNRDrop compares the same mean over 1 min with the 10 min "
                      "before."),
    Panel("timeseries", "LPIPS",
          [Q(f"aoi3d_render_lpips{S}", "{{site}} latest"),
           Q(mean_of("aoi3d_quality_lpips", RATE, S), "{{site}} mean")],
          w=8, unit="none",
          description="Lower is better. Latest render and the mean over every render (needs "
                      "the LPIPS weights: `make install` fetches them)."),
    Panel("timeseries", "Mean SSIM and reward over every render",
          [Q(mean_of("aoi3d_quality_ssim", RATE, S), "{{site}} SSIM"),
           Q(mean_of("aoi3d_quality_reward", RATE, S), "{{site}} reward")],
          w=8, unit="none", description="From the histograms."),
    Panel("timeseries", "Policy in force: MAT Γ",
          [Q(f"aoi3d_policy_mat_seconds{S}", "{{site}} Γ"),
           Q(f"aoi3d_policy_info{S}")],
          unit="s",
          description="Γ of the MAT policy in force (empty for other kinds), and "
                      "aoi3d_policy_info, whose labels (kind, spec) name the policy in force."),
    Panel("timeseries", "Mean AoI per camera over time",
          [Q(f"sum by (site, camera) ({rate('aoi3d_decision_aoi_seconds_sum', SC)}) / "
             f"sum by (site, camera) ({rate('aoi3d_decision_aoi_seconds_count', SC)})",
             "{{site}} camera {{camera}}")],
          unit="s",
          description="AoI at every decision averaged over the window (the summary's sum and "
                      "count), not the latest decision's snapshot."),
    Panel("timeseries", "Decision ledger: how decisions end",
          [Q(f"sum by (site, state, reason) ({rate('aoi3d_ledger_decisions_total')})",
             "{{site}} {{state}} {{reason}}")],
          unit="ops",
          description="Decisions ended per second by state and reason (the metrics service's "
                      "ledger, GET /ledger): scored, skipped by choice (superseded), lost with "
                      "a reason."),
    Panel("stat", "Decisions lost (share, 5 min) and open",
          [Q(f"aoi3d:ledger_lost_share:5m{S}", "{{site}} lost share"),
           Q(f"sum(aoi3d_ledger_open{S})", "open")],
          unit="none",
          description="Share of the decisions ended in the last 5 minutes that were lost "
                      "(recording rule aoi3d:ledger_lost_share:5m; alert AoI3DDecisionsLost "
                      "above 5 %), and decisions still open."),
]


@dataclass(frozen=True)
class Variable:
    name: str
    label: str
    metric: str
    """label_values(<metric>, <name>): Grafana asks Prometheus for the label's values."""

    @property
    def query(self) -> str:
        return f"label_values({self.metric}, {self.name})"


VARIABLES = [
    Variable("site", "Site", "aoi3d_dispatcher_decisions_total"),
    Variable("worker", "Worker", "aoi3d_pool_worker_busy_ratio"),
    Variable("camera", "Camera", f"aoi3d_frames_offered_total{S}"),
]


# ---------------------------------------------------------------------------- builders
def dashboard() -> dict:
    """The dashboard as Grafana's JSON model (a dict), built with grafana-foundation-sdk."""
    from grafana_foundation_sdk.builders import dashboard as gd
    from grafana_foundation_sdk.builders import prometheus as gp
    from grafana_foundation_sdk.builders import stat as gs
    from grafana_foundation_sdk.builders import timeseries as gt
    from grafana_foundation_sdk.builders.common import ScaleDistributionConfig
    from grafana_foundation_sdk.cog.encoder import JSONEncoder
    from grafana_foundation_sdk.models.common import ScaleDistribution
    from grafana_foundation_sdk.models.dashboard import (
        DashboardCursorSync,
        DataSourceRef,
        VariableOption,
        VariableRefresh,
        VariableSort,
    )

    ds = DataSourceRef(type_val="prometheus", uid=DATASOURCE_UID)
    board = (gd.Dashboard("aoi3d — live pipeline")
             .uid("aoi3d-live")
             .description("Timeliness–fidelity of the live pipeline: novel-view quality, AoI "
                          "per camera, selection, links, the reconstruction pool, rejected "
                          "input and online PPO learning. Generated by deploy/monitoring.py: "
                          "edit that, not this file.")
             .tags(["aoi3d"]).readonly().tooltip(DashboardCursorSync.CROSSHAIR)
             .refresh("5s").time("now-15m", "now")
             .timepicker(gd.TimePicker().refresh_intervals(["5s", "10s", "30s", "1m", "5m"])))
    for var in VARIABLES:
        board = board.with_variable(
            gd.QueryVariable(var.name).label(var.label).datasource(ds).query(var.query)
            .refresh(VariableRefresh.ON_TIME_RANGE_CHANGED)
            .sort(VariableSort.ALPHABETICAL_ASC).multi(True).include_all(True)
            .all_value(".*")
            .current(VariableOption(selected=True, text=["All"], value=["$__all"])))
    panel_id = 0
    for item in PANELS:
        panel_id += 1
        if isinstance(item, Row):
            board = board.with_row(gd.Row(item.title).id(panel_id))
            continue
        builder = gs.Panel() if item.kind == "stat" else gt.Panel()
        builder = (builder.id(panel_id).title(item.title).datasource(ds)
                   .description(item.full_description()).span(item.w).height(item.h))
        if item.unit:
            builder = builder.unit(item.unit)
        if item.min is not None:
            builder = builder.min(item.min)
        if item.max is not None:
            builder = builder.max(item.max)
        if item.log_scale:
            builder = builder.scale_distribution(
                ScaleDistributionConfig().type(ScaleDistribution.LOG).log(10))
        for i, q in enumerate(item.targets):
            builder = builder.with_target(
                gp.Dataquery().ref_id(chr(ord("A") + i)).datasource(ds).expr(q.expr)
                .legend_format(q.legend).range())
        board = board.with_panel(builder)
    return json.loads(JSONEncoder(sort_keys=True, indent=2).encode(board.build()))


def rules() -> dict:
    """The Prometheus rule file: the recording rules and the alerts."""
    return {"groups": [
        {"name": "aoi3d-recording", "rules": [{"record": r.record, "expr": r.expr}
                                              for r in RECORDS]},
        {"name": "aoi3d", "rules": ALERTS},
    ]}




def _dump_rules() -> str:
    def literal(dumper, value):
        style = "|" if "\n" in value else None
        return dumper.represent_scalar("tag:yaml.org,2002:str", value, style=style)

    class Dumper(yaml.SafeDumper):
        pass

    Dumper.add_representer(str, literal)
    header = ("# Generated by deploy/monitoring.py (make monitoring) from the same source as "
              "the Grafana\n# dashboard: edit that file, not this one. Checked by `promtool "
              "check rules`, unit-tested by\n# `promtool test rules deploy/prometheus/tests/"
              "*.yml` (tests/deploy/test_prometheus_rules.py) and\n# evaluated on a live "
              "pipeline (tests/monitoring/test_prometheus_live.py).\n")
    comments = "".join(f"#   {r.record}: {r.comment}\n" for r in RECORDS)
    return (header + "# Recording rules:\n" + comments
            + yaml.dump(rules(), Dumper=Dumper, sort_keys=False, allow_unicode=True,
                        width=100))


def outputs() -> dict[Path, str]:
    return {DASHBOARD_FILE: json.dumps(dashboard(), indent=2, ensure_ascii=False) + "\n",
            RULES_FILE: _dump_rules()}


def _shown(path: Path) -> str:
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true",
                        help="exit 1 if a generated file differs from what this source makes")
    args = parser.parse_args(argv)
    stale = []
    for path, text in outputs().items():
        if args.check:
            if not path.exists() or path.read_text(encoding="utf-8") != text:
                stale.append(_shown(path))
        else:
            path.write_text(text, encoding="utf-8")
            print(f"wrote {_shown(path)}")
    if stale:
        print(f"stale (run make monitoring): {', '.join(map(str, stale))}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
