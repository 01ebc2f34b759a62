"""The network's core: offered frames and a time in, frames due for delivery out.

No bus, no threads, no metrics library: the runtime (:mod:`services.network.runtime`) feeds it
under its lock and publishes what it returns; tests drive it directly.

Camera n's offered frame goes through its :class:`aoi3d.channel.link.Link` (a D/G/1/0
queue), entering it at ``max(generation_ms, send_ms)`` (the camera emulator sends at generation;
the ingest service of real cameras at receipt, so emulated delay adds to the real link's):
``offer`` gives the frame's delivery slot, or drops it when the previous frame is still
in flight. The channel may change on its own (``regimes:``, a ``trace:`` played from the time
it was set, a ``cell:`` whose capacity the links share; :mod:`aoi3d.channel.varying`); a
frame's size is its encoded image's bytes. Accepted frames wait in a heap ordered by
delivery time (then by arrival) until :meth:`NetworkCore.pop_due` hands them out.
"""

from __future__ import annotations

import heapq
import itertools
from dataclasses import dataclass, field

import numpy as np

from aoi3d.channel import Channel, Link, camera_rngs, parse_channel
from aoi3d.channel.varying import check_frame_encoding, jpeg_bytes
from services.kit.codec import decode_frame
from services.kit.rejected import Rejected, RejectReason

__all__ = ["ChannelConfig", "ChannelConfigError", "LinkStats", "NetworkCore", "Pending"]


class ChannelConfigError(ValueError):
    """A channel change that cannot be applied; the message says what is accepted."""


@dataclass(frozen=True)
class ChannelConfig:
    """The links' settings: the default delay spec, per-camera overrides and the seed."""

    delay: str
    per_camera: dict[int, str] = field(default_factory=dict)
    seed: int = 1

    def spec_of(self, camera_id: int) -> str:
        return self.per_camera.get(camera_id, self.delay)


@dataclass
class LinkStats:
    """One link's counts since the service started (they survive a reseed)."""

    camera_id: int
    delay: Channel
    offered: int = 0
    dropped: int = 0
    delivered: int = 0
    in_flight: bool = False


@dataclass(order=True)
class Pending:
    """An accepted frame waiting for its delivery slot."""

    delivery_ms: float
    order: int
    camera_id: int = field(compare=False)
    generation_ms: float = field(compare=False)
    payload: bytes = field(compare=False, repr=False)


