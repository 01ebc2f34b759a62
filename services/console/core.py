"""The console's core: what the page shows, from the messages and the services' answers.

No bus, no HTTP client, no threads, no metrics library: the runtime
(:mod:`services.console.runtime`) feeds it decoded-at-the-edge bytes and polled JSON under its
lock, with the wall time; tests drive it directly.

It keeps the latest Render, the truth frame of the same simulated time (a ring by generation
time), every Quality (a timeline of ``history_s``: the scores at the decision's time and at
its display time), the latest Decision (AoI per camera, the frames selected, the policy, its
budget and the scheduler's expected lag), the Γ each decision applied (a timeline too) and
the services' polled state; a policy or channel change puts a marker on the timeline.
:meth:`ConsoleCore.snapshot` is the JSON pushed to the page, with the display summary
(:meth:`ConsoleCore.display`: the measured lag from decision to display, the expected one,
the budget in force).
"""

from __future__ import annotations

import bisect
import functools
import io
import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from aoi3d.channel import parse_channel
from services.kit.codec import decode_decision, decode_frame, decode_quality, decode_render

__all__ = ["GAMMA_EVERY_S", "LAG_RENDERS", "TRUTH_FRAMES", "ConsoleCore", "Pair"]

TRUTH_FRAMES = 256
"""Truth frames kept to pair a render with the truth of its own time."""

GAMMA_EVERY_S = 0.25
"""The Γ series keeps a decision's Γ when it changed, else one every this many seconds."""

LAG_RENDERS = 20
"""The display lag shown is the median over this many of the newest scored renders."""


@dataclass(frozen=True)
class Pair:
    """The latest render and the truth frame of the same simulated time (PNG bytes)."""

    render_png: bytes
    truth_png: bytes | None
    decision_id: int
    render_time_ms: float
    truth_time_ms: float | None
    training_step: int
    n_views: int
    carry: str
    received_wall_s: float


