"""The metrics service: render ↔ ground-truth pairing, the Quality messages, /quality, /metrics."""

from __future__ import annotations

import io
import itertools
import math
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

import services.metrics.app as metrics_app
from aoi3d.clock import SimClock
from aoi3d.lpips import LPIPS, load_lpips
from aoi3d.quality import dynamic_mask, dynamic_score, psnr, ssim
from services.kit.codec import (
    PNG,
    decode_image,
    decode_quality,
)
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.settings import CommonSettings
from services.metrics.app import create_app
from services.metrics.core import TruthFrame, TruthRing
from services.metrics.settings import Settings
from tests.support.metrics import value
from tests.support.quality import KEYS, PERIOD_MS, RUN, H, W, noisy, render, truth, truth_image
from tests.support.waits import wait_for


class Harness:
    def __init__(self, client: TestClient, bus: MemoryBus) -> None:
        self.client, self.bus = client, bus

    def qualities(self) -> list[pb.Quality]:
        return [decode_quality(p) for p in self.bus.messages(KEYS.quality)]

    def rejected(self, reason: str) -> float:
        text = self.client.get("/metrics").text
        return value(text, f'aoi3d_messages_rejected_total{{reason="{reason}"}}') or 0.0

    def flush(self) -> pb.Quality:
        """Score a probe render (t = 0, perfect); the thread handles messages in order, so
        everything published before has been handled once its Quality is out."""
        return self.score(0.0, truth_image(0.0), decision_id=424242)

    def score(self, time_ms: float, image: np.ndarray, **kw) -> pb.Quality:
        before = len(self.qualities())
        self.bus.publish(KEYS.render, render(time_ms, image, **kw))
        wait_for(lambda: len(self.qualities()) > before)
        return self.qualities()[-1]


@pytest.fixture
def make_harness() -> Iterator[Callable[..., Harness]]:
    clients: list[TestClient] = []

    def make(*, lpips: bool = False, settings_kw: dict | None = None, **app_kw) -> Harness:
        """The service on a memory bus; LPIPS off unless asked for (``lpips=True`` loads the
        cached weights, ``lpips_fn=`` injects one), so no test depends on the cache."""
        bus = MemoryBus()
        settings = Settings(truth_period_ms=PERIOD_MS, common=CommonSettings(run_id=RUN),
                            lpips=lpips, **(settings_kw or {}))
        app = create_app(settings, bus=bus,
                         clock=SimClock(epoch_s=time.time() - 60.0, time_scale=1.0),
                         **app_kw)
        client = TestClient(app)
        client.__enter__()
        clients.append(client)
        h = Harness(client, bus)
        for gen_ms in (0.0, 30.0, 60.0, 90.0):
            bus.publish(KEYS.truth, truth(gen_ms))
        return h

    yield make
    for client in clients:
        client.__exit__(None, None, None)


# ---------------------------------------------------------------- pairing and the messages
def test_render_is_scored_against_the_truth_of_the_same_time(make_harness) -> None:
    h = make_harness()
    pred = noisy(truth_image(60.0), seed=1)
    q = h.score(60.0, pred, decision_id=11, step=999)
    assert q.truth_time_ms == 60.0 and q.time_ms == 60.0
    assert q.scene_time_ms == 60.0
    assert q.decision_id == 11 and q.training_step == 999

    gt = decode_image(pb.Frame.FromString(truth(60.0)).image)
    got = decode_image(pb.Render.FromString(render(60.0, pred)).image)
    assert q.psnr_db == pytest.approx(psnr(got, gt), abs=1e-9)
    assert q.ssim == pytest.approx(ssim(got, gt), abs=1e-9)
    assert 10.0 < q.psnr_db < 40.0 and 0.0 < q.ssim < 1.0
    # scored against another time's truth the numbers would differ: the pairing matters
    assert abs(psnr(got, decode_image(pb.Frame.FromString(truth(30.0)).image)) - q.psnr_db) > 1
    assert q.reward == pytest.approx(0.02 * q.psnr_db + 0.5 * q.ssim)
    assert list(q.reward_terms) == ["psnr", "ssim"]
    assert not q.HasField("lpips")  # absent, not 0

    exact = h.score(30.0, truth_image(30.0))
    assert exact.truth_time_ms == 30.0 and exact.psnr_db == 100.0 and exact.ssim == 1.0


