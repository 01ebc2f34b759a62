"""The spec parser: any channel spec's text → its :class:`Channel`."""

from __future__ import annotations

from aoi3d.channel.delay import DelayDistribution, DelaySpecError, parse_delay
from aoi3d.channel.varying.base import Channel
from aoi3d.channel.varying.burst import parse_burst
from aoi3d.channel.varying.regimes import parse_regimes
from aoi3d.channel.varying.spec import ChannelSpecError
from aoi3d.channel.varying.stationary import StationaryChannel
from aoi3d.channel.varying.trace import parse_trace


def trace_path_of(spec: str) -> str | None:
    """The trace path a ``trace:`` or ``cell:`` spec names (read from the text alone, no file
    touched: a service checks where it lies before reading it); None for the other kinds."""
    kind, _, body = str(spec).strip().partition(":")
    if kind.strip().lower() not in ("trace", "cell"):
        return None
    return body.split(",")[0].strip()


def parse_channel(spec: str | Channel | DelayDistribution) -> Channel:
    """Parse any channel spec (a delay distribution, ``regimes:``, ``trace:``, ``cell:``);
    a channel passes through, a distribution is wrapped. Raises ``DelaySpecError``."""
    if isinstance(spec, Channel):
        return spec
    if isinstance(spec, DelayDistribution):
        return StationaryChannel(spec)
    if not isinstance(spec, str):
        raise DelaySpecError(f"expected a string, got {type(spec).__name__}", repr(spec))
    text = spec.strip()
    kind, _, body = text.partition(":")
    kind = kind.strip().lower()
    if kind == "regimes":
        return parse_regimes(body, spec)
    if kind == "burst":
        return parse_burst(body, spec)
    if kind in ("trace", "cell"):
        return parse_trace(kind, body, spec)
    try:
        return StationaryChannel(parse_delay(text))
    except ChannelSpecError:
        raise
    except DelaySpecError as err:
        raise ChannelSpecError(err.problem, spec) from None
