"""The cameras' uplinks: delay distributions, channels that change (regimes, traces, a
shared cell), the per-camera D/G/1/0 link, the vectorised batch simulation, its statistics
and the exact theory they are checked against."""

from aoi3d.channel.batch import ChannelRun, simulate
from aoi3d.channel.delay import (
    ACCEPTED_FORMS,
    ConstantDelay,
    DelayDistribution,
    DelaySpecError,
    ExponentialDelay,
    GammaDelay,
    LogNormalDelay,
    UniformDelay,
    delay_slots,
    parse_delay,
)
from aoi3d.channel.link import Link, camera_rngs, make_links
from aoi3d.channel.stats import aoi_slot_counts, channel_statistics
from aoi3d.channel.theory import ChannelTheory, aoi_cdf, aoi_pmf, channel_theory, slot_delay_pmf
from aoi3d.channel.varying import (
    CHANNEL_FORMS,
    DEFAULT_FRAME_BYTES,
    BurstChannel,
    CellChannel,
    Channel,
    ChannelSpecError,
    RegimeChannel,
    StationaryChannel,
    TraceChannel,
    parse_channel,
    trace_path_of,
    transmission_summary,
)

__all__ = [
    "ACCEPTED_FORMS",
    "CHANNEL_FORMS",
    "DEFAULT_FRAME_BYTES",
    "BurstChannel",
    "CellChannel",
    "Channel",
    "ChannelRun",
    "ChannelSpecError",
    "ChannelTheory",
    "ConstantDelay",
    "DelayDistribution",
    "DelaySpecError",
    "ExponentialDelay",
    "GammaDelay",
    "Link",
    "LogNormalDelay",
    "RegimeChannel",
    "StationaryChannel",
    "TraceChannel",
    "UniformDelay",
    "aoi_cdf",
    "aoi_pmf",
    "aoi_slot_counts",
    "camera_rngs",
    "channel_statistics",
    "channel_theory",
    "delay_slots",
    "make_links",
    "parse_channel",
    "parse_delay",
    "simulate",
    "slot_delay_pmf",
    "trace_path_of",
    "transmission_summary",
]
