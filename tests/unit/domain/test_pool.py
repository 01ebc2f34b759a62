"""The pool's dispatcher as pure logic: who gets which decision, and how each one ends."""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from aoi3d.pool import POOL_LOST, DecisionRef, Dispatcher, PoolReason, Report
from services.kit.reasons import SKIPPED, TRAINER_LOST, EndReason


def d(i: int, inc: int = 7) -> DecisionRef:
    return DecisionRef(inc, i, 100.0 * i)


def ask(pool: Dispatcher, w: str, now: float, done: DecisionRef | None = None,
        rendered: bool = True, reason: str = "", wait: float = 2.0, busy: float = 0.0):
    return pool.request(Report(w, done=None if done is None else done.key, rendered=rendered,
                               reason=reason, max_wait_s=wait, busy_s=busy), now)


def test_the_pools_reasons_are_the_wires_skipped_or_trainer_lost_ones() -> None:
    """The domain names the pool's reasons (it imports no proto); each is an EndReason of the
    wire with the same label, and the pool tells exactly the dispatcher's reasons."""
    assert {EndReason(r) for r in PoolReason} == set(SKIPPED) | set(TRAINER_LOST)
    assert set(POOL_LOST) <= set(TRAINER_LOST)
    assert all(EndReason(r) == r for r in PoolReason)


def test_the_newest_decision_wins_and_older_pending_ones_are_superseded() -> None:
    pool = Dispatcher()
    pool.joined("a", 0.0)
    assert pool.offer(d(1), 0.0) is None
    assert pool.offer(d(2), 0.1) is None
    assert pool.offer(d(3), 0.2) is None
    got = ask(pool, "a", 0.5)
    assert got is not None and got.decision == d(3) and got.worker_id == "a"
    assert math.isclose(got.wait_s, 0.3)
    assert pool.superseded == 2 and pool.pending() is None
    # nothing pending: the worker waits, and the next decision goes to it at once
    assert ask(pool, "a", 1.0, done=d(3)) is None
    handed = pool.offer(d(4), 1.2)
    assert handed is not None and handed.worker_id == "a" and handed.wait_s == 0.0
    assert pool.rendered == 1 and pool.assigned == 2


def test_each_decision_goes_to_exactly_one_worker_longest_waiting_first() -> None:
    pool = Dispatcher()
    for w in "abc":
        pool.joined(w, 0.0)
        assert ask(pool, w, 0.0) is None
    first = pool.offer(d(1), 1.0)
    second = pool.offer(d(2), 1.1)
    third = pool.offer(d(3), 1.2)
    assert [x.worker_id for x in (first, second, third)] == ["a", "b", "c"]
    assert pool.offer(d(4), 1.3) is None  # all busy: pending
    assert ask(pool, "b", 2.0, done=d(2)).decision == d(4)
    assert ask(pool, "a", 2.1, done=d(1)) is None
    s = pool.status(2.2)
    assert (s.assigned, s.rendered, s.in_flight, s.superseded) == (4, 2, 2, 0)


def test_prefer_warm_gives_a_decision_to_the_waiting_worker_with_the_newest_model() -> None:
    pool = Dispatcher()
    pool.prefer_warm = True
    for w in "abc":
        pool.joined(w, 0.0)
    assert ask(pool, "a", 0.0) is None and ask(pool, "b", 0.0) is None
    assert pool.offer(d(1), 1.0).worker_id == "a"  # no model anywhere: the longest waiting
    assert pool.offer(d(2), 1.1).worker_id == "b"  # a is busy
    assert ask(pool, "a", 1.5, done=d(1)) is None  # a waits again (model of d(1))
    assert ask(pool, "b", 1.6, done=d(2)) is None  # b too (model of d(2), newer)
    assert ask(pool, "c", 1.7) is None  # c never had a job
    assert pool.offer(d(3), 2.0).worker_id == "b"  # the warmest, though a waited longer
    assert pool.offer(d(4), 2.1).worker_id == "a"  # then the next warmest
    # another site's decision goes by that site's models: none yet, so the longest waiting
    other = DecisionRef(7, 5, 500.0, "north")
    assert pool.offer(other, 2.2).worker_id == "c"
    assert pool.offer(d(6), 2.3) is None  # nobody free: pending, as always
    pool.prefer_warm = False
    assert ask(pool, "b", 3.0, done=d(3)).decision == d(6)


def test_a_worker_that_dies_loses_only_its_own_decision() -> None:
    pool = Dispatcher()
    for w in "ab":
        pool.joined(w, 0.0)
        ask(pool, w, 0.0)
    pool.offer(d(1), 1.0)
    pool.offer(d(2), 1.0)
    lost = pool.left("a", 1.5)
    assert lost is not None and lost.decision == d(1)
    assert pool.lost == {"worker_died": 1}
    assert pool.worker_ids == ["b"]
    assert ask(pool, "b", 2.0, done=d(2)) is None
    assert pool.rendered == 1
    # an idle worker leaving loses nothing
    assert pool.left("b", 3.0) is None and pool.lost == {"worker_died": 1}


