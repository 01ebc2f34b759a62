"""The recorder on a full disk (issue 44), on a real filesystem: a tmpfs of a few hundred KiB
that each test mounts (and skips, saying why, where mounting is not permitted). When the disk
fills the recording stops, the file written so far is a whole MCAP — summary and index, from
the disk space held back for it — or, when even that does not fit, cut at its last whole
message and read to there; the failure shows in GET /status, /readyz, a metric (for the alert
AoI3DRecordingFailed); the pipeline beside it goes on. With a segment cap the recording
rotates until the disk fills, then stops the same way."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from mcap.reader import make_reader

from services.kit.membus import MemoryBus
from services.kit.settings import CommonSettings
from services.recorder import sink
from services.recorder.app import create_app
from services.recorder.core import Recording, segments
from services.recorder.recording import load
from services.recorder.settings import Settings
from tests.support.metrics import metric
from tests.support.recording import RUN, K, frame, small_disk
from tests.support.waits import wait_for


def _fill(rec: Recording, n: int = 3000) -> int:
    """Deliveries of ~1.3 kB of incompressible pixels until the recording stops; how many
    were recorded."""
    for i in range(n):
        rec.write(K.edge_frame(1 + i % 2), frame(1 + i % 2, 30.0 * i, delivery_ms=30.0 * i + 1,
                                                 seed=i), log_ns=i)
        if not rec.active:
            return i
    raise AssertionError("the disk never filled")


def _whole(path: Path) -> int:
    """The messages of a whole MCAP (its summary read, every chunk index followed)."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.chunk_indexes, path
        count = sum(1 for _ in reader.iter_messages())
    assert summary.statistics.message_count == count
    return count


def test_a_full_disk_finishes_the_file_whole_in_the_space_held_for_it(tmp_path: Path) -> None:
    with small_disk(tmp_path, 512) as disk:
        rec = Recording(disk / "run.mcap", chunk_bytes=16 << 10)
        assert (disk / ".run.mcap.reserve").is_file()  # the space held for the summary
        written = _fill(rec)
        status = rec.close()
        assert status.state == "failed" and status.whole is True, status
        assert "disk is full" in status.error and "finished whole" in status.error
        assert str(disk / "run.mcap") in status.error
        assert not (disk / ".run.mcap.reserve").exists()
        messages = _whole(disk / "run.mcap")
        # every recorded bus message is in it (4 MCAP messages a delivery), and one more
        # partly: the one being written when the disk filled
        assert written * 4 <= messages <= written * 4 + 4, (written, messages)
        got = load(disk / "run.mcap")
        assert got.cut_short == [] and not got.refused
        deliveries = got.sites["site1"].deliveries
        assert len(deliveries) >= written and got.sites["site1"].frames_without_pixels == 0
        assert status.bytes_written == (disk / "run.mcap").stat().st_size


def test_when_the_disk_fills_faster_than_a_chunk_the_file_is_cut_at_a_whole_message(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # another writer takes the room the recording counted on: it sees room for every chunk
    # and holds nothing back, so a write meets the full disk
    monkeypatch.setattr(sink.Sink, "room", lambda self, message_bytes: True)
    monkeypatch.setattr(sink.Sink, "reserve", lambda self: None)
    with small_disk(tmp_path, 256) as disk:
        rec = Recording(disk / "run.mcap", chunk_bytes=16 << 10)
        written = _fill(rec)
        status = rec.close()
        assert status.state == "failed" and status.whole is False, status
        assert "cut at its last whole message" in status.error and "mcap recover" in status.error
        got = load(disk / "run.mcap")  # read to the cut, which it names
        assert got.cut_short and str(disk / "run.mcap") in got.cut_short[0]
        assert not got.refused
        n = len(got.sites["site1"].deliveries)
        assert 0 < n <= written and got.sites["site1"].frames_without_pixels == 0


def test_with_a_segment_cap_it_rotates_until_the_disk_fills_then_stops(tmp_path: Path) -> None:
    with small_disk(tmp_path, 1024) as disk:
        rec = Recording(disk / "run.mcap", max_bytes=160 << 10, chunk_bytes=16 << 10)
        _fill(rec)
        status = rec.close()
        files = segments(disk / "run.mcap")
        assert status.state == "failed" and status.whole is True, status
        assert [str(f) for f in files] == status.segments and len(files) >= 3
        assert not any(p.name.endswith(".reserve") for p in disk.iterdir())
        for f in files:  # every segment, the one the disk filled in too, is a whole MCAP
            assert _whole(f) > 0
        assert len(load(disk / "run.mcap").sites["site1"].deliveries) > 100


def test_the_service_shows_the_failure_and_the_pipeline_goes_on(tmp_path: Path) -> None:
    from aoi3d.clock import SimClock
    from services.network.app import create_app as network_app
    from services.network.settings import Settings as NetworkSettings

    bus = MemoryBus()
    common = CommonSettings(run_id=RUN, cameras=2, files_roots=[str(tmp_path)])
    clock = SimClock(time.time(), 1.0)
    delivered: list[str] = []
    bus.subscribe(K.edge_frames, lambda key, payload: delivered.append(key))
    with small_disk(tmp_path, 384) as disk, \
            TestClient(create_app(Settings(common=common, path=disk / "run.mcap",
                                           chunk_bytes=16 << 10), bus=bus)) as rec, \
            TestClient(network_app(NetworkSettings(common=common, delay="const:1"), bus=bus,
                                   clock=clock)) as net:
        assert rec.get("/status").json()["state"] == "recording"
        assert metric(rec.get("/metrics").text, "aoi3d_recorder_failed") == 0

        def publish(i: int) -> None:  # a camera frame through the network: an edge frame
            time.sleep(0.002)
            bus.publish(K.cam_frame(1 + i % 2), frame(1 + i % 2, clock.now_ms(), seed=i))

        i = 0
        while rec.get("/status").json()["state"] == "recording":
            for _ in range(20):
                publish(i)
                i += 1
            assert i < 4000, "the disk never filled"
        view = wait_for(lambda: (v := rec.get("/status").json())["state"] == "failed" and v,
                        what="the recording to fail")
        assert "disk is full" in view["error"] and view["whole"] is True, view
        assert rec.get("/recording").json() == view
        ready = rec.get("/readyz")
        assert ready.status_code == 200 and "disk is full" in ready.json()["reason"]
        text = rec.get("/metrics").text
        assert metric(text, "aoi3d_recorder_failed") == 1
        assert metric(text, "aoi3d_recorder_failures_total", reason="disk_full") == 1
        assert metric(text, "aoi3d_recorder_recording") == 0
        # the pipeline goes on: the network still delivers what the cameras send
        before = len(delivered)
        for _ in range(20):
            publish(i)
            i += 1
        wait_for(lambda: len(delivered) >= before + 10, what="deliveries after the failure")
        assert net.get("/readyz").status_code == 200
        assert _whole(disk / "run.mcap") > 0
        # a new recording elsewhere takes the failure off the gauge
        r = rec.post("/recording/start", json={"path": str(tmp_path / "b.mcap")})
        assert r.status_code == 200, r.text
        assert metric(rec.get("/metrics").text, "aoi3d_recorder_failed") == 0
        rec.post("/recording/stop")
    shutil.rmtree(tmp_path / "disk", ignore_errors=True)