def test_quality_carries_the_renders_steps_and_ready_time(make_harness) -> None:
    """What the scheduler learns the lag from (issue 40): the render's own training steps and
    the time it was ready; and the scores against the truth at that (display) time."""
    h = make_harness()
    pred = truth_image(60.0)
    q = h.score(60.0, pred, decision_id=12, render_steps=25, ready_ms=95.0)
    assert q.HasField("render_steps") and q.render_steps == 25
    assert q.HasField("ready_ms") and q.ready_ms == 95.0
    assert q.display_time_ms == 95.0 and q.display_truth_time_ms == 90.0
    assert q.psnr_db == 100.0 and q.psnr_display_db < 60.0  # the truth moved by then
    entry = h.client.get("/quality").json()["history"][-1]
    assert entry["decision_id"] == 12 and entry["display_time_ms"] == 95.0
    assert entry["psnr_display_db"] == pytest.approx(q.psnr_display_db)
    # unstamped (an older worker): ready when scored, by the service's clock
    before = time.time()
    q = h.score(90.0, truth_image(90.0), decision_id=13, render_steps=0)
    assert q.HasField("render_steps") and q.render_steps == 0
    now_ms = (time.time() - before) * 1000.0 + 60_000.0  # the clock started 60 s ago
    assert q.HasField("ready_ms") and 60_000.0 <= q.ready_ms <= now_ms + 1000.0


@pytest.mark.parametrize(("time_ms", "truth_ms"), [
    (50.0, 30.0),   # between two truth frames: the newest one at or before t
    (89.9, 60.0),
    (120.0, 90.0),  # exactly one period after the newest: still paired
])
def test_render_without_exact_truth_uses_the_newest_within_a_period(make_harness, time_ms,
                                                                    truth_ms) -> None:
    h = make_harness()
    q = h.score(time_ms, truth_image(truth_ms))
    assert q.time_ms == time_ms and q.truth_time_ms == truth_ms
    assert q.psnr_db == 100.0


def test_render_without_truth_is_rejected_and_counted(make_harness) -> None:
    h = make_harness(settings_kw={"truth_wait_s": 0.0})  # no wait: rejected at once
    h.bus.publish(KEYS.render, render(120.1, truth_image(90.0)))  # newest truth 30.1 ms old
    h.bus.publish(KEYS.render, render(-5.0, truth_image(0.0)))    # before every truth frame
    body = h.client.get("/quality").json()
    assert body["summary"]["mean_psnr_db"] is None and body["history"] == []
    h.flush()
    assert [q.decision_id for q in h.qualities()] == [424242]  # only the probe was scored
    assert h.rejected("no_truth") == 2
    body = h.client.get("/quality").json()
    assert body["summary"]["rejected_no_truth_total"] == 2
    assert body["summary"]["scored_total"] == 1 and len(body["history"]) == 1
    # a truth frame arriving later makes a later render at that time scorable
    h.bus.publish(KEYS.truth, truth(120.0))
    assert h.score(120.1, truth_image(120.0)).truth_time_ms == 120.0


