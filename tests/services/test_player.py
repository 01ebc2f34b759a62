"""``aoi3d replay --live``'s player: a recording's frames as ROS 2 cameras — each at its
recorded time (scaled, phase-locked onto the pipeline's grid), with its own pose, its camera
info and the recorded PNG bytes — and the rig file that reads them (pure logic: a fake clock,
the samples decoded back by the ingest's own core)."""

from __future__ import annotations

import re

import numpy as np

from aoi3d.rigfile import rig_from_dict
from aoi3d.scene import Camera, look_at
from services import ros
from services.ingest.core import IngestCore
from services.kit.codec import decode_frame, encode_frame, encode_png
from services.kit.keys import Keys
from services.kit.membus import key_matches
from services.kit.pb import aoi3d_pb2 as pb
from services.recorder.player import PlayConfig, Player, rig_document
from tests.support.fakeclock import FakeClock
from tests.support.recording import H, W, noise_image
from tests.support.recording import write_recording as _record

EPOCH = 1_700_000_000.0
AABB = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def _frame(cam: int, gen: float, x: float = 0.0) -> pb.Frame:
    camera = Camera(c2w=look_at((x + cam, -4.0, 1.0), (0.0, 0.0, 0.5)), fx=20.0, fy=20.0,
                    cx=W / 2, cy=H / 2, width=W, height=H)
    return pb.Frame.FromString(encode_frame(
        camera_id=cam, sequence=int(gen // 30), generation_ms=gen, scene_time_ms=gen,
        camera=camera, image=encode_png(noise_image(int(gen) + cam)), send_ms=gen))


def test_the_player_sends_each_frame_at_its_recorded_time_on_the_pipelines_grid() -> None:
    # a recording from 990 ms of its clock; camera 2 moves and lost its frame of 1050 ms
    frames = {0: [_frame(0, 990.0 + 30 * k) for k in range(4)],
              1: [_frame(1, 990.0 + 30 * k) for k in range(4)],
              2: [_frame(2, 990.0 + 30 * k, x=0.1 * k) for k in (0, 1, 3)]}
    cfg = PlayConfig(time_scale=0.5, epoch_s=EPOCH, period_ms=30.0)
    clock = FakeClock(EPOCH + 0.123)  # 61.5 ms into the pipeline's clock: its next grid time is 90

    sent: list[tuple[str, bytes, bytes | None, float]] = []
    player = Player(frames, cfg, lambda k, p, a: sent.append((k, p, a, clock())), clock=clock)
    player.run(clock)
    assert player.sent == 11 and player.shift_ms == 90.0 - 990.0
    # the ingest's own core, on the rig file written for the play, takes every frame back
    core = IngestCore(rig_from_dict(rig_document(frames, cfg, AABB)), Keys("t"),
                      epoch_s=EPOCH, time_scale=0.5)
    out = []
    for key, payload, att, at in sent:
        for route in [r for r in core.routes if key_matches(r.key_expr, key)]:
            out += core.on_sample(route, key, payload, att, at + 0.001)
    got = sorted(((p.camera_id, decode_frame(p.payload)) for p in out),
                 key=lambda x: (x[0], x[1].generation_ms))
    assert [(c, f.generation_ms) for c, f in got] == [
        (c, 90.0 + 30 * k) for c in (0, 1, 2) for k in range(4) if (c, k) != (2, 2)]
    for (_, f), want in zip(got, [fr for c in (0, 1, 2) for fr in frames[c]], strict=True):
        # sent at its time (frame g at epoch + (g + shift) / 1000 / time scale) ...
        assert f.image.data == want.image.data  # ... the recorded PNG, byte for byte ...
        assert np.allclose(f.camera.c2w.ravel(), want.pose.c2w, atol=1e-9)  # ... its pose
    times = sorted({at for *_, at in sent})
    assert np.allclose(np.array(times) - EPOCH, (90.0 + 30 * np.arange(4)) / 500.0)
    assert {ros.parse_attachment(a).sequence for k, _, a, _ in sent if "cam02/image" in k} \
        == {1, 2, 3}
    # in the ROS graph: one node, a publisher for each topic the rig file reads
    for token in player.tokens("s1"):
        core.on_liveliness(token, True)
    assert [e.node for e in core.ros_graph.entities.values()
            if e.kind == "node"] == ["aoi3d_player"]
    assert all(t["publishers"] == 1 for t in core.topic_publishers())
    assert len(core.ros_graph.entities) == 1 + len(core.topic_publishers())


def test_the_rig_file_of_a_play_validates_and_names_the_truth_camera() -> None:
    frames = {0: [_frame(0, 0.0)], 3: [_frame(3, 0.0)], 5: [_frame(5, 0.0)]}
    doc = rig_document(frames, PlayConfig(format="bridge", namespace="rec"), AABB)
    rig = rig_from_dict(doc)
    assert rig.truth == "cam00" and [c.name for c in rig.train] == ["cam03", "cam05"]
    assert rig.source.format == "bridge" and rig.working_size == (W, H)


def test_the_live_replay_command_writes_its_rig_file_and_refuses_what_is_not_live(tmp_path):
    from typer.testing import CliRunner

    from aoi3d.rigfile import load_rig
    from aoi3d_cli import app

    _record(tmp_path / "run.mcap")
    runner = CliRunner()

    def said(res) -> str:  # the message without rich's box and its line breaks
        return re.sub(r"[│╭╮╰╯─\s]+", " ", res.output)

    rig = tmp_path / "rig.yaml"
    res = runner.invoke(app, ["replay", str(tmp_path / "run.mcap"), "--live", "--write-rig",
                              str(rig), "--rig-only", "--time-scale", "0.1"])
    assert res.exit_code == 0, res.output
    r = load_rig(rig)
    assert r.truth == "cam00" and [c.name for c in r.train] == ["cam01", "cam02"]
    assert r.time_scale == 0.1 and r.scene_box.ravel().tolist() == [-1, -1, -1, 1, 1, 1]
    res = runner.invoke(app, ["replay", str(tmp_path / "run.mcap"), "--live", "--policy", "all"])
    assert res.exit_code == 2 and "are for the virtual clock" in said(res)
    res = runner.invoke(app, ["replay", str(tmp_path / "run.mcap"), "--write-rig", str(rig)])
    assert res.exit_code == 2 and "--epoch-s are for --live" in said(res)
    res = runner.invoke(app, ["replay", str(tmp_path / "run.mcap"), "--live", "--rig-only"])
    assert res.exit_code == 2 and "needs --write-rig" in said(res)


def test_a_recording_plays_from_its_file_reading_each_frames_pixels_when_it_is_sent(
        tmp_path) -> None:
    """``aoi3d replay --live`` holds the frames' metadata only: each PNG is read from the
    file as its frame goes out, byte for byte the recorded one."""
    from services.recorder.sources import recorded_streams
    from tests.support.recording import frame_seed

    _record(tmp_path / "run.mcap")
    _site, streams, _box = recorded_streams(tmp_path / "run.mcap")
    frames = {n: s.frames for n, s in streams.items()}
    assert all(not f.image.data for lst in frames.values() for f in lst)  # not in memory
    clock = FakeClock(EPOCH)
    sent: list[tuple[str, bytes]] = []
    player = Player(frames, PlayConfig(), lambda k, p, a: sent.append((k, p)), clock=clock,
                    pixels=lambda n, fr: streams[n].pixels(fr))
    player.run(clock)
    images = [ros.decode_cdr(p, ros.COMPRESSED, 1 << 20) for k, p in sent if "image" in k]
    assert len(images) == player.sent == sum(len(lst) for lst in frames.values())
    want = {encode_png(noise_image(frame_seed(n, int(f.generation_ms // 30)))).data
            for n, lst in frames.items() for f in lst}
    assert {bytes(m.data) for m in images} == want
