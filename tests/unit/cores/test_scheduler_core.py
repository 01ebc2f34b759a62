"""The scheduler's core on its own: no bus, no server, no threads."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aoi3d.policy import parse_policy
from services.kit.observe import Rejected
from services.scheduler.core import MAX_AHEAD_MS, SchedulerCore
from tests.support.scheduler import frame


def test_a_frame_counts_only_from_its_delivery_time() -> None:
    core = SchedulerCore(3, incarnation=7)
    core.ingest(frame(1, 0.0, delivery_ms=50.0), now_ms=10.0)  # reached us early
    core.ingest(frame(2, 0.0, delivery_ms=20.0), now_ms=10.0)
    d = core.decide(30.0, parse_policy("all"))
    assert [r.camera_id for r in d.selected] == [2]  # camera 1 is not delivered by 30
    assert d.aoi_ms[0] != d.aoi_ms[0] and d.aoi_ms[1] == 30.0  # NaN: unknown, never 0
    d = core.decide(60.0, parse_policy("all"))
    assert [r.camera_id for r in d.selected] == [1, 2] and d.decision_id == 2
    assert d.incarnation == 7 and core.cameras_known == 2


def test_mat_selects_by_age_and_the_newest_frame_of_each_camera() -> None:
    core = SchedulerCore(2)
    core.ingest(frame(1, 0.0, 10.0), now_ms=10.0)
    core.ingest(frame(1, 30.0, 40.0, sequence=1), now_ms=40.0)
    core.ingest(frame(2, 0.0, 90.0), now_ms=90.0)
    d = core.decide(100.0, parse_policy("mat:80"))
    assert [(r.camera_id, r.generation_ms, r.sequence) for r in d.selected] == [(1, 30.0, 1)]
    assert d.policy == "mat:80" and d.time_ms == 100.0
    snap = core.aoi(100.0)
    assert snap.aoi_ms.tolist() == [70.0, 100.0] and snap.camera_ids == (1, 2)


def test_a_waiting_policy_is_stamped_at_its_evaluation_time() -> None:
    core = SchedulerCore(1)
    core.ingest(frame(1, 30.0, 55.0), now_ms=55.0)
    d = core.decide(30.0, parse_policy("wait:40"))
    assert d.time_ms == 70.0 and [r.camera_id for r in d.selected] == [1]


def test_a_learner_acts_with_the_decision_id_it_will_carry() -> None:
    core = SchedulerCore(2)
    core.ingest(frame(2, 0.0, 5.0), now_ms=5.0)
    seen = []

    def act(decision_id: int, aoi: np.ndarray, t: float) -> np.ndarray:
        seen.append((decision_id, t, math.isnan(aoi[0])))
        return np.array([True, True])

    d = core.decide(30.0, parse_policy("all"), act=act)
    assert seen == [(1, 30.0, True)] and d.decision_id == 1
    assert [r.camera_id for r in d.selected] == [2]  # unknown AoI is never selected


@pytest.mark.parametrize(("payload", "reason"), [
    (b"\xff\xfe", "malformed"),
    (frame(9, 0.0, 1.0), "unknown_camera"),
    (frame(1, 50.0, 40.0), "bad_time"),
    (frame(1, 0.0, MAX_AHEAD_MS + 1000.0), "future_delivery"),
])
def test_frames_that_cannot_count_are_rejected_with_their_reason(payload, reason) -> None:
    core = SchedulerCore(2)
    with pytest.raises(Rejected) as err:
        core.ingest(payload, now_ms=0.0)
    assert err.value.reason == reason
    assert core.decide(10.0, parse_policy("all")).selected == []