class ConsoleCore:
    """One site's view. Not thread-safe: the runtime serialises calls. Every ``on_*`` raises
    :class:`services.kit.observe.Rejected` for a malformed message and changes nothing then.
    """

    def __init__(self, *, period_ms: float = 30.0, history_s: float = 300.0) -> None:
        self._period_ms = period_ms
        self._history_s = history_s
        self._truth_times: list[float] = []
        self._truth: dict[float, bytes] = {}
        self.pair: Pair | None = None
        self._diff: tuple[int, bytes] | None = None
        self._quality: deque[dict[str, Any]] = deque()
        self._markers: deque[dict[str, Any]] = deque()
        self._decision: dict[str, Any] | None = None
        # Γ in force per decision (an adaptive policy's moves with the channel), thinned to
        # one point per GAMMA_EVERY_S unless it changed: its own series on the page, apart
        # from the channel's
        self._gamma: deque[dict[str, Any]] = deque()
        self._status: dict[str, Any] = {}
        self._channel_prev: tuple[float, int, int] | None = None  # wall, delivered, offered
        self._last_policy: str | None = None
        self._last_channel: str | None = None
        self._last_in_force: str | None = None
        # the channel over time: {wall_s, measured_delay_ms, in_force, in_force_mean_ms}
        self._channel_series: deque[dict[str, Any]] = deque()

    # ------------------------------------------------------------------ the messages
    def on_truth(self, payload: bytes) -> None:
        frame = decode_frame(payload, camera_ids={0})
        t = frame.generation_ms
        if t not in self._truth:
            bisect.insort(self._truth_times, t)
        self._truth[t] = frame.image.data
        while len(self._truth_times) > TRUTH_FRAMES:
            self._truth.pop(self._truth_times.pop(0), None)

    def truth_at(self, t_ms: float) -> tuple[float, bytes] | None:
        """The truth frame generated at ``t_ms``, else the newest at most one period older."""
        i = bisect.bisect_right(self._truth_times, t_ms + 1e-6)
        if i == 0:
            return None
        t = self._truth_times[i - 1]
        return (t, self._truth[t]) if t_ms - t <= self._period_ms + 1e-6 else None

    def on_render(self, payload: bytes, now: float) -> None:
        msg, _camera = decode_render(payload)
        truth = self.truth_at(msg.time_ms)
        self.pair = Pair(render_png=msg.image.data,
                         truth_png=None if truth is None else truth[1],
                         decision_id=msg.decision_id, render_time_ms=msg.time_ms,
                         truth_time_ms=None if truth is None else truth[0],
                         training_step=msg.training_step, n_views=msg.n_views,
                         carry=msg.carry, received_wall_s=now)

    def on_quality(self, payload: bytes, now: float) -> None:
        q = decode_quality(payload)
        # when the render was on screen: its ready time (the display scores' time), absent
        # from an older metrics service
        shown = (q.ready_ms if q.HasField("ready_ms") else
                 q.display_time_ms if q.HasField("psnr_display_db") else None)
        entry = {"wall_s": now, "time_ms": q.time_ms, "psnr_db": q.psnr_db,
                 "ssim": q.ssim, "reward": q.reward,
                 "lpips": q.lpips if q.HasField("lpips") else None,
                 "psnr_dynamic_db": q.psnr_dynamic_db if q.HasField("psnr_dynamic_db")
                 else None,
                 "psnr_display_db": q.psnr_display_db if q.HasField("psnr_display_db")
                 else None,
                 "display_lag_ms": None if shown is None else shown - q.time_ms,
                 "render_steps": q.render_steps if q.HasField("render_steps") else None}
        self._quality.append({k: _finite(v) for k, v in entry.items()})
        self.trim(now)

    def on_decision(self, payload: bytes, now: float) -> None:
        d = decode_decision(payload)
        selected = sorted(int(r.camera_id) for r in d.selected)
        self._decision = {"decision_id": d.decision_id, "time_ms": d.time_ms,
                          "policy": d.policy, "camera_ids": list(d.camera_ids),
                          "aoi_ms": [_finite(a) for a in d.aoi_ms], "selected": selected}
        gamma = d.gamma_ms if d.HasField("gamma_ms") else None
        self._decision["gamma_ms"] = gamma
        self._decision["budget_steps"] = d.budget_steps if d.HasField("budget_steps") else None
        self._decision["expected_lag_ms"] = _finite(d.expected_lag_ms) if d.HasField(
            "expected_lag_ms") else None
        last = self._gamma[-1] if self._gamma else None
        if (last is None or last["gamma_ms"] != gamma
                or now - last["wall_s"] >= GAMMA_EVERY_S):
            self._gamma.append({"wall_s": now, "time_ms": d.time_ms, "gamma_ms": gamma,
                                "policy": d.policy})
            self.trim(now)
        if d.policy != self._last_policy:
            if self._last_policy is not None:
                self._markers.append({"wall_s": now, "text": f"policy {d.policy}"})
            self._last_policy = d.policy

    def trim(self, now: float) -> None:
        for q in (self._quality, self._markers, self._gamma, self._channel_series):
            while q and q[0]["wall_s"] < now - self._history_s:
                q.popleft()

    # ------------------------------------------------------------------ the services
    def on_status(self, status: dict[str, Any], now: float) -> None:
        """The services' answers of one poll (``channel``, ``dispatcher``, ``policy``, ``ledger``:
        JSON, or ``{"error": …}`` for a service that did not answer)."""
        self._status = {**status, "channel_summary": self._channel(status.get("channel") or {},
                                                                   now)}
        self.trim(now)

    def _channel(self, channel: dict[str, Any], now: float) -> dict[str, Any] | None:
        """Delivered/s and drop ratio since the previous poll; the configured delay's
        quantiles."""
        links = channel.get("links")
        if not links:
            return None
        delivered = sum(link["delivered"] for link in links)
        offered = sum(link["offered"] for link in links)
        dropped = sum(link["dropped"] for link in links)
        out: dict[str, Any] = {"delay": channel.get("delay"), "delivered_total": delivered,
                               "drop_ratio_total": dropped / offered if offered else None}
        if self._channel_prev is not None:
            t0, d0, o0 = self._channel_prev
            dt = now - t0
            if dt > 0 and offered >= o0:
                out["delivered_per_s"] = (delivered - d0) / dt
                out["drop_ratio"] = (1 - (delivered - d0) / (offered - o0)
                                     if offered > o0 else None)
        self._channel_prev = (now, delivered, offered)
        spec = str(channel.get("in_force") or channel.get("delay"))
        try:
            dist = parse_channel(spec).stationary
            out["delay_quantiles_ms"] = (None if dist is None else
                                         {q: dist.ppf(float(q)) for q in ("0.5", "0.9", "0.99")})
        except ValueError:
            out["delay_quantiles_ms"] = None
        configured = str(channel.get("delay"))
        in_force = str(channel.get("in_force") or configured)
        if configured != self._last_channel:
            if self._last_channel is not None:
                self._markers.append({"wall_s": now, "text": f"delay {configured}",
                                      "kind": "channel"})
            self._last_channel = configured
            self._last_in_force = in_force
        elif in_force != self._last_in_force:  # the next regime of a schedule
            self._markers.append({"wall_s": now, "text": f"channel {in_force}",
                                  "kind": "channel"})
            self._last_in_force = in_force
        in_force_mean = _mean_ms(in_force)
        measured = channel.get("measured_delay_ms")
        out["in_force"] = in_force
        out["in_force_mean_ms"] = _finite(in_force_mean)
        out["measured_delay_ms"] = _finite(measured)
        self._channel_series.append({"wall_s": now, "in_force": in_force,
                                     "in_force_mean_ms": _finite(in_force_mean),
                                     "measured_delay_ms": _finite(measured)})
        return out

    # ------------------------------------------------------------------ for the page
    def diff_png(self) -> bytes | None:
        """|render − truth| averaged over the channels, as a heat map (black → red → yellow
        → white), for the latest pair; cached per render."""
        pair = self.pair
        if pair is None or pair.truth_png is None:
            return None
        if self._diff is not None and self._diff[0] == pair.decision_id:
            return self._diff[1]
        png = heat_map_png(pair.render_png, pair.truth_png)
        if png is not None:
            self._diff = (pair.decision_id, png)
        return png

    def display(self) -> dict[str, Any]:
        """What the viewer sees, and when: the median lag from decision to display over the
        newest :data:`LAG_RENDERS` scored renders (``display_lag_ms``, and how many it is
        of), the scheduler's expected lag of the latest decision, the newest display-time
        and decision-time PSNR, and the budget in force — the latest decision's
        (``budget_source`` ``decision``), else the dispatcher's ``render_steps``
        (``dispatcher``)."""
        recent = list(self._quality)[-LAG_RENDERS:]
        lags = [q["display_lag_ms"] for q in recent if q.get("display_lag_ms") is not None]
        d = self._decision or {}
        dispatcher = self._status.get("dispatcher") or {}
        budget, source = d.get("budget_steps"), "decision"
        if budget is None:
            budget, source = dispatcher.get("render_steps"), "dispatcher"
        last = recent[-1] if recent else {}
        return {"display_lag_ms": float(np.median(lags)) if lags else None,
                "display_lag_n": len(lags),
                "expected_lag_ms": d.get("expected_lag_ms"),
                "psnr_db": last.get("psnr_db"), "psnr_display_db": last.get("psnr_display_db"),
                "budget_steps": budget, "budget_source": None if budget is None else source}

    def snapshot(self, now: float) -> dict[str, Any]:
        pair = self.pair
        return {
            "wall_s": now,
            "render": None if pair is None else {
                "decision_id": pair.decision_id, "time_ms": pair.render_time_ms,
                "truth_time_ms": pair.truth_time_ms, "training_step": pair.training_step,
                "n_views": pair.n_views, "carry": pair.carry,
                "age_s": now - pair.received_wall_s},
            "decision": self._decision,
            "quality": list(self._quality),
            "gamma": list(self._gamma),
            "markers": list(self._markers),
            "channel_series": list(self._channel_series),
            "display": self.display(),
            **self._status,
        }


