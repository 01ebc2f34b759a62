"""Channels that change: the channel spec of a link, stationary or not.

A **channel spec** says how long each accepted frame stays on its camera's D/G/1/0 link. It
is one of:

- a delay distribution (``exp:60``, ``const:40``, … — :mod:`aoi3d.channel.delay`): every
  frame draws Y afresh, whatever its size and whenever it is sent (stationary);
- ``regimes:SPEC@DUR,SPEC@DUR,…`` — piecewise regimes that cycle: the first SPEC (a delay
  distribution) holds for DUR, then the next, …, then the first again. DUR is ``10s``,
  ``500ms`` or a number of ms. A frame draws Y from the regime in force at the slot it enters
  its link, e.g. ``regimes:exp:20@10s,exp:200@10s``;
- ``trace:PATH[,offset=MS][,spread=MS][,scale=S]`` — a mahimahi uplink trace replayed per
  camera (each camera its own subchannel, M = N). A frame of B bytes entering at slot g is
  delivered at the ⌈B/1500⌉-th delivery opportunity at or after g that its link has not used,
  at least one slot later. Each camera plays the trace from its own phase, ``offset`` plus a
  uniform draw in [0, ``spread``) from its own random stream (``spread`` defaults to the
  trace's length; ``spread=0`` puts every camera at ``offset``);
- ``burst:GOOD,BAD[,good=DUR][,bad=DUR]`` — a Gilbert–Elliott channel: each link is in a
  good or a bad state, draws Y from GOOD or BAD (delay distributions), and stays in a state
  for an exponential time of mean ``good`` (default 5s) or ``bad`` (default 1s), drawn from
  its own stream; every link starts good, e.g. ``burst:exp:20,exp:300,good=4s,bad=1s``;
- ``cell:PATH[,offset=MS][,spread=MS][,scale=S]`` — the cameras share one cell's capacity:
  one trace, one FIFO of packets. A frame's packets take the next opportunities not used by
  any camera's earlier frame, in the order the frames were offered. The cell's phase is
  ``offset`` plus a draw in [0, ``spread``) from the first camera's stream.

``scale=S`` stretches the trace's time axis by S (S = 2: half the capacity, transmission
times about twice as long). The trace format (mahimahi): one integer a line, a time in ms
from the start of the trace; each line is one opportunity for one 1500-byte packet; a
repeated time is several packets in that ms; the trace repeats with the period of its last
time. Frames without a size (the stationary kinds never need one) count as
:data:`DEFAULT_FRAME_BYTES`.

**Which trace model.** ``trace:`` is right when every camera has an uplink of its own — its
own modem, or the paper's M = N orthogonal subchannels — and the trace stands for one such
uplink's capacity; the cameras' delays are then independent replays of one kind of link.
``cell:`` is right when the cameras sit behind one cellular uplink (one modem, or one cell
sector whose scheduler shares its capacity): their frames compete, so with N cameras each
sees about N times the delay of one camera alone.

Time. A channel is *started* at a slot (``start_ms``): the regimes' cycle and the trace's
playback count from there. The virtual-clock experiments and :func:`aoi3d.channel.simulate`
start at slot 0; the network service starts a channel at the clock's time when it is set.
Every link is served by a :class:`Server` made by :meth:`Channel.server`; ``Link`` and
``simulate`` use the same servers, so they agree draw for draw.

The package's modules, each importing only those listed before it: :mod:`.spec` (the forms,
:class:`ChannelSpecError`, durations, byte sizes), :mod:`.traces` (trace I/O: :func:`load_trace`,
:class:`CellQueue`), :mod:`.base` (:class:`Channel`, :class:`Server`), one module per channel
family — :mod:`.stationary`, :mod:`.regimes`, :mod:`.burst`, :mod:`.trace` (``trace:`` and
``cell:``) — then :mod:`.frames` (PNG / JPEG frame sizes) and :mod:`.parse` (:func:`parse_channel`).
"""

from aoi3d.channel.varying.base import Channel, Server
from aoi3d.channel.varying.burst import BurstChannel
from aoi3d.channel.varying.frames import FRAME_ENCODINGS, check_frame_encoding, jpeg_bytes
from aoi3d.channel.varying.parse import parse_channel, trace_path_of
from aoi3d.channel.varying.regimes import RegimeChannel
from aoi3d.channel.varying.spec import (
    CHANNEL_FORMS,
    DEFAULT_FRAME_BYTES,
    MAX_REGIMES,
    MAX_TRACE_BYTES,
    MAX_TRACE_LINES,
    MAX_TRACE_PERIOD_MS,
    PACKET_BYTES,
    ChannelSpecError,
)
from aoi3d.channel.varying.stationary import StationaryChannel
from aoi3d.channel.varying.trace import CellChannel, TraceChannel, transmission_summary
from aoi3d.channel.varying.traces import CellQueue, Trace, load_trace

__all__ = [
    "CHANNEL_FORMS",
    "DEFAULT_FRAME_BYTES",
    "FRAME_ENCODINGS",
    "MAX_REGIMES",
    "MAX_TRACE_BYTES",
    "MAX_TRACE_LINES",
    "MAX_TRACE_PERIOD_MS",
    "PACKET_BYTES",
    "BurstChannel",
    "CellChannel",
    "CellQueue",
    "Channel",
    "ChannelSpecError",
    "RegimeChannel",
    "Server",
    "StationaryChannel",
    "Trace",
    "TraceChannel",
    "check_frame_encoding",
    "jpeg_bytes",
    "load_trace",
    "parse_channel",
    "trace_path_of",
    "transmission_summary",
]
