"""The recorder: bus messages → MCAP, read back with the ``mcap`` reader and every message
decoded with the schema stored in the file; the size cap (rotation) and a full disk (a real
one: a 256 KiB tmpfs mounted by the test); the REST API over a MemoryBus."""

from __future__ import annotations

import contextlib
import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap_protobuf.decoder import DecoderFactory

from services.kit.codec import encode_frame
from services.kit.membus import MemoryBus
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.settings import CommonSettings
from services.recorder.app import create_app
from services.recorder.core import Recording, segments
from services.recorder.settings import Settings
from tests.support.recording import (
    RUN,
    H,
    K,
    W,
    camera,
    frame,
    noise_image,
    one_of_each,
    small_disk,
)
from tests.support.waits import wait_for


def read_all(path: Path) -> list[tuple[str, str, object, int]]:
    """(topic, schema name, decoded message, log time) of every message, decoded with the
    schema stored in the file."""
    out = []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            assert schema.encoding == "protobuf" and channel.message_encoding == "protobuf"
            out.append((channel.topic, schema.name, decoded, message.log_time))
    return out


def test_every_message_decodes_with_its_schema_and_images_are_foxglove(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    rec = Recording(path, metadata={"run_id": RUN, "time_scale": "0.1"})
    sent = one_of_each()
    for i, (key, payload) in enumerate(sent):
        rec.write(key, payload, log_ns=1_000 + i)
    status = rec.close()
    assert status.state == "stopped" and status.messages == len(sent)
    got = read_all(path)
    topics = Counter(t for t, *_ in got)
    assert topics == Counter({"/site1/cam1/image": 1, "/site1/cam1/calibration": 1, "/tf": 2,
                              "/site1/delivery": 1, "/site1/truth/image": 1,
                              "/site1/truth/calibration": 1, "/site1/truth": 1,
                              "/site1/decision": 1, "/site1/render": 1,
                              "/site1/render/image": 1, "/site1/quality": 1,
                              "/site1/outcome": 1})
    schemas = {t: s for t, s, *_ in got}
    assert schemas["/site1/cam1/image"] == "foxglove.CompressedImage"
    assert schemas["/site1/cam1/calibration"] == "foxglove.CameraCalibration"
    assert schemas["/tf"] == "foxglove.FrameTransform"
    assert schemas["/site1/render/image"] == "foxglove.CompressedImage"
    assert schemas["/site1/decision"] == "aoi3d.v1.Decision"
    by_topic = {t: m for t, _, m, _ in got}
    # the image is the wire's PNG, byte for byte; the delivery keeps the rest, pixels left out
    wire = pb.Frame.FromString(sent[0][1])
    img = by_topic["/site1/cam1/image"]
    assert img.format == "png" and img.data == wire.image.data
    assert img.frame_id == "site1/cam1"
    assert (img.timestamp.seconds * 10**9 + img.timestamp.nanos) == round(wire.generation_ms
                                                                         * 1e6)
    delivery = by_topic["/site1/delivery"]
    assert delivery.delivery_ms == wire.delivery_ms and delivery.image.data == b""
    assert delivery.image.width == W and list(delivery.pose.c2w) == list(wire.pose.c2w)
    calib = by_topic["/site1/cam1/calibration"]
    assert list(calib.K) == [20.0, 0, W / 2, 0, 20.0, H / 2, 0, 0, 1]
    # the pose in the optical convention: z forward = aoi3d's −z (the camera looks at target)
    tf = next(m for t, _, m, _ in got if t == "/tf" and m.child_frame_id == "site1/cam1")
    from scipy.spatial.transform import Rotation

    q = tf.rotation
    rot = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    c2w = camera().c2w
    assert np.allclose(rot[:, 2], -c2w[:3, 2]) and np.allclose(rot[:, 0], c2w[:3, 0])
    assert np.allclose([tf.translation.x, tf.translation.y, tf.translation.z], c2w[:3, 3])
    decision = by_topic["/site1/decision"]
    assert math.isnan(decision.aoi_ms[1]) and decision.selected[0].generation_ms == 260.0
    assert by_topic["/site1/render"].seed == 3
    with open(path, "rb") as f:
        meta = {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
    assert meta["aoi3d"]["run_id"] == RUN and meta["aoi3d"]["segment"] == "1"


def test_a_message_the_decoders_refuse_is_not_recorded(tmp_path: Path) -> None:
    from services.kit.rejected import Rejected

    rec = Recording(tmp_path / "run.mcap")
    for key, payload in [(K.decision, b"\xff\x00garbage"), (K.edge_frame(2), frame(3, 30.0)),
                         ("aoi3d/rec/site1/cam/1/frame", frame(1, 30.0))]:
        with pytest.raises(Rejected):
            rec.write(key, payload, log_ns=1)
    rec.write(K.decision, one_of_each()[2][1], log_ns=2)
    rec.close()
    assert [t for t, *_ in read_all(tmp_path / "run.mcap")] == ["/site1/decision"]


def test_size_cap_rotates_into_whole_segments(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    cap = 64 * 1024
    rec = Recording(path, max_bytes=cap)
    n = 120  # ~1.3 KiB of incompressible PNG each: ~160 KiB in all
    for i in range(n):
        rec.write(K.edge_frame(1 + i % 3), frame(1 + i % 3, 30.0 * i, delivery_ms=30.0 * i + 5,
                                                 seed=i), log_ns=i)
    status = rec.close()
    files = segments(path)
    assert [str(p) for p in files] == status.segments and len(files) >= 3
    assert files[1].name == "run.part2.mcap"
    deliveries = []
    for p in files:
        # each a whole MCAP (summary and footer) within the cap plus one chunk and its summary
        assert p.stat().st_size <= cap + rec.chunk_bytes + 16 * 1024, p.stat().st_size
        got = read_all(p)
        deliveries += [m.generation_ms for t, _, m, _ in got if t == "/site1/delivery"]
        with open(p, "rb") as f:
            assert make_reader(f).get_summary().statistics.message_count == len(got)
    assert deliveries == [30.0 * i for i in range(n)]  # nothing lost or doubled at a seam


def test_full_disk_stops_the_recording_with_a_clear_error(tmp_path: Path) -> None:
    with small_disk(tmp_path, 256) as disk:
        rec = Recording(disk / "run.mcap", chunk_bytes=16 * 1024)
        written = 0
        for i in range(1000):  # ~1.3 MiB offered to a 256 KiB disk
            rec.write(K.edge_frame(1), frame(1, 30.0 * i, delivery_ms=30.0 * i + 1, seed=i),
                      log_ns=i)
            if not rec.active:
                break
            written += 1
        assert rec.status.state == "failed", "the disk never filled"
        assert "disk is full" in rec.status.error and "run.mcap" in rec.status.error
        assert 50 < written < 1000
        status = rec.close()  # nothing more to do: it stays failed
        assert status.state == "failed"
        # what reached the disk before (whole chunks) reads back with a streaming reader
        records = 0
        with open(disk / "run.mcap", "rb") as f, contextlib.suppress(Exception):
            for _record in StreamReader(f, skip_magic=False).records:
                records += 1
        assert records > 10


def _client(bus: MemoryBus, tmp_path: Path, **over) -> TestClient:
    settings = Settings(common=CommonSettings(run_id=RUN, files_roots=[str(tmp_path)]), **over)
    return TestClient(create_app(settings, bus=bus))


def test_rest_start_and_stop_record_the_bus(tmp_path: Path) -> None:
    bus = MemoryBus()
    with _client(bus, tmp_path) as client:
        assert client.get("/recording").json()["recording"] is False
        bus.publish(K.decision, one_of_each()[2][1])  # idle: not recorded
        target = tmp_path / "runs" / "a.mcap"
        r = client.post("/recording/start", json={"path": str(target)})
        assert r.status_code == 200, r.text
        assert client.post("/recording/start", json={"path": str(target)}).status_code == 409
        r = client.post("/recording/start", json={"path": "/etc/x.mcap"})
        assert r.status_code in (409, 422)
        for key, payload in one_of_each():
            bus.publish(key, payload)
        bus.publish("aoi3d/rec/site2/decision", b"\x01garbage")  # counted, not recorded
        wait_for(lambda: client.get("/recording").json()["messages"] >= 6,
                 what="6 messages recorded")
        r = client.post("/recording/stop")
        assert r.status_code == 200 and r.json()["state"] == "stopped", r.text
        assert "aoi3d_messages_rejected_total" in client.get("/metrics").text
    topics = {t for t, *_ in read_all(target)}
    assert "/site1/cam1/image" in topics and "/site1/outcome" in topics
    assert sum(t == "/site1/decision" for t, *_ in read_all(target)) == 1


def test_rest_refuses_a_path_outside_the_files_roots(tmp_path: Path) -> None:
    with _client(MemoryBus(), tmp_path) as client:
        r = client.post("/recording/start", json={"path": "/etc/aoi3d.mcap"})
        assert r.status_code == 422 and "AOI3D_FILES_ROOTS" in r.text
        assert client.post("/recording/stop").status_code == 409
        assert not Path("/etc/aoi3d.mcap").exists()


def test_full_disk_ends_the_recording_and_the_service_goes_on(tmp_path: Path) -> None:
    bus = MemoryBus()
    with small_disk(tmp_path, 128) as disk, \
            _client(bus, tmp_path, path=disk / "run.mcap", chunk_bytes=16 * 1024) as client:
        assert client.get("/recording").json()["state"] == "recording"
        for i in range(400):
            bus.publish(K.edge_frame(1), frame(1, 30.0 * i, delivery_ms=30.0 * i + 1, seed=i))
        view = wait_for(lambda: (v := client.get("/recording").json())["state"] == "failed"
                        and v, what="the recording to fail")
        assert "disk is full" in view["error"], view
        assert client.get("/healthz").status_code == 200
        r = client.get("/readyz")
        assert r.status_code == 200 and "disk is full" in r.json()["reason"]
        bus.publish(K.decision, one_of_each()[2][1])  # the service still takes messages
        # a new recording elsewhere works
        r = client.post("/recording/start", json={"path": str(tmp_path / "b.mcap")})
        assert r.status_code == 200, r.text
        bus.publish(K.decision, one_of_each()[2][1])
        wait_for(lambda: client.get("/recording").json()["messages"] >= 1, what="recorded")
        assert client.post("/recording/stop").json()["state"] == "stopped"


# ---------------------------------------------------------------- replay: the arrivals
def _decision(s: float, newest: dict[int, float], cams=(1, 2), selected=()) -> pb.Decision:
    return pb.Decision(decision_id=int(s), time_ms=s, camera_ids=list(cams), policy="all",
                       aoi_ms=[s - newest[c] if c in newest else math.nan for c in cams],
                       selected=[pb.FrameRef(camera_id=c, generation_ms=newest[c])
                                 for c in selected])


def _delivery(cam: int, gen: float, delivered: float) -> pb.Frame:
    return pb.Frame(camera_id=cam, generation_ms=gen, delivery_ms=delivered)


def test_arrivals_follow_the_schedulers_vectors() -> None:
    """A frame counts from its delivery stamp, unless the first decision after the stamp did
    not know it (it reached the scheduler late): then from the first decision that did."""
    from services.recorder.arrivals import arrivals
    from services.recorder.recording import SiteRecord

    rec = SiteRecord()
    rec.deliveries = [_delivery(1, 0.0, 10.0), _delivery(2, 5.0, 30.0),  # 2: late, at s = 30
                      _delivery(1, 30.0, 55.0), _delivery(2, 35.0, 70.0)]  # never known
    rec.decisions = [_decision(30.0, {1: 0.0}), _decision(60.0, {1: 30.0, 2: 5.0}),
                     _decision(90.0, {1: 30.0, 2: 5.0})]
    arr = arrivals(rec)
    assert arr.late == 1
    assert np.array_equal(arr.newest_at(30.0), [0.0, np.nan], equal_nan=True)
    assert np.array_equal(arr.newest_at(59.0), [30.0, np.nan], equal_nan=True)
    assert np.array_equal(arr.newest_at(60.0), [30.0, 5.0])
    assert np.array_equal(arr.newest_at(10_000.0), [30.0, 5.0])  # 35 never reached it
    assert arr.frame(2, 35.0).arrival_ms == math.inf and arr.frame(2, 5.0).arrival_ms == 60.0
    for d in rec.decisions:  # so every recorded vector comes back
        assert np.allclose(d.time_ms - arr.newest_at(d.time_ms), d.aoi_ms, equal_nan=True)


def test_frames_known_before_the_recording_enter_without_pixels() -> None:
    from services.recorder.arrivals import arrivals
    from services.recorder.recording import SiteRecord

    rec = SiteRecord()
    rec.deliveries = [_delivery(1, 40.0, 45.0)]
    rec.decisions = [_decision(30.0, {1: 0.0, 2: -30.0}), _decision(60.0, {1: 40.0, 2: -30.0})]
    arr = arrivals(rec)
    assert np.array_equal(arr.newest_at(30.0), [0.0, -30.0])
    assert arr.frame(2, -30.0).frame is None and arr.frame(1, 40.0).frame is not None


def test_replay_reproduces_selections_and_a_changed_policy_differs(tmp_path: Path) -> None:
    """Without scores: a recording of decisions under mat:10 replays to the same selections;
    under all, to more cameras on the same AoI vectors."""
    from services.recorder.recording import load
    from services.recorder.replay import replay

    _mat10_recording(tmp_path / "r.mcap")
    data = load(tmp_path / "r.mcap")
    same = replay(data, None, score=False)
    assert len(same.decisions) == 20 and same.selections_equal == 20
    assert all(d.aoi_equal for d in same.decisions)
    every = replay(data, "all", score=False)
    assert every.selections_equal < 20
    assert all(len(d.selected) == 2 for d in every.decisions)


def test_policies_pair_on_the_epochs_every_one_can_rebuild() -> None:
    """At the first decision camera 2's newest frame was delivered before the recording
    (no pixels): mat:20 leaves it out and can be rebuilt, all names it and cannot. The
    paired epochs are those both can rebuild, so --max-renders 1 with --policy all rebuilds
    the second decision for both rather than none for all."""
    from services.recorder.recording import Recorded, SiteRecord
    from services.recorder.replay import rebuildable_keys, replay

    site = SiteRecord()
    site.deliveries = [pb.Frame.FromString(frame(1, 25.0, delivery_ms=28.0)),
                       pb.Frame.FromString(frame(1, 55.0, delivery_ms=58.0)),
                       pb.Frame.FromString(frame(2, 40.0, delivery_ms=45.0))]
    site.decisions = [_decision(30.0, {1: 25.0, 2: -30.0}, selected=[1]),
                      _decision(60.0, {1: 55.0, 2: 40.0}, selected=[1])]
    for d in site.decisions:
        d.policy = "mat:20"
        key = (d.incarnation, d.decision_id)
        site.renders[key] = pb.Render(decision_id=d.decision_id, carry="fresh",
                                      frame_generation_ms=[d.selected[0].generation_ms],
                                      frame_camera_ids=[1])
        site.qualities[key] = pb.Quality(decision_id=d.decision_id, psnr_db=20.0)
    rec = Recorded(Path("r.mcap"), [], {}, {"site1": site})
    every = replay(rec, "all", score=False)
    assert [d.rebuildable for d in every.decisions] == [False, True]
    assert [d.skipped for d in every.decisions] == ["frames_not_recorded", None]
    assert [len(d.selected) for d in every.decisions] == [2, 2]
    assert [d.rebuildable for d in replay(rec, None, score=False).decisions] == [True, True]
    assert rebuildable_keys(rec, [None]) == {("site1", (0, 30)), ("site1", (0, 60))}
    assert rebuildable_keys(rec, [None, "all"]) == {("site1", (0, 60))}
    # only= keeps the rest out of the rebuild: the first decision is not even looked at
    only = replay(rec, "all", score=False, only={("site1", (0, 60))})
    assert [d.rebuildable for d in only.decisions] == [None, True]


@pytest.mark.parametrize("carry", ["warm", "fork"])
def test_scores_of_a_background_carry_are_refused_saying_how_to_record_one(carry: str) -> None:
    """A warm or fork model trains between jobs on the wall clock, which no recording holds:
    the replay cannot rebuild its renders and says so before anything runs (selections alone
    still replay)."""
    from services.recorder.recording import Recorded, SiteRecord
    from services.recorder.replay import replay

    site = SiteRecord()
    site.deliveries = [pb.Frame.FromString(frame(1, 25.0, delivery_ms=28.0))]
    site.decisions = [_decision(30.0, {1: 25.0}, selected=[1])]
    d = site.decisions[0]
    d.policy = "mat:20"
    key = (d.incarnation, d.decision_id)
    site.renders[key] = pb.Render(decision_id=d.decision_id, carry=carry,
                                  frame_generation_ms=[25.0], frame_camera_ids=[1])
    site.qualities[key] = pb.Quality(decision_id=d.decision_id, psnr_db=20.0)
    rec = Recorded(Path("r.mcap"), [], {}, {"site1": site})
    with pytest.raises(ValueError, match=rf"{carry} renders.*AOI3D_DISPATCHER_CARRY=stream or "
                                         r"fresh.*--no-score"):
        replay(rec, None)
    assert [x.rebuildable for x in replay(rec, None, score=False).decisions] == [True]


def _mat10_recording(path: Path) -> None:
    """20 decisions of two cameras under mat:10, their deliveries before them."""
    rec = Recording(path)
    newest: dict[int, float] = {}
    for k in range(1, 21):
        s = 30.0 * k
        for cam in (1, 2):
            gen = s - 2.0 - 7.0 * cam * (k % 3)
            if gen > newest.get(cam, -math.inf):
                rec.write(K.edge_frame(cam), frame(cam, gen, delivery_ms=s - 1.0, seed=k),
                          log_ns=k)
                newest[cam] = gen
        aoi = {c: s - g for c, g in newest.items()}
        d = _decision(s, newest, selected=[c for c in (1, 2) if aoi[c] < 10.0])
        d.policy = "mat:10"
        rec.write(K.decision, d.SerializeToString(), log_ns=k)
    rec.close()


def test_the_counterfactual_rows_pair_by_epoch_and_keep_their_columns() -> None:
    """A counterfactual row (typed: Counterfactual) pairs the decisions both replays scored;
    LPIPS is compared only where every one has it; --json writes the columns it always did."""
    from services.recorder.replay import Counterfactual, DecisionReplay, ReplayResult

    def result(policy: str, psnr: list[float | None], lpips_from: int = 0) -> ReplayResult:
        out = []
        for i, p in enumerate(psnr):
            q = None if p is None else pb.Quality(psnr_db=p, ssim=0.5, reward=1.0 + i)
            if q is not None and i >= lpips_from:
                q.lpips = 0.1
            out.append(DecisionReplay("site1", (1, i), 30.0 * i, ((i, 0.0),) * i, (), True,
                                      math.nan if i == 0 else 10.0, q))
        return ReplayResult(policy, out)

    base = result("mat:70", [20.0, 21.0, 22.0])
    row = Counterfactual.of(result("all", [21.0, None, 23.0], lpips_from=1), base)
    assert (row.n, row.means["psnr_db"], row.cameras_used, row.aoi_selected_ms) == (
        2, 22.0, 1.0, 10.0)
    assert row.vs_recorded["psnr_db"].mean == 1.0 and "lpips" not in row.vs_recorded
    assert list(row.to_dict()) == [
        "policy", "n", "psnr_db", "psnr_db_vs_recorded", "ssim", "ssim_vs_recorded", "lpips",
        "reward", "reward_vs_recorded", "cameras_used", "aoi_selected_ms"]
    assert row.to_dict()["psnr_db_vs_recorded"] == {"mean": 1.0, "ci95": 0.0, "n": 2}


def test_replay_command_json_and_its_errors(tmp_path: Path) -> None:
    import json

    from typer.testing import CliRunner

    from aoi3d_cli import app

    _mat10_recording(tmp_path / "r.mcap")
    out = CliRunner().invoke(app, ["replay", str(tmp_path / "r.mcap"), "--json", "--no-score",
                                   "--policy", "all"])
    assert out.exit_code == 0, out.output
    doc = json.loads(out.stdout)
    assert (doc["decisions"], doc["selections_equal"]) == (20, 20)
    assert doc["recorded_policies"] == ["mat:10"] and doc["rendered"] == 0
    assert doc["max_abs_score_diff"] is None and doc["late_arrivals"] == 0
    out = CliRunner().invoke(app, ["replay", str(tmp_path / "none.mcap")])
    assert out.exit_code == 1 and "no recording at" in out.output
    (tmp_path / "bad.mcap").write_bytes(b"not an mcap file at all")
    out = CliRunner().invoke(app, ["replay", str(tmp_path / "bad.mcap")])
    assert out.exit_code == 1 and "cannot be read as an MCAP recording" in out.output
    out = CliRunner().invoke(app, ["replay", str(tmp_path / "r.mcap"), "--site", "site9"])
    assert out.exit_code == 1 and "no site site9" in out.output


def test_a_raw_frame_is_a_foxglove_raw_image(tmp_path: Path) -> None:
    from services.kit.codec import RAW

    pixels = noise_image(4)
    payload = encode_frame(camera_id=2, sequence=1, generation_ms=30.0, scene_time_ms=30.0,
                           camera=camera(), delivery_ms=40.0,
                           image=pb.Image(encoding=RAW, width=W, height=H,
                                          data=pixels.tobytes()))
    rec = Recording(tmp_path / "raw.mcap")
    rec.write(K.edge_frame(2), payload, log_ns=1)
    rec.close()
    got = {t: (s, m) for t, s, m, _ in read_all(tmp_path / "raw.mcap")}
    schema, img = got["/site1/cam2/image"]
    assert schema == "foxglove.RawImage" and img.encoding == "rgb8"
    assert (img.width, img.height, img.step) == (W, H, 3 * W)
    assert np.array_equal(np.frombuffer(img.data, np.uint8).reshape(H, W, 3), pixels)


def test_a_replay_compares_the_reward_only_where_the_recording_scored_it() -> None:
    """A render the metrics service scored without LPIPS (``lpips_skipped``: reward NaN) is
    compared on PSNR and SSIM alone; the others on every score."""
    from types import SimpleNamespace

    from services.recorder.replay import score_diffs

    def q(psnr: float, reward: float, lpips: float | None, skipped: bool = False):
        msg = pb.Quality(psnr_db=psnr, ssim=0.5, reward=reward, lpips_skipped=skipped)
        if lpips is not None:
            msg.lpips = lpips
        return msg

    live = {(0, 1): q(20.0, 0.7, 0.2), (0, 2): q(21.0, math.nan, None, skipped=True)}
    replayed = {(0, 1): q(20.5, 0.71, 0.19), (0, 2): q(21.25, 0.9, 0.15)}
    rec = SimpleNamespace(sites={"site1": SimpleNamespace(qualities=live)})
    result = SimpleNamespace(decisions=[SimpleNamespace(site="site1", key=k, quality=v,
                                                        exact=None)
                                        for k, v in replayed.items()])
    diffs = score_diffs(rec, result)
    assert diffs["psnr_db"] == 0.5 and diffs["ssim"] == 0.0
    assert diffs["reward"] == pytest.approx(0.01) and diffs["lpips"] == pytest.approx(0.01)
    only_skipped = SimpleNamespace(decisions=result.decisions[1:])
    assert set(score_diffs(rec, only_skipped)) == {"psnr_db", "ssim"}  # not "equal": not compared