def test_a_render_ahead_of_its_truth_waits_for_it_then_gives_up(make_harness) -> None:
    """A render whose time is past every truth frame received is held (the camera lags) and
    scored when its truth comes; one whose truth never comes is rejected after truth_wait_s.
    A render before every truth frame is not held: its truth will not come."""
    h = make_harness(settings_kw={"truth_wait_s": 1.0})
    h.bus.publish(KEYS.render, render(150.0, truth_image(150.0), decision_id=1))
    h.bus.publish(KEYS.render, render(-5.0, truth_image(0.0), decision_id=2))
    h.flush()
    assert [q.decision_id for q in h.qualities()] == [424242] and h.rejected("no_truth") == 1
    h.bus.publish(KEYS.truth, truth(120.0))  # not yet: 150 is past it and not within a period
    h.bus.publish(KEYS.truth, truth(150.0))
    wait_for(lambda: [q.decision_id for q in h.qualities()] == [424242, 1], timeout_s=10.0)
    assert h.qualities()[-1].truth_time_ms == 150.0 and h.qualities()[-1].psnr_db == 100.0
    h.bus.publish(KEYS.render, render(900.0, truth_image(150.0), decision_id=3))  # never
    wait_for(lambda: h.rejected("no_truth") == 2, timeout_s=10.0)
    assert [q.decision_id for q in h.qualities()] == [424242, 1]


# ---------------------------------------------------------------- the dynamic region
SIDE = 4


def square_scene(col: int, row: int = 7) -> np.ndarray:
    """A static background with a bright SIDE×SIDE square at (row, col), uint8."""
    img = np.full((H, W, 3), 50, np.uint8)
    img[row:row + SIDE, col:col + SIDE] = 200
    return img


def grown(col: int, row: int = 7) -> np.ndarray:
    mask = np.zeros((H, W), bool)
    mask[row - 1:row + SIDE + 1, col - 1:col + SIDE + 1] = True
    return mask


def test_dynamic_region_score_in_quality_rest_and_metrics(make_harness) -> None:
    h = make_harness()
    # The truth at t − 2C, t − C, t: the square moves 7 px a period (t = 360 ms).
    for gen_ms, col in ((300.0, 2), (330.0, 9), (360.0, 16)):
        h.bus.publish(KEYS.truth, truth(gen_ms, image=square_scene(col)))
    mask = grown(2) | grown(9) | grown(16)
    gt = square_scene(16)
    pred = gt.astype(np.int16)
    pred[mask] += 25   # every masked value off by 25 levels: 20·log10(255/25) dB
    pred[~mask] -= 40  # the static part is worse, and must not count
    q = h.score(360.0, pred.astype(np.uint8), decision_id=5)
    assert q.truth_time_ms == 360.0
    assert q.HasField("psnr_dynamic_db") and q.HasField("ssim_dynamic")
    assert q.psnr_dynamic_db == pytest.approx(20 * math.log10(255 / 25), abs=1e-9)
    assert q.dynamic_fraction == pytest.approx(mask.sum() / (W * H)) == 3 * 36 / (W * H)
    assert q.ssim_dynamic == pytest.approx(
        dynamic_score(pred.astype(np.uint8), gt, mask).ssim, abs=1e-9)
    full_mse = (mask.sum() * 25**2 + (~mask).sum() * 40**2) / mask.size / 255**2
    assert q.psnr_db == pytest.approx(10 * math.log10(1 / full_mse), abs=1e-9)
    assert q.reward == pytest.approx(0.02 * q.psnr_db + 0.5 * q.ssim)  # full image only

    body = h.client.get("/quality").json()
    entry = body["history"][-1]
    assert entry["decision_id"] == 5
    assert entry["psnr_dynamic_db"] == pytest.approx(q.psnr_dynamic_db)
    assert entry["ssim_dynamic"] == pytest.approx(q.ssim_dynamic)
    assert entry["dynamic_fraction"] == pytest.approx(q.dynamic_fraction)
    summary = body["summary"]
    assert summary["dynamic_window"] == 1 and summary["window"] == 1
    assert summary["mean_psnr_dynamic_db"] == pytest.approx(q.psnr_dynamic_db)
    assert summary["dynamic_no_history_total"] == 0

    text = h.client.get("/metrics").text
    assert value(text, "aoi3d_render_psnr_dynamic_db") == pytest.approx(q.psnr_dynamic_db)
    assert value(text, "aoi3d_render_ssim_dynamic") == pytest.approx(q.ssim_dynamic)
    assert value(text, "aoi3d_render_dynamic_fraction") == pytest.approx(q.dynamic_fraction)


