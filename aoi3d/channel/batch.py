"""Vectorised batch simulation of N independent D/G/1/0 camera links on the slot grid.

Camera (link) i generates a frame at slots ``phase_ms[i] + j·period_ms`` (j = 0, 1, …) below
``duration_ms``. The rule is the one of ``Link``: with Ys = delay_slots(Y), an accepted frame
at slot g is delivered at g + Ys, and the next accepted frame is the first one generated at or
after that slot, i.e. K = ceil(Ys / C) periods later. So the accepted frames are the running
sums of K over one Y draw per accepted frame, taken in order from the link's own stream
(``camera_rngs``) — the same draws ``Link.offer`` makes, without a loop over frames or slots.

A channel that changes (``regimes:``, ``trace:``, ``cell:``; :mod:`aoi3d.channel.varying`)
is simulated frame by frame with the links' own servers, the ones ``Link`` uses; a ``cell:``
channel's links take their frames in the order (generation slot, link), the order a live
service offers frames of one slot in when the cameras publish in camera order.

Link i serves the i-th training camera (camera id i + 1 of the rig; id 0 is held out).
"""

from __future__ import annotations

import heapq
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from aoi3d.channel.delay import DelayDistribution, delay_slots
from aoi3d.channel.link import camera_rngs
from aoi3d.channel.varying import DEFAULT_FRAME_BYTES, Channel, parse_channel

#: A frame's size in bytes: one number for every frame, or f(link index, generation slot).
FrameBytes = int | Callable[[int, int], int]


@dataclass(frozen=True, eq=False)
class ChannelRun:
    """The outcome of ``simulate``: per link, the accepted frames and their delivery slots."""

    delay_spec: str
    period_ms: int
    duration_ms: int
    seed: int
    phase_ms: np.ndarray  # (N,) int64, first generation slot of each link
    offered: np.ndarray  # (N,) int64, frames generated in [0, duration_ms)
    gen_ms: tuple[np.ndarray, ...]  # per link: generation slots of the accepted frames
    delivery_ms: tuple[np.ndarray, ...]  # per link: their delivery slots (may be >= duration)

    @property
    def n_cameras(self) -> int:
        return len(self.gen_ms)

    @property
    def accepted(self) -> np.ndarray:
        """(N,) frames accepted onto each link (delivered, or in flight at the end)."""
        return np.array([len(g) for g in self.gen_ms], dtype=np.int64)

    @property
    def dropped(self) -> np.ndarray:
        """(N,) frames dropped because the link was busy."""
        dropped: np.ndarray = self.offered - self.accepted
        return dropped

    @property
    def delivered(self) -> np.ndarray:
        """(N,) frames delivered at a slot below ``duration_ms``."""
        return np.array(
            [np.searchsorted(d, self.duration_ms) for d in self.delivery_ms], dtype=np.int64
        )

    @property
    def first_delivery_ms(self) -> np.ndarray:
        """(N,) float64 slot of each link's first delivery; NaN if none before the end."""
        out = np.full(self.n_cameras, np.nan)
        for i, d in enumerate(self.delivery_ms):
            if len(d) and d[0] < self.duration_ms:
                out[i] = d[0]
        return out

    def newest_ms(self, t_ms: int) -> np.ndarray:
        """(N,) U_n(t): generation slot of the newest frame delivered by slot t (NaN: none)."""
        out = np.full(self.n_cameras, np.nan)
        for i, (g, d) in enumerate(zip(self.gen_ms, self.delivery_ms, strict=True)):
            k = int(np.searchsorted(d, t_ms, side="right")) - 1
            if k >= 0:
                out[i] = g[k]
        return out

    def aoi_ms(self, t_ms: int) -> np.ndarray:
        """(N,) AoI Δ_n(t) = t − U_n(t) in ms; NaN before a link's first delivery."""
        return t_ms - self.newest_ms(t_ms)

    def aoi_trace(self, start_ms: int = 0, stop_ms: int | None = None) -> np.ndarray:
        """(N, stop − start) float64 AoI at every slot of [start, stop); NaN = unknown.

        Vectorised per link (``np.repeat`` of U over the slots between deliveries).
        """
        stop = self.duration_ms if stop_ms is None else int(stop_ms)
        start = int(start_ms)
        if not 0 <= start <= stop <= self.duration_ms:
            raise ValueError(
                f"need 0 <= start_ms <= stop_ms <= duration_ms ({self.duration_ms}), "
                f"got start_ms={start}, stop_ms={stop}"
            )
        slots = np.arange(start, stop, dtype=np.float64)
        out = np.full((self.n_cameras, stop - start), np.nan)
        for i, (g, d) in enumerate(zip(self.gen_ms, self.delivery_ms, strict=True)):
            edges = np.clip(np.append(d, stop), start, stop) - start
            first = int(edges[0])  # slots before the first delivery stay unknown
            newest = np.repeat(g.astype(np.float64), np.diff(edges))
            out[i, first:] = slots[first:] - newest
        return out


