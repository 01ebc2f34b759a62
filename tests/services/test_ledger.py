"""The decision ledger live in the metrics service (one MemoryBus, the real runtime): each
state and lost reason reaches GET /ledger and /metrics, an open decision expires, nonsense is
refused and counted, and the ledger survives a restart of the service (its state folder).
The dispatcher's side — an Outcome for each decision that ends without a render — is in
tests/services/test_dispatcher.py and tests/unit/domain/test_pool.py."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from aoi3d.clock import SimClock
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.reasons import EndReason
from services.kit.settings import CommonSettings
from services.metrics.app import create_app
from services.metrics.ledger import LOST_REASONS
from services.metrics.settings import Settings
from tests.support.metrics import value
from tests.support.quality import KEYS, PERIOD_MS, RUN, noisy, render, truth, truth_image
from tests.support.waits import wait_for

INC = 99


class Site:
    def __init__(self, state_dir: Path | None, open_s: float = 60.0) -> None:
        self.bus = MemoryBus()
        settings = Settings(truth_period_ms=PERIOD_MS, common=CommonSettings(run_id=RUN),
                            lpips=False, ledger_open_s=open_s, state_dir=state_dir,
                            truth_wait_s=0.5)
        self.client = TestClient(create_app(settings, bus=self.bus, clock=SimClock(
            epoch_s=time.time() - 60.0, time_scale=1.0)))
        self.client.__enter__()
        for gen_ms in (0.0, 30.0, 60.0, 90.0):
            self.bus.publish(KEYS.truth, truth(gen_ms))

    def close(self) -> None:
        self.client.__exit__(None, None, None)

    def decide(self, *ids: int, inc: int = INC) -> None:
        for i in ids:
            self.bus.publish(KEYS.decision, pb.Decision(
                decision_id=i, incarnation=inc, time_ms=60.0, policy="all").SerializeToString())

    def outcome(self, i: int, state: str, reason: str | int, inc: int = INC) -> None:
        """``reason``: a label, or a raw enum number (one the proto does not have)."""
        self.bus.publish(KEYS.outcome, pb.Outcome(
            decision_id=i, incarnation=inc, site="site1", state=state,
            reason=reason if isinstance(reason, int) else EndReason(reason).wire
        ).SerializeToString())

    def render(self, i: int, time_ms: float = 60.0, image=None) -> None:
        msg = pb.Render.FromString(render(time_ms, noisy(truth_image(60.0), seed=i)
                                          if image is None else image, decision_id=i))
        msg.decision_incarnation = INC
        self.bus.publish(KEYS.render, msg.SerializeToString())

    def ledger(self) -> dict:
        r = self.client.get("/ledger")
        assert r.status_code == 200, r.text
        return r.json()

    def settle(self, decisions: int) -> dict:
        wait_for(lambda: self.ledger()["decisions"] >= decisions and self.ledger()["open"] == 0,
                 timeout_s=10.0)
        return self.ledger()


@pytest.fixture
def sites() -> Iterator[list]:
    made: list[Site] = []
    yield made
    for s in made:
        s.close()


def test_each_state_and_reason_reaches_rest_and_prometheus(sites, tmp_path: Path) -> None:
    site = Site(None)
    sites.append(site)
    site.decide(1, 2, 3, 4, 5, 6, 7, 8, 10, 11, 12)  # 9 never arrives: unseen
    site.render(1)  # scored
    site.outcome(2, "skipped", "superseded")
    for i, reason in zip((3, 4, 5, 6, 7, 12), ("worker_died", "timeout", "not_delivered",
                                              "render_failed", "refused", "not_received"),
                         strict=True):
        site.outcome(i, "lost", reason)
    site.render(8, time_ms=5000.0)  # no truth frame of its time: truth_missing
    site.render(10, image=truth_image(60.0)[:9])  # another size: render_rejected
    site.render(11)  # scored
    got = site.settle(12)
    assert got["scored"] == 2 and got["skipped"] == {"superseded": 1}
    for reason in ("worker_died", "timeout", "not_delivered", "render_failed", "refused",
                   "not_received", "truth_missing", "render_rejected", "unseen"):
        assert got["lost"][reason] == 1, (reason, got)
    assert got["lost"]["expired"] == 0 and got["lost_total"] == 9
    assert got["decisions"] == 12 and not got["persisted"]
    text = site.client.get("/metrics").text
    for reason in LOST_REASONS:  # every reason is a series from the start
        assert value(text, f'aoi3d_ledger_decisions_total{{reason="{reason}",state="lost"}}'
                      ) == got["lost"][reason]
    assert value(text, 'aoi3d_ledger_decisions_total{reason="",state="scored"}') == 2
    assert value(text, "aoi3d_ledger_open") == 0
    # the same under the site's own path
    assert site.client.get("/sites/site1/ledger").json()["decisions"] == 12


def test_an_open_decision_expires_and_nonsense_is_counted_not_believed(sites) -> None:
    site = Site(None, open_s=0.5)
    sites.append(site)
    site.decide(1)
    wait_for(lambda: site.ledger()["lost"]["expired"] == 1, timeout_s=5.0)
    site.decide(10**12)  # would skip a trillion ids
    site.bus.publish(KEYS.outcome, b"\xff\x00junk")
    site.outcome(1, "lost", 99)  # no such EndReason
    wait_for(lambda: "implausible_decision_id" in site.client.get("/metrics").text,
             timeout_s=10.0)
    got = site.ledger()
    assert got["decisions"] == 1 and got["lost"]["expired"] == 1 and got["after_close"] == 0
    text = site.client.get("/metrics").text
    assert value(text, 'aoi3d_messages_rejected_total{reason="malformed"}') == 2


def test_the_ledger_survives_a_restart_of_the_service(sites, tmp_path: Path) -> None:
    first = Site(tmp_path)
    sites.append(first)
    first.decide(1, 2, 3)
    first.render(1)
    first.outcome(2, "skipped", "superseded")
    wait_for(lambda: first.ledger()["scored"] == 1 and first.ledger()["skipped"]["superseded"],
             timeout_s=10.0)
    assert first.ledger()["persisted"]
    first.close()
    sites.remove(first)
    saved = tmp_path / f"ledger-{RUN}-site1.json"
    assert saved.exists()

    second = Site(tmp_path)  # decisions 4 and 5 were made while it was down
    sites.append(second)
    assert second.ledger()["decisions"] == 3 and second.ledger()["open"] == 1
    second.outcome(3, "lost", "timeout")  # still open across the restart: closed now
    second.decide(6)
    second.render(6)
    got = second.settle(6)
    assert (got["scored"], got["skipped"]["superseded"], got["lost"]["timeout"],
            got["lost"]["unseen"], got["decisions"]) == (2, 1, 1, 2, 6)
