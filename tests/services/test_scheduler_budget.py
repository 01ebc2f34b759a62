"""The budget in the live decision (issue 40): ``PUT /policy`` with ``budget_steps`` (and the
refusals that change nothing), the Decision that carries it, and the lag from a decision to
its display the scheduler learns from the Quality of its own renders (``expected_lag_ms``).
The scheduler runs on a manual clock and the in-memory bus, as in test_scheduler.py."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest
from fastapi.testclient import TestClient

from aoi3d.clock import SimClock
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.settings import CommonSettings
from services.scheduler.app import create_app
from services.scheduler.settings import Settings
from tests.support.scheduler import KEYS, N_CAMERAS, PERIOD_MS, RUN, Harness, ManualWall, frame
from tests.support.waits import settle, wait_for

TIME_SCALE = 0.1
STEP_MS = 3.4  # wall ms per step: the prior slope is 0.34 scene ms per step


@pytest.fixture
def make_harness() -> Iterator[Callable[..., Harness]]:
    clients: list[TestClient] = []

    def make(policy: str = "mat:70") -> Harness:
        wall = ManualWall(10.0)
        bus = MemoryBus()
        settings = Settings(policy=policy, decision_period_ms=PERIOD_MS, step_ms=STEP_MS,
                            common=CommonSettings(run_id=RUN, cameras=N_CAMERAS,
                                                  time_scale=TIME_SCALE))
        client = TestClient(create_app(settings, bus=bus, clock=SimClock(
            epoch_s=0.0, time_scale=1.0, wall=wall)))
        client.__enter__()
        clients.append(client)
        h = Harness(client, bus, wall)
        for cam in range(1, N_CAMERAS + 1):  # every camera known, AoI 30 at t = 60
            h.put(KEYS.edge_frame(cam), frame(cam, 30.0, 40.0))
        return h

    yield make
    for client in clients:
        client.__exit__(None, None, None)


def budget(d: pb.Decision) -> int | None:
    return d.budget_steps if d.HasField("budget_steps") else None


def expected_lag(d: pb.Decision) -> float | None:
    return d.expected_lag_ms if d.HasField("expected_lag_ms") else None


# ---------------------------------------------------------------- PUT /policy with a budget
def test_a_budget_put_with_the_policy_is_shown_and_carried_by_the_next_decision(
        make_harness) -> None:
    h = make_harness("mat:70")
    first = h.decide_at(30.0)
    assert budget(first) is None and h.client.get("/decision").json()["budget_steps"] is None
    assert "budget_steps" not in h.client.get("/policy").json()

    r = h.client.put("/policy", json={"kind": "mat", "mat_ms": 70, "budget_steps": 50})
    assert r.status_code == 200, r.text
    assert r.json()["spec"] == "mat:70@50" and r.json()["budget_steps"] == 50
    got = h.client.get("/policy").json()
    assert (got["kind"], got["mat_ms"], got["budget_steps"], got["spec"]) == ("mat", 70, 50,
                                                                              "mat:70@50")
    d = h.decide_at(60.0)
    assert d.policy == "mat:70@50" and budget(d) == 50
    assert [s.camera_id for s in d.selected] == [1, 2, 3, 4]  # selects as mat:70 does
    assert h.client.get("/decision").json()["budget_steps"] == 50
    # a GET body can be PUT back as it is, budget and all
    assert h.client.put("/policy", json=got).json()["spec"] == "mat:70@50"
    # any kind takes one; a PUT without one goes back to the pool's render_steps
    r = h.client.put("/policy", json={"kind": "freshest", "k": 2, "budget_steps": 25})
    assert r.status_code == 200 and r.json()["spec"] == "freshest:2@25"
    assert budget(h.decide_at(90.0)) == 25
    assert h.client.put("/policy", json={"kind": "all"}).json()["spec"] == "all"
    d = h.decide_at(120.0)
    assert budget(d) is None and h.client.get("/decision").json()["budget_steps"] is None


@pytest.mark.parametrize(("body", "expect"), [
    ({"kind": "mat", "mat_ms": 70, "budget_steps": 0}, "greater than or equal to 1"),
    ({"kind": "mat", "mat_ms": 70, "budget_steps": 100_001}, "less than or equal to 100000"),
    ({"kind": "mat", "mat_ms": 70, "budget_steps": "50"}, "valid integer"),
    ({"kind": "mat", "mat_ms": 70, "budget_steps": True}, "valid integer"),
    ({"kind": "mat", "mat_ms": 70, "budget_steps": 50.5}, "valid integer"),
    ({"kind": "deadline", "mat_ms": 70, "deadline_ms": 100, "budget_steps": 50},
     "deadline chooses each decision's budget itself"),
])
def test_a_refused_budget_is_a_422_that_changes_nothing(make_harness, body, expect) -> None:
    h = make_harness("mat:70")
    assert h.client.put("/policy", json={"kind": "freshest", "k": 3, "budget_steps": 40}
                        ).status_code == 200
    before = h.client.get("/policy").json()
    r = h.client.put("/policy", json=body)
    assert r.status_code == 422, r.text
    assert expect in r.text and "budget" in r.text
    assert h.client.get("/policy").json() == before
    d = h.decide_at(30.0)
    assert d.policy == "freshest:3@40" and budget(d) == 40  # still the one in force


def test_a_deadline_policy_is_put_without_a_budget(make_harness) -> None:
    h = make_harness("mat:70")
    r = h.client.put("/policy", json={"kind": "deadline", "mat_ms": 70, "deadline_ms": 40})
    assert r.status_code == 200, r.text
    assert r.json()["spec"] == "deadline:70:40" and r.json()["deadline_ms"] == 40
    d = h.decide_at(30.0)
    assert budget(d) is None and expected_lag(d) is None  # no lag learned: the pool's budget


# ---------------------------------------------------------------- the lag, from Quality
def quality(h: Harness, decision_id: int, time_ms: float, *, steps: int, lag_ms: float,
            incarnation: int | None = None) -> None:
    worker = h.client.app.state.worker
    h.put(KEYS.quality, pb.Quality(
        decision_id=decision_id, time_ms=time_ms, psnr_db=25.0, ssim=0.8, reward=0.9,
        decision_incarnation=worker.incarnation if incarnation is None else incarnation,
        render_steps=steps, ready_ms=time_ms + lag_ms).SerializeToString())


def test_the_scheduler_learns_the_lag_from_its_own_renders(make_harness) -> None:
    h = make_harness("mat:70")
    worker = h.client.app.state.worker
    d1 = h.decide_at(30.0)
    assert expected_lag(d1) is None
    # renders of decisions of another scheduler process (before a restart): ignored
    for i in range(5):
        quality(h, 100 + i, 30.0, steps=50, lag_ms=500.0, incarnation=worker.incarnation + 1)
    quality(h, 1, 30.0, steps=50, lag_ms=30.0)  # the inbox is handled in order
    wait_for(lambda: len(worker.core.lag) == 1, what="the scheduler's own Quality observed")
    settle(0.05)
    assert len(worker.core.lag) == 1
    d2 = h.decide_at(60.0)
    assert expected_lag(d2) is None  # fewer renders than the estimate needs
    assert h.client.get("/decision").json()["expected_lag_ms"] is None
    quality(h, 1, 30.0, steps=50, lag_ms=28.0)
    quality(h, 2, 60.0, steps=50, lag_ms=32.0)
    # one without the new fields (an older metrics service): nothing learned from it
    h.put(KEYS.quality, pb.Quality(decision_id=2, time_ms=60.0, reward=0.5,
                                   decision_incarnation=worker.incarnation).SerializeToString())
    wait_for(lambda: len(worker.core.lag) == 3, what="three renders observed")
    # one budget seen: the prior slope (3.4 wall ms × 0.1 = 0.34 scene ms per step), the
    # fixed part from the mean: 30 − 0.34·50 = 13
    d3 = h.decide_at(90.0)
    assert budget(d3) is None and expected_lag(d3) == pytest.approx(30.0)
    assert h.client.get("/decision").json()["expected_lag_ms"] == pytest.approx(30.0)
    # the lag at the decision's own budget
    h.client.put("/policy", json={"kind": "mat", "mat_ms": 70, "budget_steps": 100})
    d4 = h.decide_at(120.0)
    assert budget(d4) == 100 and expected_lag(d4) == pytest.approx(13.0 + 0.34 * 100)
    # renders of a second budget: the slope is fitted, the prior forgotten
    for _ in range(3):
        quality(h, 4, 120.0, steps=100, lag_ms=55.0)  # 30 at 50 steps, 55 at 100
    wait_for(lambda: len(worker.core.lag) == 6, what="six renders observed")
    lag = worker.core.lag.estimate()
    assert lag.step_ms == pytest.approx(0.5) and lag.fixed_ms == pytest.approx(5.0)
    assert expected_lag(h.decide_at(150.0)) == pytest.approx(55.0)


def test_dmat_reads_the_learned_lag_live(make_harness) -> None:
    """dmat:70 selects on Δ + L: with L = 30 learned, a camera of AoI 30 is 60 old at display
    (used), one of AoI 60 is 90 old (not used) — mat:70 would use both."""
    h = make_harness("dmat:70")
    worker = h.client.app.state.worker
    h.put(KEYS.edge_frame(1), frame(1, 60.0, 61.0))  # AoI 30 at t = 90, the others 60
    h.decide_at(30.0)
    for _ in range(3):
        quality(h, 1, 30.0, steps=50, lag_ms=30.0)
    wait_for(lambda: len(worker.core.lag) == 3, what="three renders observed")
    d = h.decide_at(90.0)
    assert d.policy == "dmat:70" and expected_lag(d) == pytest.approx(30.0)
    assert [s.camera_id for s in d.selected] == [1]
    # the same ages at the next decision (AoI 30, 60, 60, 60): mat:70 uses them all
    h.put(KEYS.edge_frame(1), frame(1, 90.0, 91.0))
    for cam in (2, 3, 4):
        h.put(KEYS.edge_frame(cam), frame(cam, 60.0, 61.0))
    assert h.client.put("/policy", json={"kind": "mat", "mat_ms": 70}).status_code == 200
    d = h.decide_at(120.0)
    assert [s.aoi_ms for s in d.selected] == [30.0, 60.0, 60.0, 60.0]
    assert expected_lag(d) == pytest.approx(30.0)  # the lag is told, mat is blind to it
