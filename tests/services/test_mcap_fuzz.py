"""MCAP files fuzzed (issue 44): a recording cut anywhere, bytes flipped or spliced, records
that claim huge lengths, schemas that are not the recorder's, messages that are not their
schema — reading it (``load``), replaying it (selections, the virtual clock), telling its
kind and importing it give a result, notes and counted refusals, or one error naming the
file; never another exception, never a slow read. Budget: tests/support/fuzz.py."""

from __future__ import annotations

import io
import shutil
import struct
import tempfile
import time
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from mcap.writer import CompressionType, Writer

from services.recorder.importer import import_mcap
from services.recorder.mcapfile import McapFileError
from services.recorder.recording import load
from services.recorder.replay import replay
from services.recorder.sources import NotImportable
from tests.support.fuzz import fuzz
from tests.support.recording import write_long_recording
from tests.support.timeouts import timeout_scale

SLOW_S = 5.0 * timeout_scale()
TMP = Path(tempfile.mkdtemp(prefix="aoi3d-mcap-fuzz-"))


def _recording(compression: str) -> bytes:
    path = TMP / f"whole-{compression}.mcap"
    write_long_recording(path, steps=6, size=(24, 18), compression=compression)
    return path.read_bytes()


WHOLE = {c: _recording(c) for c in ("zstd", "none")}


def _one_line(err: Exception, path: Path) -> None:
    text = str(err)
    assert "\n" not in text and str(path) in text, text


def _read(raw: bytes, name: str = "f.mcap") -> None:
    """``raw`` read, replayed and imported as a user would: results or one-line errors."""
    path = TMP / name
    path.write_bytes(raw)
    t = time.perf_counter()
    try:
        rec = load(path)
    except McapFileError as err:
        _one_line(err, path)
        rec = None
    if rec is not None:
        assert all(str(path) in note for note in rec.cut_short)
        for policy in (None, "all"):
            try:
                replay(rec, policy, score=False)
            except ValueError as err:  # no decision to replay, e.g.: the command's one line
                assert "\n" not in str(err)
    out = TMP / "ds"
    shutil.rmtree(out, ignore_errors=True)
    try:
        import_mcap(path, out, fps=33)
    except NotImportable as err:
        assert "\n" not in str(err), err
    took = time.perf_counter() - t
    assert took < SLOW_S, f"{took:.2f} s"


@fuzz(80)
@given(st.sampled_from(sorted(WHOLE)), st.data())
def test_a_recording_cut_anywhere_reads_up_to_the_cut(compression: str, data) -> None:
    raw = WHOLE[compression]
    cut = data.draw(st.integers(0, len(raw)))
    _read(raw[:cut])


@fuzz(150)
@given(st.sampled_from(sorted(WHOLE)), st.data())
def test_flipped_or_spliced_bytes_are_read_or_refused_in_one_line(compression, data) -> None:
    raw = bytearray(WHOLE[compression])
    for _ in range(data.draw(st.integers(1, 8))):
        at = data.draw(st.integers(8, len(raw) - 1))
        if data.draw(st.booleans()):
            raw[at] = data.draw(st.integers(0, 255))
        else:
            raw[at:at] = data.draw(st.binary(min_size=1, max_size=16))
    _read(bytes(raw))


def test_a_frame_whose_png_is_damaged_is_refused_by_the_import_naming_it() -> None:
    # what the flip test once found (raw[8786] = 0 in the uncompressed recording): a frame's
    # PNG bytes damaged in place; the import refused it with write_dataset's ValueError
    raw = bytearray(WHOLE["none"])
    at = raw.find(b"\x89PNG\r\n\x1a\n")
    assert at > 0, "the recording holds PNG frames"
    raw[at] = 0
    path = TMP / "damaged.mcap"
    path.write_bytes(bytes(raw))
    out = TMP / "damaged-ds"
    shutil.rmtree(out, ignore_errors=True)
    with pytest.raises(NotImportable, match="its image cannot be read") as err:
        import_mcap(path, out, fps=33)
    _one_line(err.value, path)
    assert not out.exists()  # nothing written
    _read(bytes(raw), "damaged-read.mcap")  # read and replayed as before
    raw = bytearray(WHOLE["none"])  # damaged inside (its compressed pixels), not at its ends
    at = raw.find(b"IDAT")
    raw[at + 8:at + 24] = bytes(16)
    path.write_bytes(bytes(raw))
    with pytest.raises(NotImportable, match="its image cannot be read") as err:
        import_mcap(path, out, fps=33)
    _one_line(err.value, path)
    assert not out.exists()


@fuzz(60)
@given(st.sampled_from(sorted(WHOLE)), st.data(), st.integers(0, 2**64 - 1))
def test_a_record_that_claims_any_length_is_refused_before_it_is_read(compression, data,
                                                                     length) -> None:
    raw = bytearray(WHOLE[compression])
    # the length field of a record: 1 byte after a record's start (the first is at 8)
    at = data.draw(st.sampled_from([9, *range(9, min(len(raw) - 8, 2000), 97)]))
    raw[at:at + 8] = struct.pack("<Q", length)
    _read(bytes(raw))


TOPICS = ["/site1/decision", "/site1/delivery", "/site1/truth", "/site1/cam1/image",
          "/site1/truth/image", "/site1/render", "/site1/quality", "/site1/outcome", "/tf"]
SCHEMAS = ["aoi3d.v1.Decision", "aoi3d.v1.Frame", "aoi3d.v1.Render", "aoi3d.v1.Quality",
           "aoi3d.v1.Outcome", "aoi3d.v1.Nope", "foxglove.CompressedImage", "foxglove.RawImage",
           "sensor_msgs/msg/Image", ""]


@fuzz(120)
@given(st.lists(st.tuples(st.sampled_from(TOPICS), st.sampled_from(SCHEMAS),
                          st.sampled_from(["protobuf", "ros2msg", "", "json"]),
                          st.binary(max_size=40), st.lists(st.binary(max_size=300),
                                                           max_size=4)),
                min_size=1, max_size=6))
def test_schemas_and_messages_that_are_not_the_recorders_are_counted(channels) -> None:
    buf = io.BytesIO()
    writer = Writer(buf, compression=CompressionType.NONE)
    writer.start()
    for k, (topic, name, encoding, schema_data, messages) in enumerate(channels):
        sid = writer.register_schema(name or f"s{k}", encoding, schema_data)
        cid = writer.register_channel(topic, "protobuf", sid)
        for i, payload in enumerate(messages):
            writer.add_message(cid, log_time=k * 10 + i, data=payload, publish_time=i)
    writer.finish()
    _read(buf.getvalue())


def test_short_and_foreign_files_are_one_line_naming_them(tmp_path: Path) -> None:
    for raw, why in [(b"", "0 bytes"), (b"\x89MCAP0\r", "7 bytes"), (b"x" * 8, "another magic"),
                     (b"PK\x03\x04" + b"\x00" * 40, "another magic")]:
        path = tmp_path / "f.mcap"
        path.write_bytes(raw)
        with pytest.raises(McapFileError) as err:
            load(path)
        _one_line(err.value, path)
        assert why in str(err.value) and "not an MCAP file" in str(err.value)
        with pytest.raises(NotImportable, match="not an MCAP file"):
            import_mcap(path, tmp_path / "ds")
