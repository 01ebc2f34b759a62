"""One camera's D/G/1/0 uplink: a single server with no waiting room.

The N cameras use M = N orthogonal subchannels, so each camera has a link of its own and the
links are independent. A frame offered at slot g while the previous accepted frame is still
in flight (``g < busy_until``) is dropped; otherwise it draws a transmission time Y and is
delivered at slot ``g + delay_slots(Y)``. A frame generated exactly at the slot the previous
one is delivered is accepted. Exactly one Y is drawn per accepted frame, in order, from the
link's own random stream — ``simulate`` consumes the stream in the same way.
"""

from __future__ import annotations

import math

import numpy as np

from aoi3d.channel.delay import DelayDistribution, delay_slots, parse_delay


def camera_rngs(seed: int, n: int) -> list[np.random.Generator]:
    """One independent random stream per link: ``SeedSequence(seed).spawn(n)``."""
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 0:
        raise ValueError(f"number of cameras must be an int >= 0, got {n!r}")
    return [np.random.default_rng(child) for child in np.random.SeedSequence(seed).spawn(n)]


class Link:
    """A camera's uplink. ``offer`` each generated frame; it returns the delivery slot or None."""

    def __init__(self, delay: DelayDistribution | str, rng: np.random.Generator) -> None:
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"rng must be a numpy Generator, got {type(rng).__name__}")
        self._delay = parse_delay(delay)
        self._rng = rng
        self._busy_until = -math.inf
        self._offered = 0
        self._dropped = 0
        self._delivered = 0
        self._last_delay_ms = math.nan

    @property
    def delay(self) -> DelayDistribution:
        return self._delay

    def set_delay(self, delay: DelayDistribution | str) -> None:
        """Use ``delay`` for the frames accepted from now on (the frame in flight keeps its)."""
        self._delay = parse_delay(delay)

    @property
    def busy_until(self) -> float:
        """Delivery slot of the frame in flight (or of the last one); −inf before any frame.
        A frame offered at ``gen_ms < busy_until`` is dropped."""
        return self._busy_until

    @property
    def offered(self) -> int:
        """Frames offered so far."""
        return self._offered

    @property
    def dropped(self) -> int:
        """Frames dropped because the link was busy."""
        return self._dropped

    @property
    def delivered(self) -> int:
        """Frames accepted; each is delivered at the slot ``offer`` returned for it."""
        return self._delivered

    @property
    def last_delay_ms(self) -> float:
        """The transmission time Y drawn for the last accepted frame (NaN before any)."""
        return self._last_delay_ms

    def in_flight(self, t_ms: float) -> bool:
        """Whether a frame is on the link at time ``t_ms`` (its delivery slot not reached)."""
        return t_ms < self._busy_until

    def offer(self, gen_ms: float) -> int | None:
        """Offer a frame generated at ``gen_ms`` (it enters at slot ``floor(gen_ms)``).

        Returns its delivery slot, or None when it is dropped because the previous frame is
        still in flight.
        """
        gen = float(gen_ms)
        if not math.isfinite(gen):
            raise ValueError(f"generation time must be finite, got {gen_ms!r}")
        self._offered += 1
        if gen < self._busy_until:
            self._dropped += 1
            return None
        y_ms = float(self._delay.sample(self._rng, 1)[0])
        delivery_slot = math.floor(gen) + delay_slots(y_ms)
        self._busy_until = delivery_slot
        self._delivered += 1
        self._last_delay_ms = y_ms
        return delivery_slot

    def __repr__(self) -> str:
        return (
            f"Link(delay={self._delay.spec!r}, offered={self._offered}, "
            f"dropped={self._dropped}, delivered={self._delivered}, "
            f"busy_until={self._busy_until})"
        )