def test_timeouts_failures_and_undelivered_jobs_are_lost_with_their_reason() -> None:
    pool = Dispatcher(job_timeout_s=10.0)
    pool.joined("a", 0.0)
    ask(pool, "a", 0.0)
    pool.offer(d(1), 0.0)
    assert pool.expire(5.0) == []
    assert [x.decision for x in pool.expire(10.5)] == [d(1)]
    # its late report is ignored (the decision was already counted lost)
    assert ask(pool, "a", 11.0, done=d(1)) is None
    assert pool.late_reports == 1 and pool.rendered == 0
    pool.offer(d(2), 12.0)
    ask(pool, "a", 13.0, done=d(2), rendered=False, reason="bad_selection")
    pool.offer(d(3), 14.0)
    ask(pool, "a", 15.0)  # asks again without reporting d(3): the reply never reached it
    assert pool.lost == {"timeout": 1, "render_failed": 1, "not_delivered": 1}


def test_a_worker_that_will_not_wait_is_not_queued() -> None:
    pool = Dispatcher()
    pool.joined("a", 0.0)
    assert ask(pool, "a", 0.0, wait=0.0) is None
    assert pool.offer(d(1), 0.1) is None and pool.pending() == d(1)
    pool.joined("b", 0.0)
    assert ask(pool, "b", 0.2) is not None
    assert ask(pool, "a", 0.3, wait=0.0) is None


def test_sites_are_served_in_turn_each_with_its_newest_decision() -> None:
    pool = Dispatcher()
    pool.joined("a", 0.0)
    def a(i: int) -> DecisionRef:
        return DecisionRef(1, i, 10.0 * i, "north")

    def b(i: int) -> DecisionRef:
        return DecisionRef(1, i, 0.0, "south")

    for i in (1, 2, 3):
        pool.offer(a(i), 0.1 * i)
    pool.offer(b(1), 0.5)
    got = ask(pool, "a", 1.0)
    assert got.decision == a(3)  # both pending: north arrived first, and each site's newest
    got = ask(pool, "a", 2.0, done=got.decision)
    assert got.decision == b(1)  # then south's turn, though north has a newer one by now
    pool.offer(a(4), 2.1)
    pool.offer(b(2), 2.2)
    assert ask(pool, "a", 3.0, done=got.decision).decision == a(4)  # north served longest ago
    s = pool.status(3.0)
    assert s.by_site["north"] == {"decisions": 4, "superseded": 2, "assigned": 2, "rendered": 1}
    assert s.by_site["south"] == {"decisions": 2, "assigned": 1, "rendered": 1}
    assert s.pending == {"south": 2}


def test_give_up_takes_a_worker_out_of_the_queue() -> None:
    pool = Dispatcher()
    pool.joined("a", 0.0)
    ask(pool, "a", 0.0)
    pool.give_up("a")
    assert pool.offer(d(1), 1.0) is None and pool.pending() == d(1)


def test_status_rates_fraction_wait_age_and_busy_over_the_window() -> None:
    pool = Dispatcher(window_s=10.0)
    pool.joined("a", 0.0)
    ask(pool, "a", 0.0, busy=0.0)
    t = 0.0
    for i in range(1, 11):  # a decision every second; the worker renders every other one
        t = float(i)
        got = pool.offer(d(i), t)
        if got is None:
            continue
        ask(pool, "a", t + 0.9, done=got.decision, busy=0.9 * (i + 1) / 2)
    s = pool.status(t + 1.0)
    assert s.decisions == 10
    assert s.rendered == s.assigned
    assert 0.3 <= s.rendered_fraction <= 1.0
    assert s.renders_per_s > 0 and s.decisions_per_s > 0
    assert s.render_age_s_mean >= s.wait_s_mean >= 0
    (worker,) = s.workers
    assert worker.worker_id == "a" and 0 < worker.busy_fraction <= 1


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["offer", "offer_b", "ask", "ask_done", "fail",
                                           "leave", "join", "expire", "give_up"]),
                          st.sampled_from(["a", "b", "c"])), max_size=60))
def test_every_decision_is_accounted_for_and_none_is_handed_out_twice(events) -> None:
    pool = Dispatcher(job_timeout_s=5.0)
    handed: list[tuple] = []
    holding: dict[str, DecisionRef] = {}
    next_id, now = 1, 0.0
    for kind, w in events:
        now += 1.0
        if kind in ("offer", "offer_b"):
            ref = d(next_id) if kind == "offer" else DecisionRef(7, next_id, 0.0, "other")
            got = pool.offer(ref, now)
            next_id += 1
        elif kind == "join":
            pool.joined(w, now)
            got = None
        elif kind == "leave":
            pool.left(w, now)
            holding.pop(w, None)
            got = None
        elif kind == "expire":
            for a in pool.expire(now):
                holding.pop(a.worker_id, None)
            got = None
        elif kind == "give_up":
            pool.give_up(w)
            got = None
        else:
            done = holding.pop(w, None) if kind != "ask" else None
            got = ask(pool, w, now, done=done, rendered=kind == "ask_done",
                      reason="x" if kind == "fail" else "")
            if kind == "ask":
                holding.pop(w, None)
        if got is not None:
            handed.append(got.decision.key)
            holding[got.worker_id] = got.decision
    assert len(handed) == len(set(handed))  # never twice
    s = pool.status(now)
    assert s.assigned == len(handed)
    assert s.rendered + sum(s.lost.values()) + s.in_flight == s.assigned
    for counts in s.by_site.values():
        assert counts.get("assigned", 0) + counts.get("superseded", 0) <= counts["decisions"]
    assert s.assigned + s.superseded + len(s.pending) == s.decisions
    ended = pool.drain_ended()  # what the dispatcher tells the ledger: each end once
    assert len({e.decision.key for e in ended}) == len(ended)
    assert sum(e.state == "skipped" for e in ended) == s.superseded
    assert sum(e.state == "lost" for e in ended) == sum(s.lost.values())
    assert pool.drain_ended() == []


