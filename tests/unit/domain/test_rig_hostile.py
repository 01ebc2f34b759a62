"""Hostile rig files (issue 44): every failure a new user met is one line naming the file and
the field, at `aoi3d ros2 check` rather than at run time — non-finite numbers, encodings,
sizes, alias bombs, FFmpeg protocols, missing videos — and a PNG bomb is `too_large`."""

from __future__ import annotations

import json
import struct
import time
import zlib
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from aoi3d.rigfile import RigError, load_rig, rig_from_dict
from tests.support.ingest import rig_doc
from tests.support.timeouts import timeout_scale

SCALE = timeout_scale()


def _refused(path: Path, *fragments: str) -> str:
    with pytest.raises(RigError) as info:
        load_rig(path, videos=True)
    text = str(info.value)
    assert str(path) in text and all(f in text for f in fragments), text
    assert "Traceback" not in text
    return text


@pytest.mark.parametrize(("field", "change"), [
    ("cameras[0].pose.position.0",
     lambda d, v: d["cameras"][0].update(pose={"position": [v, 0, 1],
                                               "orientation": [0, 0, 0, 1]})),
    ("cameras[2].intrinsics.fx", lambda d, v: d["cameras"][2]["intrinsics"].update(fx=v)),
    ("cameras[2].intrinsics.fy", lambda d, v: d["cameras"][2]["intrinsics"].update(fy=v)),
    ("cameras[2].intrinsics.cx", lambda d, v: d["cameras"][2]["intrinsics"].update(cx=v)),
    ("aabb.1", lambda d, v: d.update(aabb=[0, v, 0, 1, 1, 1])),
    ("time_scale", lambda d, v: d.update(time_scale=v)),
    ("clock.future_tolerance_s", lambda d, v: d.update(clock={"future_tolerance_s": v})),
])
@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")])
@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_non_finite_numbers_are_refused_naming_the_field(
        tmp_path: Path, field: str, change, value: float, suffix: str) -> None:
    doc = rig_doc()
    change(doc, value)
    path = tmp_path / f"rig{suffix}"
    path.write_text(json.dumps(doc) if suffix == ".json" else yaml.safe_dump(doc))
    head = field.split(".")[0].split("[")[0]
    assert head in _refused(path, "finite")


def test_encodings(tmp_path: Path) -> None:
    text = yaml.safe_dump(rig_doc())
    for encoding in ("utf-16", "utf-32", "utf-8-sig"):  # each with its byte-order mark
        path = tmp_path / f"rig-{encoding}.yaml"
        path.write_bytes(text.encode(encoding))
        assert load_rig(path) == rig_from_dict(rig_doc())
    utf16 = tmp_path / "nobom.yaml"
    utf16.write_bytes(text.encode("utf-16-le"))  # no mark: NULs between the letters
    _refused(utf16, "UTF-16 without a byte-order mark?", "save the rig file as UTF-8")
    binary = tmp_path / "rig.yaml"
    binary.write_bytes(bytes(range(256)) * 4)
    _refused(binary, "not UTF-8 text")
    nul = tmp_path / "nul.yaml"
    nul.write_text("cameras: []\x00\n")
    _refused(nul, "NUL")


def test_a_json_file_in_capitals_is_read_and_refused_as_json(tmp_path: Path) -> None:
    path = tmp_path / "bad.JSON"
    path.write_text(json.dumps(rig_doc()))
    assert load_rig(path).truth == "truth"
    path.write_text("cameras: [1]\n")  # YAML, not JSON
    _refused(path, "not valid JSON")


def test_sizes_and_counts_are_refused_before_validation(tmp_path: Path) -> None:
    doc = rig_doc()
    cam = doc["cameras"][2]
    doc["cameras"] = [doc["cameras"][0]] + [
        {**cam, "name": f"c{i}", "image": f"/c{i}/image_raw/compressed"} for i in range(10_000)]
    big = tmp_path / "big.json"
    big.write_text(json.dumps(doc))
    t = time.perf_counter()
    _refused(big, "bytes; a rig file may have at most 1048576")
    compact = tmp_path / "compact.yaml"  # under the byte cap, over the camera cap
    compact.write_text("cameras:\n" + "- {}\n" * 10_000 + "aabb: [0, 0, 0, 1, 1, 1]\n")
    _refused(compact, "at most 257 cameras", "got 10000")
    assert time.perf_counter() - t < 2.0 * SCALE
    bomb = tmp_path / "bomb.yaml"  # a billion laughs: 10^9 values from 1 kB
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, 9)]
    bomb.write_text("\n".join(lines) + "\ncameras: [*a8]\n")
    t = time.perf_counter()
    _refused(bomb, "over 100000 values")
    assert time.perf_counter() - t < 2.0 * SCALE
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    _refused(deep, "not valid JSON")


