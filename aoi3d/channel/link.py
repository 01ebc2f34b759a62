"""One camera's D/G/1/0 uplink: a single server with no waiting room.

The N cameras use M = N orthogonal subchannels, so each camera has a link of its own and the
links are independent. A frame offered at slot g while the previous accepted frame is still
in flight (``g < busy_until``) is dropped; otherwise it draws a transmission time Y and is
delivered at slot ``g + delay_slots(Y)``. A frame generated exactly at the slot the previous
one is delivered is accepted. Exactly one Y is drawn per accepted frame, in order, from the
link's own random stream — ``simulate`` consumes the stream in the same way.

The link's channel may change (:mod:`aoi3d.channel.varying`): regimes, a trace replayed at
the link's own phase, or a cell shared with the other cameras' links (pass the same
``cell``). The transmission time then also depends on the slot the frame enters and on its
size in bytes.
"""

from __future__ import annotations

import math

import numpy as np

from aoi3d.channel.delay import DelayDistribution
from aoi3d.channel.varying import DEFAULT_FRAME_BYTES, CellQueue, Channel, parse_channel


def camera_rngs(seed: int, n: int) -> list[np.random.Generator]:
    """One independent random stream per link: ``SeedSequence(seed).spawn(n)``."""
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 0:
        raise ValueError(f"number of cameras must be an int >= 0, got {n!r}")
    return [np.random.default_rng(child) for child in np.random.SeedSequence(seed).spawn(n)]


class Link:
    """A camera's uplink. ``offer`` each generated frame; it returns the delivery slot or None."""

    def __init__(self, delay: Channel | DelayDistribution | str, rng: np.random.Generator, *,
                 start_ms: int = 0, cell: CellQueue | None = None) -> None:
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"rng must be a numpy Generator, got {type(rng).__name__}")
        self._rng = rng
        self._start_ms = int(start_ms)
        self._delay = parse_channel(delay)
        self._server = self._delay.server(rng, start_ms=self._start_ms, cell=cell)
        self._busy_until = -math.inf
        self._offered = 0
        self._dropped = 0
        self._delivered = 0
        self._last_delay_ms = math.nan

    @property
    def delay(self) -> Channel:
        """The channel in force (``.spec``, ``.mean_ms``)."""
        return self._delay

    @property
    def start_ms(self) -> int:
        """The slot the channel was started at (regimes and traces count from there)."""
        return self._start_ms

    @property
    def rng(self) -> np.random.Generator:
        return self._rng

    def set_delay(self, delay: Channel | DelayDistribution | str, *, start_ms: int | None = None,
                  cell: CellQueue | None = None) -> None:
        """Use ``delay`` for the frames accepted from now on (the frame in flight keeps its).
        ``start_ms``: where the new channel's regimes or trace start (default: unchanged)."""
        channel = parse_channel(delay)
        if start_ms is not None:
            self._start_ms = int(start_ms)
        self._server = channel.server(self._rng, start_ms=self._start_ms, cell=cell)
        self._delay = channel

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
        """The transmission time Y of the last accepted frame (drawn, or from the trace; NaN
        before any)."""
        return self._last_delay_ms

    def in_flight(self, t_ms: float) -> bool:
        """Whether a frame is on the link at time ``t_ms`` (its delivery slot not reached)."""
        return t_ms < self._busy_until

    def offer(self, gen_ms: float, size_bytes: int | None = None) -> int | None:
        """Offer a frame generated at ``gen_ms`` (it enters at slot ``floor(gen_ms)``) of
        ``size_bytes`` (default 12 kB; only a trace channel reads it).

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
        slot = math.floor(gen)
        size = DEFAULT_FRAME_BYTES if size_bytes is None else int(size_bytes)
        delivery_slot = slot + self._server.slots(slot, size)
        self._busy_until = delivery_slot
        self._delivered += 1
        self._last_delay_ms = self._server.last_ms
        return delivery_slot

    def __repr__(self) -> str:
        return (
            f"Link(delay={self._delay.spec!r}, offered={self._offered}, "
            f"dropped={self._dropped}, delivered={self._delivered}, "
            f"busy_until={self._busy_until})"
        )


def make_links(delay: Channel | DelayDistribution | str, rngs: list[np.random.Generator], *,
               start_ms: int = 0) -> list[Link]:
    """One link per stream, on one channel; a ``cell:`` channel's links share one cell
    (its phase drawn from the first stream, before anything else)."""
    channel = parse_channel(delay)
    cell = channel.new_cell(rngs[0], start_ms=start_ms) if channel.shared and rngs else None
    return [Link(channel, rng, start_ms=start_ms, cell=cell) for rng in rngs]