def test_the_dynamic_reward_setting_scores_the_dynamic_region(make_harness) -> None:
    h = make_harness(settings_kw={"reward_psnr": 0.0, "reward_ssim": 0.0,
                                  "reward_psnr_dynamic": 0.02, "reward_ssim_dynamic": 0.5})
    for gen_ms, col in ((300.0, 2), (330.0, 9), (360.0, 16)):
        h.bus.publish(KEYS.truth, truth(gen_ms, image=square_scene(col)))
    gt = square_scene(16)
    pred = gt.astype(np.int16)
    pred[grown(16)] += 25
    q = h.score(360.0, pred.astype(np.uint8), decision_id=6)
    assert q.reward == pytest.approx(0.02 * q.psnr_dynamic_db + 0.5 * q.ssim_dynamic)
    assert list(q.reward_terms) == ["psnr_dynamic", "ssim_dynamic"]
    assert h.client.get("/quality").json()["summary"]["reward_terms"] == [
        "psnr_dynamic", "ssim_dynamic"]


def test_dynamic_score_without_earlier_truth_is_null_and_counted(make_harness) -> None:
    h = make_harness()  # truth at 0, 30, 60, 90 ms
    for t in (0.0, 30.0):  # t − 2C (and at 0 also t − C) was never generated
        q = h.score(t, noisy(truth_image(t), seed=int(t)))
        assert math.isfinite(q.psnr_db)  # the full-image scores are there
        for name in ("psnr_dynamic_db", "ssim_dynamic", "dynamic_fraction"):
            assert not q.HasField(name), name
    q = h.score(90.0, noisy(truth_image(90.0), seed=2))  # 30 and 60 are there
    assert q.HasField("psnr_dynamic_db") and q.dynamic_fraction > 0
    expected = dynamic_mask(truth_image(90.0), [truth_image(60.0), truth_image(30.0)])
    assert q.dynamic_fraction == pytest.approx(expected.mean())
    body = h.client.get("/quality").json()
    assert [e["psnr_dynamic_db"] is None for e in body["history"]] == [True, True, False]
    assert body["history"][0]["dynamic_fraction"] is None
    summary = body["summary"]
    assert summary["dynamic_no_history_total"] == 2 and summary["dynamic_window"] == 1
    assert summary["mean_psnr_dynamic_db"] == pytest.approx(q.psnr_dynamic_db)
    assert summary["mean_psnr_db"] is not None
    text = h.client.get("/metrics").text
    assert value(text, 'aoi3d_quality_dynamic_missing_total{reason="no_history"}') == 2
    assert value(text, 'aoi3d_quality_dynamic_missing_total{reason="empty_mask"}') == 0
    h.score(0.0, truth_image(0.0))  # the latest render has no dynamic score: NaN, not stale
    assert math.isnan(value(h.client.get("/metrics").text, "aoi3d_render_psnr_dynamic_db"))


def test_static_view_has_an_empty_mask_and_no_dynamic_scores(make_harness) -> None:
    h = make_harness()
    still = square_scene(9)
    for gen_ms in (600.0, 630.0, 660.0):
        h.bus.publish(KEYS.truth, truth(gen_ms, image=still))
    q = h.score(660.0, noisy(still, seed=9))
    assert q.HasField("dynamic_fraction") and q.dynamic_fraction == 0.0
    assert not q.HasField("psnr_dynamic_db") and not q.HasField("ssim_dynamic")
    entry = h.client.get("/quality").json()["history"][-1]
    assert entry["psnr_dynamic_db"] is None and entry["dynamic_fraction"] == 0.0
    assert h.client.get("/quality").json()["summary"]["dynamic_empty_mask_total"] == 1
    assert value(h.client.get("/metrics").text,
                  'aoi3d_quality_dynamic_missing_total{reason="empty_mask"}') == 1