class NetworkCore:
    """N independent links and the frames in flight. Not thread-safe: the runtime serialises
    calls.

    ``max_skew_ms``: a frame generated further than this after ``now_ms`` is rejected (the
    sender's clock disagrees with ours)."""

    def __init__(self, n_cameras: int, *, delay: str = "exp:60",
                 per_camera: dict[int, str] | None = None, seed: int = 1,
                 max_skew_ms: float = 1000.0, now_ms: float = 0.0,
                 frame_encoding: str = "png") -> None:
        self.camera_ids: tuple[int, ...] = tuple(range(1, n_cameras + 1))
        self._accepted = frozenset(self.camera_ids)
        self._max_skew_ms = float(max_skew_ms)
        self._jpeg_quality = check_frame_encoding(frame_encoding)
        self.config = self._checked(delay, per_camera or {}, seed)
        self.started_ms = int(now_ms)  # where the default channel's regimes / trace start
        rngs = camera_rngs(self.config.seed, n_cameras)
        on_cell = self._on_cell(self.config)
        cell = (parse_channel(self.config.delay).new_cell(rngs[on_cell[0] - 1],
                                                          start_ms=self.started_ms)
                if on_cell else None)
        self._links = {n: Link(parse_channel(self.config.spec_of(n)), rngs[n - 1],
                               start_ms=self.started_ms, cell=cell if n in on_cell else None)
                       for n in self.camera_ids}
        self._reseed: dict[int, np.random.Generator] = {}
        self._stats = {n: LinkStats(n, self._links[n].delay) for n in self.camera_ids}
        self._heap: list[Pending] = []
        self._order = itertools.count()

    # ------------------------------------------------------------------ configuration
    def _on_cell(self, cfg: ChannelConfig) -> list[int]:
        """The cameras sharing the default channel's cell (none unless it is a ``cell:``)."""
        if not parse_channel(cfg.delay).shared:
            return []
        return [n for n in self.camera_ids if n not in cfg.per_camera]

    def _share_cell(self) -> None:
        """The links on a ``cell:`` default channel share one new cell (its phase drawn from
        the first such link's stream)."""
        channel = parse_channel(self.config.delay)
        on_cell = self._on_cell(self.config)
        if not on_cell:
            return
        cell = channel.new_cell(self._links[on_cell[0]].rng, start_ms=self.started_ms)
        for n in on_cell:
            self._links[n].set_delay(channel, start_ms=self.started_ms, cell=cell)
            self._stats[n].delay = self._links[n].delay

    def _checked(self, delay: str, per_camera: dict[int, str], seed: int) -> ChannelConfig:
        """Validate a full config (raises ``DelaySpecError`` / ``ChannelConfigError``)."""
        spec = parse_channel(delay).spec
        unknown = sorted(set(per_camera) - self._accepted)
        if unknown:
            raise ChannelConfigError(
                f"per_camera names unknown camera id(s) {unknown}; the links are cameras "
                f"{self.camera_ids[0]}..{self.camera_ids[-1]}")
        overrides: dict[int, str] = {}
        for n, camera_spec in sorted(per_camera.items()):
            try:
                channel = parse_channel(camera_spec)
            except ValueError as err:
                raise ChannelConfigError(f"per_camera {n}: {err}") from err
            if channel.shared:
                raise ChannelConfigError(f"per_camera {n}: a cell: channel is shared by the "
                                         f"cameras, so it can only be the default delay")
            overrides[n] = channel.spec
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ChannelConfigError(f"seed must be an integer >= 0, got {seed!r}")
        return ChannelConfig(delay=spec, per_camera=overrides, seed=seed)

    def update(self, *, delay: str | None = None, per_camera: dict[int, str] | None = None,
               seed: int | None = None, now_ms: float | None = None) -> ChannelConfig:
        """Partial update (``per_camera`` replaces the whole override map); nothing changes
        when it raises ``DelaySpecError`` or ``ChannelConfigError``: the new config is
        checked and every link's new channel built on a scratch random stream first, and
        only then swapped in.

        A new delay applies to the frames offered from now on (a frame in flight keeps its
        delivery slot); a channel that changes (regimes, a trace) starts at ``now_ms``. A new
        seed restarts each link's random stream once its frame in flight is delivered.
        """
        old = self.config
        new = self._checked(old.delay if delay is None else delay,
                            old.per_camera if per_camera is None else per_camera,
                            old.seed if seed is None else seed)
        started_ms = (int(now_ms) if new.delay != old.delay and now_ms is not None
                      else self.started_ms)
        on_cell = self._on_cell(new)
        changes: dict[int, tuple[Channel, int]] = {}
        for n, link in self._links.items():
            if n in on_cell:
                continue
            if link.delay.spec != new.spec_of(n) or (n not in new.per_camera
                                                     and new.delay != old.delay):
                start = started_ms if n not in new.per_camera else (
                    int(now_ms) if now_ms is not None else link.start_ms)
                changes[n] = (parse_channel(new.spec_of(n)), start)
        share = bool(on_cell) and (new.delay != old.delay or on_cell != self._on_cell(old))
        self._try_build(changes, parse_channel(new.delay) if share else None, started_ms)
        # nothing below can fail: the swap
        self.config, self.started_ms = new, started_ms
        for n, (channel, start) in changes.items():
            self._links[n].set_delay(channel, start_ms=start)
            self._stats[n].delay = self._links[n].delay
        if share:
            self._share_cell()
        if new.seed != old.seed:
            rngs = camera_rngs(new.seed, len(self.camera_ids))
            self._reseed = {n: rngs[n - 1] for n in self.camera_ids}
        return new

    @staticmethod
    def _try_build(changes: dict[int, tuple[Channel, int]], cell: Channel | None,
                   started_ms: int) -> None:
        """Build each new server (and the shared cell) on a scratch stream, so a channel
        that cannot start (a phase out of range, ...) is refused before anything changes."""
        scratch = np.random.default_rng(0)
        try:
            for channel, start in changes.values():
                channel.server(scratch, start_ms=start)
            if cell is not None:
                queue = cell.new_cell(scratch, start_ms=started_ms)
                cell.server(scratch, start_ms=started_ms, cell=queue)
        except (ValueError, OverflowError) as err:
            raise ChannelConfigError(f"the channel cannot start: {err}") from None

    def regime(self, now_ms: float) -> str:
        """The spec in force now on the links without an override (a regime's own spec)."""
        return parse_channel(self.config.delay).regime_at(now_ms, self.started_ms)

    def link_stats(self, now_ms: float) -> list[LinkStats]:
        """A snapshot of every link's counts and state at ``now_ms``."""
        return [LinkStats(n, s.delay, s.offered, s.dropped, s.delivered,
                          self._links[n].in_flight(now_ms)) for n, s in self._stats.items()]

    # ------------------------------------------------------------------ frames
    def offer(self, key: str, payload: bytes, now_ms: float) -> tuple[int, Pending | None]:
        """Offer a camera's frame (published on ``key``) to its link at ``now_ms``: (camera,
        the queued delivery) or (camera, None) when the link dropped it. Raises
        :class:`Rejected` for a malformed frame, a key naming another camera or a frame from
        the future."""
        frame = decode_frame(payload, self._accepted)
        key_camera = key.rsplit("/", 2)[-2]
        if key_camera != str(frame.camera_id):
            raise Rejected(RejectReason.KEY_MISMATCH,
                           f"frame of camera {frame.camera_id} published on "
                           f"{key}")
        if frame.generation_ms > now_ms + self._max_skew_ms:
            raise Rejected(RejectReason.CLOCK_SKEW,
                           f"frame generated at {frame.generation_ms:.0f} ms but the clock "
                           f"says {now_ms:.0f} ms; check AOI3D_EPOCH_S and AOI3D_TIME_SCALE")
        n = frame.camera_id
        # a frame enters its link when it was sent: at its generation for the emulated
        # cameras, at its receipt for real ones (the ingest's send_ms), so the emulated delay
        # comes on top of the real link's
        entry_ms = max(frame.generation_ms, frame.send_ms)
        link = self._links[n]
        rng = self._reseed.get(n)
        if rng is not None and not link.in_flight(entry_ms) and not link.delay.shared:
            link = self._links[n] = Link(link.delay, rng, start_ms=link.start_ms)
            del self._reseed[n]
        size = len(frame.image.data)
        if self._jpeg_quality is not None and link.delay.size_dependent:
            size = jpeg_bytes(frame.rgb(), self._jpeg_quality)
        slot = link.offer(entry_ms, size)
        stats = self._stats[n]
        stats.offered += 1
        if slot is None:
            stats.dropped += 1
            return n, None
        item = Pending(float(slot), next(self._order), n, frame.generation_ms, payload)
        heapq.heappush(self._heap, item)
        return n, item

    @property
    def pending(self) -> int:
        """Frames in flight (accepted, not yet handed out)."""
        return len(self._heap)

    def next_due_ms(self) -> float | None:
        """Delivery time of the next frame in flight; None when none is."""
        return self._heap[0].delivery_ms if self._heap else None

    def pop_due(self, now_ms: float) -> list[Pending]:
        """Every frame whose delivery slot is at or before ``now_ms``, in delivery order;
        each counts as delivered."""
        out = []
        while self._heap and self._heap[0].delivery_ms <= now_ms:
            item = heapq.heappop(self._heap)
            self._stats[item.camera_id].delivered += 1
            out.append(item)
        return out