@pytest.mark.parametrize(("url", "ok"), [
    ("rtsp://10.0.0.7:554/s", True), ("RTSPS://cam.example/s", True),
    ("concat:/a.mp4|/b.mp4", False), ("http://example.com/v.mp4", False),
    ("file:/etc/passwd", False), ("subfile,,start,0,end,0,,:/x", True),  # a path: must exist
    ("tcp://1.2.3.4:5", False),
])
def test_url_protocols_beyond_rtsp_need_the_rigs_leave(url: str, ok: bool) -> None:
    doc = rig_doc()
    doc["cameras"].append({"name": "ip", "url": url, "intrinsics": doc["cameras"][0][
        "intrinsics"], "pose": doc["cameras"][0]["pose"]})
    if ok:
        rig_from_dict(doc)
        return
    with pytest.raises(RigError, match=r"cameras\[3\]\.url: the \w+: protocol is not accepted"):
        rig_from_dict(doc)
    scheme = url.split(":")[0]
    assert rig_from_dict({**doc, "url_protocols": [scheme]}).cameras[3].protocol == scheme


def test_check_says_which_video_file_is_missing(tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    from aoi3d_cli import ros2

    monkeypatch.chdir(tmp_path)
    doc = rig_doc()
    doc["cameras"].append({"name": "vid", "url": "videos/cam3.mp4", "intrinsics": doc[
        "cameras"][0]["intrinsics"], "pose": doc["cameras"][0]["pose"]})
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(doc))
    result = CliRunner().invoke(ros2.app, ["check", "rig.yaml"])
    assert result.exit_code == 1
    assert "error: rig.yaml: cameras[3].url: no video file 'videos/cam3.mp4'" in result.output
    (tmp_path / "videos").mkdir()
    (tmp_path / "videos" / "cam3.mp4").write_bytes(b"x")
    result = CliRunner().invoke(ros2.app, ["check", "rig.yaml"])
    assert result.exit_code == 0, result.output
    assert "3 training cameras" in result.output
    for bad in ("nan", ".inf"):
        (tmp_path / "rig.yaml").write_text(yaml.safe_dump(doc).replace(
            "fx: 20.0", f"fx: {bad}", 1))
        result = CliRunner().invoke(ros2.app, ["check", "rig.yaml"])
        assert result.exit_code == 1 and "intrinsics.fx" in result.output, result.output


def _chunk(kind: bytes, data: bytes) -> bytes:
    return (struct.pack(">I", len(data)) + kind + data
            + struct.pack(">I", zlib.crc32(kind + data)))


def _png_header(width: int, height: int) -> bytes:
    """A PNG that declares its size and holds (almost) no pixels."""
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", width, height,
                                                                8, 2, 0, 0, 0))
            + _chunk(b"IDAT", zlib.compress(b"\x00" * 16)) + _chunk(b"IEND", b""))


def test_a_png_bomb_over_pillows_limit_is_too_large() -> None:
    import dataclasses

    import numpy as np

    from services import ros
    from services.kit.rejected import Rejected
    from services.ros.decode import image_rgb

    msg = ros.compressed_msg(0.0, "c", np.zeros((2, 2, 3), np.uint8), "png")
    for size, reason in [(20000, "too_large"), (100, "bad_image")]:  # the header alone
        bomb = dataclasses.replace(msg, data=np.frombuffer(_png_header(size, size), np.uint8))
        with pytest.raises(Rejected) as info:
            image_rgb(bomb, ros.COMPRESSED, 8192 * 8192)
        assert info.value.reason == reason, info.value
