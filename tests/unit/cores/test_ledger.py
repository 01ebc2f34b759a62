"""The decision ledger (services/metrics/ledger.py): every decision ends in exactly one state,
a test per state and reason, the unseen and expired rules, the snapshot, and a property test
that no sequence of events counts an id twice or leaves one out."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.kit.observe import Rejected
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.reasons import EndReason
from services.metrics.ledger import (
    LOST_REASONS,
    MAX_GAP,
    SKIPPED_REASONS,
    Ledger,
    decode_outcome,
    render_header,
)

INC = 7


def test_the_type_checkers_endreason_is_the_built_one() -> None:
    """services/kit/reasons.py spells EndReason's members out for mypy (TYPE_CHECKING): the
    same names and values as the enum built from the proto at run time."""
    import ast
    import inspect

    from services.kit import reasons

    tree = ast.parse(inspect.getsource(reasons))
    static = next(node for node in ast.walk(tree)
                  if isinstance(node, ast.ClassDef) and node.name == "EndReason")
    spelled = {stmt.targets[0].id: stmt.value.value for stmt in static.body
               if isinstance(stmt, ast.Assign)}
    assert spelled == {r.name: r.value for r in EndReason}


def test_a_scored_decision() -> None:
    led = Ledger()
    led.decided(INC, 1, 0.0)
    assert led.summary(0.0).open == 1
    assert led.closed(INC, 1, "scored", "", 1.0)
    s = led.summary(1.0)
    assert (s.decisions, s.scored, s.open, s.oldest_open_s) == (1, 1, 0, None)


@pytest.mark.parametrize("reason", SKIPPED_REASONS)
def test_each_skip_reason(reason: str) -> None:
    led = Ledger()
    led.decided(INC, 1, 0.0)
    led.closed(INC, 1, "skipped", reason, 0.5)
    assert led.summary(1.0).skipped[reason] == 1


@pytest.mark.parametrize("reason", [r for r in LOST_REASONS if r not in ("unseen", "expired")])
def test_each_reason_told_to_the_ledger(reason: str) -> None:
    led = Ledger()
    led.decided(INC, 1, 0.0)
    led.closed(INC, 1, "lost", reason, 0.5)
    s = led.summary(1.0)
    assert s.lost[reason] == 1 and s.decisions == 1 and s.open == 0
    assert sum(s.lost.values()) == 1


def test_unseen_ids_between_two_seen_ones_and_before_the_first() -> None:
    led = Ledger()
    led.decided(INC, 3, 0.0)  # 1 and 2 were made before the ledger listened
    led.decided(INC, 7, 0.0)  # 4, 5, 6 never arrived
    s = led.summary(0.0)
    assert s.lost["unseen"] == 5 and s.open == 2 and s.decisions == 7
    led.decided(INC + 1, 1, 0.0)  # a restarted scheduler numbers from 1 again
    assert led.summary(0.0).lost["unseen"] == 5 and led.summary(0.0).incarnations == 2


def test_open_too_long_expires_and_never_hangs() -> None:
    led = Ledger(open_bound_s=10.0)
    led.decided(INC, 1, 0.0)
    led.decided(INC, 2, 5.0)
    assert led.expire(10.0) == 0
    assert led.expire(10.5) == 1
    s = led.summary(10.5)
    assert s.lost["expired"] == 1 and s.open == 1 and s.oldest_open_s == pytest.approx(5.5)
    assert led.expire(16.0) == 1 and led.summary(16.0).open == 0


def test_the_first_end_wins_and_later_events_count_after_close() -> None:
    led = Ledger()
    led.decided(INC, 1, 0.0)
    assert led.closed(INC, 1, "lost", "timeout", 1.0)
    assert not led.closed(INC, 1, "scored", "", 2.0)  # its late render
    led.decided(INC, 1, 3.0)  # a repeated Decision
    s = led.summary(3.0)
    assert (s.scored, s.lost["timeout"], s.after_close, s.decisions) == (0, 1, 2, 1)


def test_an_outcome_before_its_decision_opens_and_closes_it() -> None:
    led = Ledger()
    assert led.closed(INC, 2, "skipped", "superseded", 0.0)
    led.decided(INC, 2, 0.1)  # the Decision itself, late: counted already
    s = led.summary(1.0)
    assert (s.decisions, s.skipped["superseded"], s.lost["unseen"], s.after_close) == (2, 1, 1, 1)


def test_nonsense_is_refused_and_changes_nothing() -> None:
    led = Ledger()
    led.decided(INC, 1, 0.0)
    before = led.to_json()
    with pytest.raises(Rejected, match="implausible"):
        led.decided(INC, 2 + MAX_GAP + 1, 0.0)
    with pytest.raises(Rejected, match="ids start at 1"):
        led.decided(INC, 0, 0.0)
    with pytest.raises(Rejected, match="no decision ends"):
        led.closed(INC, 1, "lost", "gremlins", 0.0)
    with pytest.raises(Rejected, match="no decision ends"):
        led.closed(INC, 1, "scored", "because", 0.0)
    assert led.to_json() == before


def test_the_snapshot_round_trips_and_refuses_garbage() -> None:
    led = Ledger(open_bound_s=30.0)
    led.decided(INC, 4, 0.0)
    led.decided(INC, 5, 1.0)
    led.closed(INC, 4, "lost", "worker_died", 2.0)
    back = Ledger.from_json(led.to_json())
    assert back.to_json() == led.to_json()
    assert back.summary(3.0) == led.summary(3.0)
    back.decided(INC, 7, 3.0)  # continues where it stopped: 6 unseen, nothing recounted
    assert back.summary(3.0).lost["unseen"] == 3 + 1
    assert Ledger.from_json(led.to_json(), open_bound_s=99.0).open_bound_s == 99.0
    for junk in ("", "{}", '{"version": 2}', '{"version": 1, "totals": [["lost", "x", 1]]}'):
        with pytest.raises(ValueError):
            Ledger.from_json(junk)


def test_outcome_and_render_decoding() -> None:
    ok = pb.Outcome(decision_id=3, incarnation=INC, site="site1", state="lost",
                    reason=pb.END_REASON_WORKER_DIED).SerializeToString()
    assert decode_outcome(ok, "site1").reason == "worker_died"
    assert decode_outcome(ok, "site1").reason is EndReason.WORKER_DIED
    bad = {b"\xff\xff": "not an Outcome",
           pb.Outcome(decision_id=3, site="site2", state="lost", reason=pb.END_REASON_TIMEOUT)
           .SerializeToString(): "site 'site2'",
           pb.Outcome(decision_id=3, state="scored").SerializeToString(): "skipped or lost",
           pb.Outcome(decision_id=3, state="lost").SerializeToString(): "no reason given",
           pb.Outcome(decision_id=3, state="lost", reason=99).SerializeToString():
               "unknown EndReason 99",
           pb.Outcome(decision_id=3, state="lost", reason=pb.END_REASON_UNSEEN)
           .SerializeToString(): "does not lose",
           pb.Outcome(decision_id=3, state="skipped", reason=pb.END_REASON_TIMEOUT)
           .SerializeToString(): "no decision ends"}
    for payload, message in bad.items():
        with pytest.raises(Rejected, match=message):
            decode_outcome(payload, "site1")
    render = pb.Render(decision_id=9, decision_incarnation=INC, time_ms=60.0)
    assert render_header(render.SerializeToString()) == (INC, 9, 60.0)
    assert render_header(b"\xff\xff") is None
    assert render_header(b"") == (0, 0, 0.0)  # an empty Render names no decision (id 0)


EVENT = st.tuples(st.sampled_from(["decided", "scored", "skipped", "lost", "expire"]),
                  st.integers(1, 3), st.integers(1, 40), st.floats(0, 5))


@settings(max_examples=200, deadline=None)
@given(st.lists(EVENT, max_size=80))
def test_every_id_is_counted_exactly_once(events) -> None:
    """Whatever the order, repeats and gaps: decisions = the sum of the highest ids seen,
    each of them open or in one state, and the snapshot agrees."""
    led = Ledger(open_bound_s=3.0)
    high: dict[int, int] = {}
    now = 0.0
    for kind, inc, did, dt in events:
        now += dt
        if kind == "expire":
            led.expire(now)
            continue
        if kind == "decided":
            led.decided(inc, did, now)
        else:
            reason = {"scored": "", "skipped": "superseded", "lost": "timeout"}[kind]
            led.closed(inc, did, kind, reason, now)
        high[inc] = max(high.get(inc, 0), did)
    s = led.summary(now)
    assert s.decisions == sum(high.values())
    assert s.decisions == s.scored + sum(s.skipped.values()) + sum(s.lost.values()) + s.open
    assert Ledger.from_json(led.to_json()).summary(now) == s