def test_truth_ring_finds_the_frames_one_and_two_periods_before() -> None:
    ring = TruthRing(capacity=8)
    img = pb.Image()
    for gen_ms in (0.0, 31.0, 58.0, 90.0, 200.0):  # jittered generation times
        ring.add(TruthFrame(generation_ms=gen_ms, scene_time_ms=gen_ms, image=img))
    assert [f.generation_ms for f in ring.before(90.0, 30.0, 2)] == [58.0, 31.0]
    assert [f.generation_ms for f in ring.before(58.0, 30.0, 2)] == [31.0, 0.0]
    assert ring.before(200.0, 30.0, 1) is None  # nothing near 170 ms
    assert ring.before(31.0, 30.0, 2) is None   # nothing near −29 ms


def test_truth_ring_keeps_the_newest_frames() -> None:
    ring = TruthRing(capacity=3)
    img = pb.Image()
    for gen_ms in (60.0, 0.0, 30.0, 90.0):  # out of order; 0 is the oldest and is evicted
        ring.add(TruthFrame(generation_ms=gen_ms, scene_time_ms=gen_ms, image=img))
    assert len(ring) == 3
    assert ring.pair(30.0, 30.0).generation_ms == 30.0
    assert ring.pair(30.0 - 1e-9, 30.0).generation_ms == 30.0  # float round-off of t
    assert ring.pair(59.9, 30.0).generation_ms == 30.0
    assert ring.pair(100.0, 30.0).generation_ms == 90.0
    with pytest.raises(ValueError, match="no ground-truth frame generated at t = 10 ms"):
        ring.pair(10.0, 30.0)


# ---------------------------------------------------------------- REST and metrics
def test_quality_history_json_and_gauges(make_harness) -> None:
    h = make_harness()
    scores = [h.score(t, noisy(truth_image(t), seed=i), decision_id=i + 1)
              for i, t in enumerate((0.0, 30.0, 60.0))]
    body = h.client.get("/quality", params={"limit": 2}).json()
    hist = body["history"]
    assert [e["time_ms"] for e in hist] == [30.0, 60.0]  # the 2 most recent, oldest first
    for entry, q in zip(hist, scores[1:], strict=True):
        assert "lpips" in entry and entry["lpips"] is None
        assert entry["reward_terms"] == ["psnr", "ssim"]
        assert entry["psnr_db"] == pytest.approx(q.psnr_db)
        assert entry["decision_id"] == q.decision_id and entry["n_views"] == 5
        assert entry["backend"] == "grid"
    summary = body["summary"]
    assert summary["scored_total"] == 3 and summary["window"] == 2
    assert summary["lpips_available"] is False and summary["mean_lpips"] is None
    assert summary["reward_terms"] == ["psnr", "ssim"]
    assert summary["mean_psnr_db"] == pytest.approx(np.mean([q.psnr_db for q in scores[1:]]))

    assert h.client.get("/quality", params={"limit": 0}).status_code == 422
    assert len(h.client.get("/quality").json()["history"]) == 3

    text = h.client.get("/metrics").text
    assert value(text, "aoi3d_quality_total") == 3
    assert value(text, "aoi3d_render_psnr_db") == pytest.approx(scores[-1].psnr_db)
    assert value(text, "aoi3d_render_ssim") == pytest.approx(scores[-1].ssim)
    assert value(text, "aoi3d_reward") == pytest.approx(scores[-1].reward)
    assert value(text, "aoi3d_truth_frames_total") == 4
    assert "aoi3d_render_lpips" not in text
    assert h.client.get("/readyz").status_code == 200


