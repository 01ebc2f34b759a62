"""Bounded work on a trace (issue 44): its size, length and period are capped, its summary
costs O(its opportunities) whatever its period, the cache of loaded traces is capped in
bytes, and a refused channel change leaves the network's links and config untouched."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

from aoi3d.channel import ChannelSpecError, parse_channel, transmission_summary
from aoi3d.channel.varying import MAX_TRACE_PERIOD_MS, spec, traces
from services.network.core import ChannelConfigError, NetworkCore
from tests.support.timeouts import timeout_scale

SCALE = timeout_scale()


def _write(path: Path, times: list[float] | str) -> Path:
    path.write_text(times if isinstance(times, str) else "\n".join(f"{t:.0f}" for t in times))
    return path


def test_a_trace_with_a_period_of_a_day_is_summarised_at_once(tmp_path: Path) -> None:
    # opportunities a day apart: a frame every 30 ms for 30 days is 86 million offers, but
    # at most 43,200 are accepted (each waits up to MAX_DELAY_MS): the work is those
    day = _write(tmp_path / "day.up", [0, 1, MAX_TRACE_PERIOD_MS])
    channel = parse_channel(f"trace:{day},spread=0")
    t = time.perf_counter()
    month = transmission_summary(channel, 12_000, 30, duration_ms=30 * MAX_TRACE_PERIOD_MS)
    took = time.perf_counter() - t
    assert took < 1.0 * SCALE, f"{took:.2f} s"
    assert month["drop_ratio"] == pytest.approx(1 - 43_200 / (30 * 2_880_000), abs=1e-5)
    got = transmission_summary(channel, 12_000, 30)
    assert got["mean_ms"] == 60_000 and 0.99 < got["drop_ratio"] < 1.0
    t = time.perf_counter()
    assert channel.mean_ms == got["mean_ms"]
    assert channel.mean_ms == got["mean_ms"]  # cached: once per channel
    assert time.perf_counter() - t < 1.0 * SCALE


@pytest.mark.parametrize(("text", "why"), [
    ("0\n100000000000000000000\n", "over the 86400000 ms"),
    ("0\n86400001\n", "over the 86400000 ms"),
    ("0\n1e400\n", "non-decreasing times"),
    ("0\nnan\n", "non-decreasing times"),
    ("0\n-1\n", "non-decreasing times"),
    ("", "no opportunities"),
    ("0 1\n2 3\n", "no opportunities"),
    ("\x00\xff\xfe\x00", "not a mahimahi trace"),
])
def test_a_bad_trace_is_one_line_naming_the_file(tmp_path: Path, text: str, why: str) -> None:
    bad = tmp_path / "bad.up"
    bad.write_bytes(text.encode("latin-1"))
    with pytest.raises(ChannelSpecError) as err:
        parse_channel(f"trace:{bad}")
    assert why in str(err.value) and str(bad) in str(err.value)


def test_a_scale_that_stretches_a_trace_past_a_day_is_refused(tmp_path: Path) -> None:
    path = _write(tmp_path / "t.up", [0, 1_000_000])
    assert parse_channel(f"trace:{path},scale=86").trace.period_ms == 86_000_000
    with pytest.raises(ChannelSpecError, match="over the 86400000 ms"):
        parse_channel(f"trace:{path},scale=87")


def test_too_many_bytes_or_lines_are_refused_before_being_kept(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = _write(tmp_path / "t.up", list(range(0, 1000)))
    monkeypatch.setattr(traces, "MAX_TRACE_BYTES", 100)
    with pytest.raises(ChannelSpecError, match="bytes, over the 100"):
        parse_channel(f"trace:{path}")
    monkeypatch.setattr(traces, "MAX_TRACE_BYTES", spec.MAX_TRACE_BYTES)
    monkeypatch.setattr(traces, "MAX_TRACE_LINES", 999)
    with pytest.raises(ChannelSpecError, match="over 999 lines"):
        parse_channel(f"trace:{path}")


def test_the_trace_cache_holds_at_most_its_bytes(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    path = _write(tmp_path / "t.up", list(range(0, 10_000)))  # 80 kB loaded
    monkeypatch.setattr(traces, "_TRACES", type(traces._TRACES)())
    monkeypatch.setattr(traces, "MAX_TRACE_CACHE_BYTES", 250_000)
    for k in range(1, 40):  # each scale is a trace of its own in the cache
        traces.load_trace(path, 1.0 + k / 100)
        assert traces.cached_trace_bytes() <= 250_000
    assert len(traces._TRACES) == 3
    newest = traces.load_trace(path, 1.39)
    assert traces.load_trace(path, 1.39) is newest  # still a hit


@pytest.mark.parametrize("delay", ["trace:{t}", "cell:{t}"])
def test_a_channel_that_cannot_start_changes_nothing(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, delay: str) -> None:
    trace = _write(tmp_path / "t.up", list(range(0, 400, 3)))
    core = NetworkCore(3, delay="const:40", per_camera={2: "exp:10"}, seed=4)
    before = (core.config, core.started_ms, [(s.delay.spec, s.offered)
                                             for s in core.link_stats(0.0)])
    rngs = [core._links[n].rng.bit_generator.state for n in core.camera_ids]

    def broken(self, rng, **kw):
        rng.integers(0, 10)  # consumes the stream it is given, then fails
        raise ValueError("high is out of bounds for int64")
    from aoi3d.channel.varying import trace as trace_module
    monkeypatch.setattr(trace_module.TraceChannel, "server", broken)
    monkeypatch.setattr(trace_module.CellChannel, "server", broken)
    with pytest.raises(ChannelConfigError, match="cannot start: high is out of bounds"):
        core.update(delay=delay.format(t=trace), per_camera={}, seed=5, now_ms=500.0)
    assert (core.config, core.started_ms, [(s.delay.spec, s.offered)
                                           for s in core.link_stats(0.0)]) == before
    assert [core._links[n].rng.bit_generator.state for n in core.camera_ids] == rngs
    assert core._reseed == {}
    assert np.isfinite(core.offer("t/cam/1/frame", _frame(1), 0.0)[1].delivery_ms)


def _frame(camera_id: int) -> bytes:
    from tests.support.network import frame
    return frame(camera_id, 0.0)


def test_a_rewritten_trace_has_its_own_mean(tmp_path: Path) -> None:
    # the same path, the same number of opportunities and period: only the times differ, and
    # the mean delay read from the rewritten file is the new one (it was keyed on path, n and
    # period, so the first file's mean stood)
    path = tmp_path / "link.up"
    _write(path, [*([0] * 20), 1000])
    first = parse_channel(f"trace:{path},spread=0").mean_ms
    before = path.stat()
    _write(path, [*range(0, 1000, 50), 1000])
    os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns + 1_000_000_000))  # a later write
    second = parse_channel(f"trace:{path},spread=0").mean_ms
    assert second != first
    assert second == transmission_summary(parse_channel(f"trace:{path},spread=0"), 12_000,
                                          30)["mean_ms"]