def heat_map_png(render_png: bytes, truth_png: bytes) -> bytes | None:
    """|a − b| of two PNGs as a heat map PNG; None when their sizes differ."""
    from PIL import Image

    a = np.asarray(Image.open(io.BytesIO(render_png)).convert("RGB"), np.float32)
    b = np.asarray(Image.open(io.BytesIO(truth_png)).convert("RGB"), np.float32)
    if a.shape != b.shape:
        return None
    e = np.clip(np.abs(a - b).mean(axis=2) / 128.0, 0.0, 1.0)
    heat = np.stack([np.clip(3 * e, 0, 1), np.clip(3 * e - 1, 0, 1),
                     np.clip(3 * e - 2, 0, 1)], axis=2)
    buf = io.BytesIO()
    Image.fromarray((heat * 255).astype(np.uint8), "RGB").save(buf, format="PNG")
    return buf.getvalue()


@functools.lru_cache(maxsize=64)
def _mean_ms(spec: str) -> float | None:
    """The mean transmission time of a spec in force; None for a trace (it depends on the
    frames' sizes: the measured delay is the one to read)."""
    try:
        channel = parse_channel(spec)
        return None if channel.size_dependent else float(channel.mean_ms)
    except (ValueError, OSError):
        return None


def _finite(value: Any) -> Any:
    """NaN and infinities as None: JSON has no such numbers."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