def test_lpips_when_available_is_published_and_enters_the_reward(make_harness) -> None:
    h = make_harness(lpips_fn=lambda pred, gt: 0.25)
    q = h.score(30.0, noisy(truth_image(30.0), seed=3))
    assert q.HasField("lpips") and q.lpips == 0.25
    assert list(q.reward_terms) == ["psnr", "ssim", "lpips"]
    assert q.reward == pytest.approx(0.02 * q.psnr_db + 0.5 * q.ssim - 0.25)
    entry = h.client.get("/quality").json()["history"][-1]
    assert entry["lpips"] == 0.25 and entry["reward_terms"] == ["psnr", "ssim", "lpips"]
    assert value(h.client.get("/metrics").text, "aoi3d_render_lpips") == 0.25


def test_lpips_sampling_marks_the_renders_it_leaves_out(make_harness) -> None:
    """lpips_per_s: LPIPS (and so the reward) on at most that many renders a wall second; the
    others keep PSNR and SSIM, are marked lpips_skipped, have no reward anywhere (Quality NaN,
    REST null, no gauge or histogram sample) and are counted."""
    calls: list[int] = []

    def lpips_fn(pred, gt) -> float:
        calls.append(1)
        return 0.25

    h = make_harness(lpips_fn=lpips_fn, settings_kw={"lpips_per_s": 0.001})  # 1 per 1000 s
    first = h.score(30.0, noisy(truth_image(30.0), seed=3))
    second = h.score(60.0, noisy(truth_image(60.0), seed=4))
    assert not first.lpips_skipped and first.lpips == 0.25
    assert first.reward == pytest.approx(0.02 * first.psnr_db + 0.5 * first.ssim - 0.25)
    assert second.lpips_skipped and not second.HasField("lpips")
    assert math.isnan(second.reward) and list(second.reward_terms) == []
    assert 10.0 < second.psnr_db < 40.0 and 0.0 < second.ssim < 1.0  # scored all the same
    assert len(calls) == 1  # LPIPS did not run for the second
    doc = h.client.get("/quality").json()
    entry = doc["history"][-1]
    assert entry["lpips_skipped"] and entry["reward"] is None and entry["lpips"] is None
    assert doc["summary"]["lpips_skipped_window"] == 1
    assert doc["summary"]["mean_reward"] == pytest.approx(first.reward)
    assert doc["summary"]["mean_lpips"] == 0.25
    text = h.client.get("/metrics").text
    assert value(text, "aoi3d_quality_lpips_skipped_total") == 1
    assert value(text, "aoi3d_quality_reward_count") == 1
    assert value(text, "aoi3d_reward") == pytest.approx(first.reward)


def test_lpips_sampling_off_scores_every_render(make_harness) -> None:
    h = make_harness(lpips_fn=lambda pred, gt: 0.25, settings_kw={"lpips_per_s": 0})
    qs = [h.score(t, noisy(truth_image(t), seed=int(t))) for t in (30.0, 60.0, 90.0)]
    assert all(q.lpips == 0.25 and not q.lpips_skipped for q in qs)
    assert value(h.client.get("/metrics").text, "aoi3d_quality_lpips_skipped_total") == 0


def test_lpips_setting_loads_the_cached_weights(make_harness, monkeypatch) -> None:
    calls: list[str] = []

    def cached(net: str):
        calls.append(net)
        return lambda pred, gt: 0.125

    monkeypatch.setattr(metrics_app, "load_lpips_fn", cached)
    h = make_harness(lpips=True)
    q = h.score(30.0, noisy(truth_image(30.0), seed=4))
    assert calls == ["alex"]
    assert q.HasField("lpips") and q.lpips == 0.125
    assert list(q.reward_terms) == ["psnr", "ssim", "lpips"]
    assert q.reward == pytest.approx(0.02 * q.psnr_db + 0.5 * q.ssim - 0.125)
    summary = h.client.get("/quality").json()["summary"]
    assert summary["lpips_available"] is True
    assert summary["reward_terms"] == ["psnr", "ssim", "lpips"]
    assert summary["mean_lpips"] == 0.125

    make_harness(lpips=False)
    assert calls == ["alex"]  # switched off: the weights are not even looked for


