"""The decision ledger: every decision of a site ends in exactly one state.

Pure logic (no bus, no threads, no files): the metrics runtime feeds it the site's Decision,
Outcome and Render messages and a clock, saves its snapshot and exports its totals. A
decision is named by (incarnation, decision id); a scheduler numbers its decisions 1, 2, …
per incarnation, so the ids the ledger has not seen are known: they lie between the highest
id seen of that incarnation and the next one seen.

States (:data:`STATES`) and their reasons:

- ``scored``: its render was paired with its truth frame and a Quality published.
- ``skipped`` (by choice): ``superseded`` — a newer decision of its site was taken before a
  worker was free (the pool keeps one pending decision per site).
- ``lost``, with a reason (:data:`LOST_REASONS`): from the dispatcher's Outcome —
  ``worker_died``, ``timeout``, ``not_delivered``, ``render_failed``, ``refused``,
  ``not_received`` (a gap in the ids the dispatcher received: lost in transit); from the
  metrics service itself — ``truth_missing`` (no truth frame of its time), ``render_rejected``
  (its render could not be scored); from the ledger — ``unseen`` (it never saw the decision: made
  while the metrics service was down, or lost in transit) and ``expired`` (still open after
  ``open_bound_s``: a dispatcher or worker died holding it, or its render or outcome was lost).

Every reason is a member of :class:`services.kit.reasons.EndReason` (the proto's one enum); the
ledger keeps and saves its label, the same text as before the enum (snapshot version 1).

The first terminal event wins: a later one (a late render of a decision counted lost, a
repeated message) only counts ``after_close``. Every id from 1 to the highest seen of an
incarnation is therefore counted exactly once — open, or in one state.
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass

from services.kit import reasons
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.reasons import EndReason
from services.kit.rejected import Rejected, RejectReason

__all__ = ["LOST_REASONS", "SKIPPED_REASONS", "STATES", "Ledger", "LedgerSummary", "Outcome",
           "decode_outcome", "render_header"]

STATES = ("scored", "skipped", "lost")
SKIPPED_REASONS = tuple(str(r) for r in reasons.SKIPPED)
"""The labels of :data:`services.kit.reasons.SKIPPED`: ``superseded``."""
TRAINER_LOST = tuple(str(r) for r in reasons.TRAINER_LOST)
LOST_REASONS = tuple(str(r) for r in reasons.LOST)
"""The labels of :data:`services.kit.reasons.LOST`, in the proto's order."""
MAX_GAP = 1_000_000
"""Ids skipped at once that the ledger believes (8 h of decisions every 30 ms); a larger jump
is a corrupt or hostile message and is refused, so one message cannot add a billion ``unseen``."""


@dataclass(frozen=True)
class LedgerSummary:
    """The ledger's totals; ``decisions`` = ``scored`` + skipped + lost + ``open``."""

    decisions: int
    scored: int
    skipped: dict[str, int]
    lost: dict[str, int]
    open: int
    oldest_open_s: float | None
    """Age of the oldest open decision (wall s), None when none is open."""
    after_close: int
    incarnations: int


