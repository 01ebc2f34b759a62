"""The MCAP cases of issue 44, each as a new user met it: a recording with a schema that is not
a protobuf descriptor, a recording cut short, a file of 8 bytes, and an import grid without a
cap. Each ends in a result with a note, a counted refusal, or one line naming the file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from aoi3d_cli import app
from services.recorder.importer import MAX_GRID_FRAMES, import_mcap
from services.recorder.recording import load
from services.recorder.sources import NotImportable, kind_of
from tests.support.recording import write_long_recording, write_recording


def _bad_schemas(src: Path, dst: Path) -> None:
    """``src``'s messages again, each schema's descriptor replaced by bytes that are not one
    (a reader that decodes with the file's schemas cannot decode any message)."""
    from mcap.writer import Writer

    from services.recorder.mcapfile import Reading

    with open(dst, "wb") as f:
        writer = Writer(f)
        writer.start()
        schemas: dict[str, int] = {}
        channels: dict[str, int] = {}
        for m in Reading([src]).messages():
            name = m.schema.name
            if name not in schemas:
                schemas[name] = writer.register_schema(name, "protobuf", b"\xff" * 40)
            if m.channel.topic not in channels:
                channels[m.channel.topic] = writer.register_channel(
                    m.channel.topic, "protobuf", schemas[name])
            writer.add_message(channels[m.channel.topic], log_time=m.message.log_time,
                               data=m.message.data, publish_time=m.message.publish_time)
        writer.finish()


def test_a_recording_whose_schemas_are_garbage_still_imports(tmp_path: Path) -> None:
    src = tmp_path / "run.mcap"
    write_recording(src)
    bad = tmp_path / "bad.mcap"
    _bad_schemas(src, bad)
    ds, report = import_mcap(bad, tmp_path / "ds")  # decoded by name with the project's types
    assert report.n_frames > 10 and len(ds.cameras) == 3


def test_a_cut_recording_reads_to_its_cut_and_says_so(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    write_long_recording(path, steps=40, size=(24, 18), compression="none",
                         chunk_bytes=16 << 10)
    raw = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(raw[:len(raw) * 2 // 3])  # no summary, no footer, a record half written
    assert kind_of(cut) == "recording"  # the schemas on the way, no summary needed
    rec = load(cut)
    assert rec.cut_short and "cut short at byte" in rec.cut_short[0]
    assert "mcap recover" in rec.cut_short[0] and str(cut) in rec.cut_short[0]
    assert 10 < len(rec.sites["site1"].decisions) < 40
    out = CliRunner().invoke(app, ["replay", str(cut), "--json", "--no-score"])
    assert out.exit_code == 0, out.output
    assert "note: " in out.stderr and "cut short" in out.stderr
    assert json.loads(out.stdout)["decisions"] == len(rec.sites["site1"].decisions)
    out = CliRunner().invoke(app, ["scene", "import", str(cut), "--out", str(tmp_path / "ds"),
                                   "--json", "--fps", "33", "--aabb", "-1,-1,-1,1,1,1"])
    assert out.exit_code == 0, out.output
    assert json.loads(out.stdout)["rejected"] == {"cut_short": 1}


@pytest.mark.parametrize("size", [0, 3, 8, 27])
def test_a_tiny_file_is_one_line_naming_it(tmp_path: Path, size: int) -> None:
    path = tmp_path / "tiny.mcap"
    path.write_bytes(b"\x89MCAP0\r\n"[:size] + b"\x00" * max(0, size - 8))
    for args in (["replay", str(path)], ["scene", "import", str(path), "--out",
                                         str(tmp_path / "ds")]):
        out = CliRunner().invoke(app, args)
        assert out.exit_code == 1, out.output
        lines = [line for line in out.output.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith("error: ") and str(path) in lines[0]
        assert "Traceback" not in out.output and "Errno" not in out.output


def test_the_import_grid_is_capped(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    write_recording(path)  # 20 frames 30 ms apart
    with pytest.raises(NotImportable, match=r"--fps must be 1\.\.1000"):
        import_mcap(path, tmp_path / "a", fps=5000)
    import services.recorder.importer as importer

    importer.MAX_GRID_FRAMES, saved = 50, MAX_GRID_FRAMES
    try:
        with pytest.raises(NotImportable, match="over the 50 frames a dataset may have"):
            import_mcap(path, tmp_path / "b", fps=1000)  # 571 ms at 1000 fps: 572 × 3
    finally:
        importer.MAX_GRID_FRAMES = saved
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    out = CliRunner().invoke(app, ["scene", "import", str(path), "--out", str(tmp_path / "c"),
                                   "--fps", "100000"])
    assert out.exit_code != 0 and "1000" in out.output


def test_a_sub_millisecond_truth_gap_needs_fps(tmp_path: Path) -> None:
    from services.kit.codec import encode_frame, encode_png
    from services.recorder.core import Recording
    from tests.support.recording import AABB, K, noise_image, recording_camera

    path = tmp_path / "fast.mcap"
    rec = Recording(path)
    for k in range(30):
        for cam in (0, 1):
            gen = 0.25 * k  # four truth frames a millisecond
            rec.write(K.truth if cam == 0 else K.edge_frame(cam), encode_frame(
                camera_id=cam, sequence=k, generation_ms=gen, scene_time_ms=gen,
                camera=recording_camera(float(cam)), image=encode_png(noise_image(k)),
                send_ms=gen, delivery_ms=gen + 0.1 if cam else 0.0), log_ns=k)
    rec.close()
    with pytest.raises(NotImportable, match=r"0\.25 ms apart .*give --fps"):
        import_mcap(path, tmp_path / "ds", aabb=AABB)