def test_without_cached_weights_lpips_is_absent_and_the_reward_says_so(make_harness,
                                                                       monkeypatch) -> None:
    monkeypatch.setattr(metrics_app, "load_lpips_fn", lambda net: None)  # nothing cached
    h = make_harness(lpips=True)
    q = h.score(30.0, noisy(truth_image(30.0), seed=5))
    assert not q.HasField("lpips")
    assert list(q.reward_terms) == ["psnr", "ssim"]
    assert q.reward == pytest.approx(0.02 * q.psnr_db + 0.5 * q.ssim)
    summary = h.client.get("/quality").json()["summary"]
    assert summary["lpips_available"] is False and summary["mean_lpips"] is None
    assert summary["reward_terms"] == ["psnr", "ssim"]


def test_images_too_small_for_lpips_are_rejected_as_unscorable(make_harness) -> None:
    model = LPIPS("alex").eval()  # random weights: only the size check matters here
    assert model.min_size > max(W, H)
    h = make_harness(lpips_fn=model.distance)
    h.bus.publish(KEYS.render, render(30.0, truth_image(30.0)))
    h.bus.publish(KEYS.truth, truth(150.0, image=np.zeros((48, 64, 3), np.uint8)))
    q = h.score(150.0, np.full((48, 64, 3), 40, np.uint8))
    assert q.time_ms == 150.0 and q.HasField("lpips")  # the larger pair is scored
    assert h.rejected("unscorable") == 1


def test_pretrained_lpips_is_published_for_real_renders(make_harness) -> None:
    model = load_lpips("alex")
    if model is None:
        pytest.skip("LPIPS alex weights not cached; run `python -m aoi3d.lpips fetch`")
    h = make_harness(lpips_fn=model.distance)
    yy, xx = np.mgrid[0:48, 0:64]
    gt = (np.stack([np.sin(xx / 5.0), np.cos(yy / 6.0), np.sin((xx + yy) / 9.0)], -1) * 100
          + 128).astype(np.uint8)
    h.bus.publish(KEYS.truth, truth(150.0, image=gt))
    pred = noisy(gt, seed=6, sigma=20.0)
    q = h.score(150.0, pred)
    expected = model.distance(decode_image(pb.Render.FromString(render(150.0, pred)).image), gt)
    assert 0.0 < q.lpips == pytest.approx(expected, abs=1e-6)
    assert q.reward == pytest.approx(0.02 * q.psnr_db + 0.5 * q.ssim - q.lpips)
    assert h.score(150.0, gt).lpips == 0.0


