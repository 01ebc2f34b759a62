"""The metrics service's core on its own: truth frames and renders in, Quality out (no bus,
no server, no thread)."""

from __future__ import annotations

import math

import pytest

from services.kit.observe import Rejected
from services.metrics.core import MetricsCore
from tests.support.quality import noisy, render, truth, truth_image


def test_a_render_is_scored_against_the_truth_of_its_time_with_the_dynamic_region() -> None:
    core = MetricsCore(truth_period_ms=30.0, site="north")
    for t in (0.0, 30.0, 60.0):
        core.on_truth(truth(t), now_ms=t)
    scored = core.score(render(60.0, noisy(truth_image(60.0), seed=1)), now_ms=65.0)
    q = scored.message
    assert (q.decision_id, q.time_ms, q.truth_time_ms, q.site) == (7, 60.0, 60.0, "north")
    assert 10 < q.psnr_db < 60 and 0 < q.ssim <= 1 and not q.HasField("lpips")
    assert list(q.reward_terms) == ["psnr", "ssim"]
    assert scored.record.lag_ms == 5.0 and scored.record.psnr_db == q.psnr_db
    assert q.HasField("dynamic_fraction")  # two earlier truth frames were there
    assert (scored.dynamic_missing is None) == q.HasField("psnr_dynamic_db")


def test_without_earlier_truth_the_dynamic_scores_are_absent_and_say_why() -> None:
    core = MetricsCore(truth_period_ms=30.0)
    core.on_truth(truth(90.0), now_ms=90.0)
    scored = core.score(render(100.0, truth_image(90.0)), now_ms=100.0)
    assert scored.message.truth_time_ms == 90.0  # the newest within a period before t
    assert scored.dynamic_missing == "no_history"
    assert not scored.message.HasField("dynamic_fraction")
    assert math.isinf(scored.message.psnr_db) or scored.message.psnr_db > 40


@pytest.mark.parametrize(("setup", "payload", "reason"), [
    ((), lambda: render(100.0, truth_image(100.0)), "no_truth"),
    ((0.0,), lambda: render(1e9, truth_image(0.0)), "clock_skew"),
    ((0.0,), lambda: b"\xff\x00", "malformed"),
])
def test_renders_that_cannot_be_scored_are_rejected_with_their_reason(setup, payload,
                                                                      reason) -> None:
    core = MetricsCore(truth_period_ms=30.0, max_skew_ms=50.0)
    for t in setup:
        core.on_truth(truth(t), now_ms=t)
    with pytest.raises(Rejected) as err:
        core.score(payload(), now_ms=100.0)
    assert err.value.reason == reason
    with pytest.raises(Rejected):
        core.on_truth(truth(10_000.0), now_ms=100.0)  # from the future


def test_a_render_is_also_scored_against_the_truth_when_it_is_ready() -> None:
    from services.kit.pb import aoi3d_pb2 as pb

    core = MetricsCore(truth_period_ms=30.0)
    for t in (0.0, 30.0, 60.0, 90.0, 120.0):
        core.on_truth(truth(t), now_ms=t)
    # a render of the truth at 60 that was ready at 95: at display, the truth of 90 stands
    msg = pb.Render.FromString(render(60.0, truth_image(60.0)))
    msg.ready_ms = 95.0
    scored = core.score(msg.SerializeToString(), now_ms=130.0)
    q, rec = scored.message, scored.record
    assert q.psnr_db > 40  # exact at its decision time
    assert (q.display_time_ms, q.display_truth_time_ms) == (95.0, 90.0)
    assert q.HasField("psnr_display_db") and q.psnr_display_db < q.psnr_db - 5
    assert rec.psnr_display_db == q.psnr_display_db and rec.display_time_ms == 95.0
    assert q.HasField("psnr_dynamic_display_db")  # the truth of 30 and 60 were there
    # unstamped: the time it is scored is its display time
    scored = core.score(render(60.0, truth_image(60.0)), now_ms=61.0)
    assert scored.message.display_time_ms == 61.0
    assert scored.message.display_truth_time_ms == 60.0
    assert scored.message.psnr_display_db == scored.message.psnr_db
    # no truth in [display − C, display]: the display scores are absent, the rest is there
    late = pb.Render.FromString(render(60.0, truth_image(60.0)))
    late.ready_ms = 500.0
    scored = core.score(late.SerializeToString(), now_ms=501.0)
    assert not scored.message.HasField("psnr_display_db")
    assert scored.record.psnr_display_db is None and scored.message.psnr_db > 40