class Ledger:
    """One site's ledger; see the module docstring. Not thread-safe: one thread calls it."""

    def __init__(self, *, open_bound_s: float = 150.0) -> None:
        if not open_bound_s > 0:
            raise ValueError(f"open_bound_s must be > 0, got {open_bound_s}")
        self.open_bound_s = float(open_bound_s)
        self.totals: Counter[tuple[str, str]] = Counter()
        """(state, reason) → decisions; reason "" for scored."""
        self._high: dict[int, int] = {}
        """incarnation → highest decision id seen."""
        self._open: dict[tuple[int, int], float] = {}
        """(incarnation, id) → wall s it was opened."""
        self.after_close = 0
        self.changes = 0
        """Increments on every change (the runtime saves when it moved)."""

    # ------------------------------------------------------------------ events
    def decided(self, incarnation: int, decision_id: int, now_s: float) -> None:
        """A Decision was seen: opened (ids skipped since the last seen counted ``unseen``)."""
        if not self._see(incarnation, decision_id, now_s):
            self._after_close()

    def closed(self, incarnation: int, decision_id: int, state: str, reason: str,
               now_s: float) -> bool:
        """The decision ended in ``state`` (``reason`` "" for scored); False when it had ended
        already (counted ``after_close``). A decision not yet seen is opened and closed."""
        self._check(state, reason)
        key = (incarnation, decision_id)
        if key not in self._open and not self._see(incarnation, decision_id, now_s):
            self._after_close()
            return False
        del self._open[key]
        self.totals[state, reason] += 1
        self.changes += 1
        return True

    def expire(self, now_s: float) -> int:
        """Count the decisions open longer than ``open_bound_s`` lost (``expired``)."""
        due = [k for k, t in self._open.items() if now_s - t > self.open_bound_s]
        for key in due:
            del self._open[key]
        if due:
            self.totals["lost", str(EndReason.EXPIRED)] += len(due)
            self.changes += 1
        return len(due)

    # ------------------------------------------------------------------ reading
    def summary(self, now_s: float) -> LedgerSummary:
        by = {s: {r: n for (st, r), n in sorted(self.totals.items()) if st == s and n}
              for s in STATES}
        closed = sum(self.totals.values())
        oldest = min(self._open.values(), default=None)
        return LedgerSummary(
            decisions=closed + len(self._open), scored=self.totals["scored", ""],
            skipped={r: by["skipped"].get(r, 0) for r in SKIPPED_REASONS} | by["skipped"],
            lost={r: by["lost"].get(r, 0) for r in LOST_REASONS} | by["lost"],
            open=len(self._open), oldest_open_s=None if oldest is None else now_s - oldest,
            after_close=self.after_close, incarnations=len(self._high))

    # ------------------------------------------------------------------ snapshot
    def to_json(self) -> str:
        return json.dumps({
            "version": 1, "open_bound_s": self.open_bound_s,
            "totals": [[s, r, n] for (s, r), n in sorted(self.totals.items())],
            "high": [[i, d] for i, d in sorted(self._high.items())],
            "open": [[i, d, t] for (i, d), t in sorted(self._open.items())],
            "after_close": self.after_close})

    @classmethod
    def from_json(cls, text: str, *, open_bound_s: float | None = None) -> Ledger:
        """A ledger restored from :meth:`to_json` (``ValueError`` when it is not one)."""
        try:
            doc = json.loads(text)
            if doc.get("version") != 1:
                raise ValueError(f"unknown ledger snapshot version {doc.get('version')!r}")
            led = cls(open_bound_s=open_bound_s or float(doc["open_bound_s"]))
            for s, r, n in doc["totals"]:
                led._check(str(s), str(r))
                led.totals[str(s), str(r)] = int(n)
            led._high = {int(i): int(d) for i, d in doc["high"]}
            led._open = {(int(i), int(d)): float(t) for i, d, t in doc["open"]}
            led.after_close = int(doc["after_close"])
        except (KeyError, TypeError, json.JSONDecodeError) as err:
            raise ValueError(f"not a ledger snapshot: {err!r}") from None
        return led

    # ------------------------------------------------------------------ internals
    def _see(self, incarnation: int, decision_id: int, now_s: float) -> bool:
        """Open the decision if it is newer than every one seen of its incarnation (counting
        the ids in between ``unseen``); False when it is not (seen, so counted already)."""
        if decision_id < 1:
            raise Rejected(RejectReason.MALFORMED, f"decision id {decision_id} (ids start at 1)")
        high = self._high.get(incarnation, 0)
        if decision_id <= high:
            return False
        gap = decision_id - high - 1
        if gap > MAX_GAP:
            raise Rejected(RejectReason.IMPLAUSIBLE_DECISION_ID,
                           f"decision {decision_id} of incarnation {incarnation} would skip "
                           f"{gap} ids (at most {MAX_GAP} are believed)")
        if gap:
            self.totals["lost", str(EndReason.UNSEEN)] += gap
        self._high[incarnation] = decision_id
        self._open[incarnation, decision_id] = now_s
        self.changes += 1
        return True

    def _after_close(self) -> None:
        self.after_close += 1
        self.changes += 1

    @staticmethod
    def _check(state: str, reason: str) -> None:
        ok = {"scored": ("",), "skipped": SKIPPED_REASONS, "lost": LOST_REASONS}
        if reason not in ok.get(state, ()):
            raise Rejected(RejectReason.MALFORMED,
                           f"no decision ends {state!r} with reason {reason!r}")


@dataclass(frozen=True)
class Outcome:
    """A decoded Outcome: its reason as an :class:`EndReason` (a ``str``, its label)."""

    decision_id: int
    incarnation: int
    site: str
    state: str
    reason: EndReason
    detail: str


def decode_outcome(payload: bytes, site: str) -> Outcome:
    """An Outcome message of ``site`` (:class:`Rejected` when it is not a valid one)."""
    try:
        msg = pb.Outcome.FromString(payload)
    except Exception as err:  # protobuf raises DecodeError and others
        raise Rejected(RejectReason.MALFORMED,
                       f"not an Outcome ({err.__class__.__name__})") from None
    if msg.site and msg.site != site:
        raise Rejected(RejectReason.WRONG_SITE,
                       f"an Outcome of site {msg.site!r} on site {site!r}'s key")
    if msg.state not in ("skipped", "lost"):
        raise Rejected(RejectReason.MALFORMED,
                       f"an Outcome's state is skipped or lost, not {msg.state!r}")
    try:
        reason = reasons.from_wire(msg.reason)
    except ValueError as err:
        raise Rejected(RejectReason.MALFORMED, f"an Outcome's reason: {err}") from None
    if msg.state == "lost" and reason not in reasons.TRAINER_LOST:
        raise Rejected(RejectReason.MALFORMED,
                       f"the dispatcher does not lose a decision for {reason!s} "
                       f"(its reasons: {', '.join(TRAINER_LOST)})")
    Ledger._check(msg.state, str(reason))
    return Outcome(msg.decision_id, msg.incarnation, msg.site, msg.state, reason, msg.detail)


def render_header(payload: bytes) -> tuple[int, int, float] | None:
    """(incarnation, decision id, time t in sim ms) of a Render, or None when the payload does
    not parse."""
    try:
        msg = pb.Render.FromString(payload)
    except Exception:  # protobuf raises DecodeError and others
        return None
    return msg.decision_incarnation, msg.decision_id, msg.time_ms