def test_bad_messages_are_counted_and_dropped(make_harness) -> None:
    h = make_harness()
    good_render = render(30.0, truth_image(30.0))
    nan_render = pb.Render.FromString(good_render)
    nan_render.time_ms = float("nan")
    for key, payload in (
        (KEYS.truth, b"\xff\xff not a frame"),
        (KEYS.truth, truth(120.0, camera_id=3)),      # not the held-out camera
        (KEYS.render, good_render[: len(good_render) // 2]),
        (KEYS.render, nan_render.SerializeToString()),
        (KEYS.render, render(60.0, np.zeros((12, 20, 3), np.uint8))),  # size differs from truth
    ):
        h.bus.publish(key, payload)
    assert h.flush().psnr_db == 100.0  # the worker is still alive
    assert len(h.qualities()) == 1  # only the probe was scored
    assert h.rejected("unknown_camera") == 1
    assert h.rejected("non_finite") == 1
    assert h.rejected("image_size_mismatch") == 1
    assert h.rejected("malformed") + h.rejected("bad_image") + h.rejected("bad_pose") == 2


def test_decode_quality_rejects_a_dynamic_fraction_outside_0_1() -> None:
    from services.kit.observe import Rejected

    ok = pb.Quality(time_ms=30.0, psnr_dynamic_db=18.0, dynamic_fraction=0.25)
    assert decode_quality(ok.SerializeToString()).dynamic_fraction == 0.25
    for bad in (1.5, -0.1, float("nan")):
        with pytest.raises(Rejected, match="dynamic_fraction"):
            decode_quality(pb.Quality(time_ms=30.0, dynamic_fraction=bad).SerializeToString())


# ---------------------------------------------------------------- hostile senders (issue 11)
def test_truth_frames_from_the_future_cannot_stop_quality(make_harness) -> None:
    """512 truth frames stamped far ahead used to fill the ring and push every real one out:
    Quality stopped until a restart. Now they are rejected (clock_skew) and scoring goes on."""
    h = make_harness()
    for k in range(512):
        h.bus.publish(KEYS.truth, truth(1e9 + 30.0 * k))
    q = h.score(60.0, truth_image(60.0), decision_id=7)
    assert q.truth_time_ms == 60.0 and q.psnr_db == 100.0
    assert h.rejected("clock_skew") == 512
    # a render stamped far ahead is refused too, never paired with a future truth
    h.bus.publish(KEYS.render, render(1e9, truth_image(0.0)))
    h.flush()
    assert h.rejected("clock_skew") == 513


def test_oversized_render_is_rejected_before_decoding(make_harness) -> None:
    h = make_harness()
    big = pb.Render.FromString(render(60.0, truth_image(60.0)))
    buf = io.BytesIO()
    Image.new("RGB", (3000, 3000)).save(buf, format="PNG")
    big.image.CopyFrom(pb.Image(encoding=PNG, width=3000, height=3000, data=buf.getvalue()))
    big.intrinsics.width, big.intrinsics.height = 3000, 3000
    h.bus.publish(KEYS.render, big.SerializeToString())
    h.flush()
    assert h.rejected("too_large") == 1


def test_every_score_goes_into_histograms(make_harness) -> None:
    """A scrape every 5 s sees one render in three through the last-value gauges; the
    histograms count every one (issue 10: Prometheus loses nothing)."""
    h = make_harness()
    scores = [h.score(t, noisy(truth_image(t), seed=i), decision_id=i + 1)
              for i, t in enumerate((0.0, 30.0, 60.0, 90.0))]
    text = h.client.get("/metrics").text
    assert value(text, "aoi3d_quality_psnr_db_count") == 4
    assert value(text, "aoi3d_quality_psnr_db_sum") == pytest.approx(
        sum(q.psnr_db for q in scores))
    assert value(text, "aoi3d_quality_ssim_count") == 4
    assert value(text, "aoi3d_quality_reward_sum") == pytest.approx(sum(q.reward for q in scores))
    assert value(text, "aoi3d_quality_lpips_count") is None  # no LPIPS here: no series


def test_lpips_sampler_keeps_its_rate_and_lets_a_short_burst_through() -> None:
    from services.metrics.sampling import LpipsSampler

    s = LpipsSampler(4.0)
    taken = []
    for i in range(200):  # a render every 50 ms for 10 s
        now = i * 0.05
        if s.due(now):
            s.taken(now)
            taken.append(now)
    assert [round(t, 2) for t in taken[:4]] == [0.0, 0.05, 0.1, 0.15]  # one second's worth
    assert len(taken) <= 4 * 10 + 4 and len([t for t in taken if t >= 5.0]) == 20  # 4 a second
    assert all(b - a >= 0.25 - 1e-9 for a, b in itertools.pairwise(taken[4:]))  # then evenly
    every = LpipsSampler(0.0)
    assert all(every.due(i * 0.001) for i in range(10))
    slow = LpipsSampler(0.5)  # a burst of one, then one every 2 s
    assert slow.due(0.0)
    slow.taken(0.0)
    assert not slow.due(1.9) and slow.due(2.0)
    for bad in (-1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="per_s"):
            LpipsSampler(bad)