def _phases(phase_ms: int | Sequence[int] | np.ndarray, n_cameras: int) -> np.ndarray:
    phases = np.asarray(phase_ms)
    if phases.ndim == 0:
        phases = np.full(n_cameras, phases)
    if phases.shape != (n_cameras,):
        raise ValueError(f"phase_ms must be one value or {n_cameras} values, got {phases.shape}")
    if not np.issubdtype(phases.dtype, np.integer) and not np.all(phases == np.round(phases)):
        raise ValueError("phase_ms must be whole slots (ms)")
    phases = phases.astype(np.int64)
    if np.any(phases < 0):
        raise ValueError("phase_ms must be >= 0")
    return phases


def _positive_int(name: str, value: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise ValueError(f"{name} must be an int >= 1, got {value!r}")
    return int(value)


def _frame_sizes(frame_bytes: FrameBytes | None) -> Callable[[int, int], int]:
    if frame_bytes is None:
        return lambda _i, _g: DEFAULT_FRAME_BYTES
    if callable(frame_bytes):
        return frame_bytes
    size = _positive_int("frame_bytes", frame_bytes)
    return lambda _i, _g: size


def _simulate_changing(channel: Channel, period: int, n: int, duration: int, seed: int,
                       phases: np.ndarray, offered: np.ndarray,
                       frame_bytes: FrameBytes | None) -> tuple[list[np.ndarray],
                                                                list[np.ndarray]]:
    """Frame by frame, with the servers ``Link`` uses (the same draws in the same order)."""
    rngs = camera_rngs(seed, n)
    cell = channel.new_cell(rngs[0]) if channel.shared else None
    servers = [channel.server(rng, cell=cell) for rng in rngs]
    size_of = _frame_sizes(frame_bytes)
    gens: list[list[int]] = [[] for _ in range(n)]
    deliveries: list[list[int]] = [[] for _ in range(n)]
    busy = [-(2**62)] * n
    if not channel.shared:
        for i in range(n):
            server, g_list, d_list = servers[i], gens[i], deliveries[i]
            g = int(phases[i])
            while g < duration:
                d = g + server.slots(g, size_of(i, g))
                g_list.append(g)
                d_list.append(d)
                g += -(-(d - g) // period) * period  # the first frame at or after d
    else:
        # every link's frames in (slot, link) order through the one cell
        heap = [(int(phases[i]), i) for i in range(n) if offered[i] > 0]
        heapq.heapify(heap)
        while heap:
            g, i = heapq.heappop(heap)
            if g >= busy[i]:
                d = g + servers[i].slots(g, size_of(i, g))
                busy[i] = d
                gens[i].append(g)
                deliveries[i].append(d)
            if g + period < duration:
                heapq.heappush(heap, (g + period, i))
    return ([np.asarray(x, dtype=np.int64) for x in gens],
            [np.asarray(x, dtype=np.int64) for x in deliveries])


def simulate(
    delay: Channel | DelayDistribution | str,
    period_ms: int,
    n_cameras: int,
    duration_ms: int,
    seed: int,
    phase_ms: int | Sequence[int] | np.ndarray = 0,
    frame_bytes: FrameBytes | None = None,
) -> ChannelRun:
    """Simulate ``n_cameras`` links for slots [0, duration_ms); one stream per link from
    ``camera_rngs(seed, n_cameras)``, consumed exactly as ``Link.offer`` consumes it.

    ``frame_bytes``: each frame's size (only a trace channel reads it; default 12 kB), one
    number or ``f(link index, generation slot)``."""
    channel = parse_channel(delay)
    period = _positive_int("period_ms", period_ms)
    n = _positive_int("n_cameras", n_cameras)
    duration = _positive_int("duration_ms", duration_ms)
    phases = _phases(phase_ms, n)
    offered = np.maximum(0, -(-(duration - phases) // period))  # ceil((T − φ) / C)
    dist = channel.stationary
    if dist is None:
        gens, deliveries = _simulate_changing(channel, period, n, duration, int(seed), phases,
                                              offered, frame_bytes)
        return ChannelRun(delay_spec=channel.spec, period_ms=period, duration_ms=duration,
                          seed=int(seed), phase_ms=phases, offered=offered.astype(np.int64),
                          gen_ms=tuple(gens), delivery_ms=tuple(deliveries))
    gens = []
    deliveries = []
    for rng, phase, n_frames in zip(camera_rngs(seed, n), phases, offered, strict=True):
        # At most one draw per offered frame is needed; only the leading ones are used, in the
        # order Link.offer would make them.
        ys = delay_slots(dist.sample(rng, int(n_frames)))
        k = -(-ys // period)  # periods until the next accepted frame
        index = np.concatenate(([0], np.cumsum(k[:-1]))) if n_frames else ys
        m = int(np.searchsorted(index, n_frames))  # accepted frames: index < n_frames
        gen = phase + index[:m] * period
        gens.append(gen)
        deliveries.append(gen + ys[:m])
    return ChannelRun(
        delay_spec=dist.spec,
        period_ms=period,
        duration_ms=duration,
        seed=int(seed),
        phase_ms=phases,
        offered=offered.astype(np.int64),
        gen_ms=tuple(gens),
        delivery_ms=tuple(deliveries),
    )