def test_each_end_without_a_render_is_told_with_its_reason() -> None:
    """The Ended events the dispatcher publishes as Outcomes: one per pool reason."""
    pool = Dispatcher(job_timeout_s=5.0)
    for w in "abcd":
        pool.joined(w, 0.0)
    pool.offer(d(1), 0.0)
    pool.offer(d(2), 0.1)  # 1 superseded
    a = ask(pool, "a", 0.2)  # takes 2
    pool.offer(d(3), 0.3)
    ask(pool, "b", 0.4)  # takes 3
    pool.offer(d(4), 0.5)
    ask(pool, "c", 0.6)  # takes 4
    pool.offer(d(5), 0.7)
    ask(pool, "d", 0.8)  # takes 5
    pool.left("a", 1.0)  # 2: worker_died
    ask(pool, "b", 1.1, done=d(3), rendered=False, reason="out of memory")  # 3: render_failed
    ask(pool, "c", 1.2)  # 4: not_delivered (asks again without reporting it)
    pool.expire(10.0)  # 5: timeout
    pool.refuse(d(6), "stale_decision")
    pool.never_received(d(7))
    got = [(e.decision.decision_id, e.state, e.reason, e.detail) for e in pool.drain_ended()]
    assert got == [(1, "skipped", "superseded", ""), (2, "lost", "worker_died", ""),
                   (3, "lost", "render_failed", "out of memory"),
                   (4, "lost", "not_delivered", ""), (5, "lost", "timeout", ""),
                   (6, "lost", "refused", "stale_decision"),
                   (7, "lost", "not_received", "")]
    assert a is not None and pool.lost["render_failed"] == 1  # the why is the detail only


def periodic(pool: Dispatcher, n: int, period: float = 0.03) -> None:
    """Offer decisions 1..n at a steady period (the dispatcher learns it), none taken."""
    for i in range(1, n + 1):
        pool.offer(d(i), i * period)


def test_fresh_fraction_leaves_a_stale_pending_decision_for_the_next_one() -> None:
    """A worker that asks when the pending decision has waited more than the fraction of the
    period waits; the next decision goes to it and the stale one ends superseded."""
    pool = Dispatcher(fresh_fraction=0.5)
    pool.joined("a", 0.0)
    periodic(pool, 5)  # pending: d(5), offered at 0.15; period 0.03
    assert ask(pool, "a", 0.17) is None  # 20 ms old > 15 ms: wait for d(6)
    assert pool.waited_fresh == 1 and pool.pending() == d(5)
    got = pool.offer(d(6), 0.18)
    assert got is not None and got.decision == d(6) and got.wait_s == 0.0
    assert pool.pending() is None and pool.superseded == 5  # d(1)..d(4), then d(5)
    ended = {e.decision.decision_id: e.reason for e in pool.drain_ended()}
    assert ended[5] == PoolReason.SUPERSEDED


def test_fresh_fraction_takes_a_young_or_overdue_pending_decision_at_once() -> None:
    pool = Dispatcher(fresh_fraction=0.5)
    pool.joined("a", 0.0)
    periodic(pool, 5)
    young = ask(pool, "a", 0.16)  # 10 ms old < 15 ms
    assert young is not None and young.decision == d(5)
    pool.offer(d(6), 0.18)
    # the next one is late (more than 1.5 periods since d(6)): waiting could wait for nothing
    late = ask(pool, "a", 0.24, done=d(5))
    assert late is not None and late.decision == d(6) and pool.waited_fresh == 0


def test_fresh_fraction_one_and_a_worker_that_cannot_wait_take_the_pending_one() -> None:
    for fraction, wait in ((1.0, 2.0), (0.5, 0.0)):
        pool = Dispatcher(fresh_fraction=fraction)
        pool.joined("a", 0.0)
        periodic(pool, 5)
        got = ask(pool, "a", 0.17, wait=wait)
        assert got is not None and got.decision == d(5) and pool.waited_fresh == 0


def test_fresh_fraction_is_checked() -> None:
    for bad in (-0.1, 1.5, math.nan):
        try:
            Dispatcher(fresh_fraction=bad)
        except ValueError as err:
            assert "fresh_fraction" in str(err)
        else:
            raise AssertionError(f"fresh_fraction={bad} accepted")
