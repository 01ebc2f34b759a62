"""A recording opens with the reader Foxglove and Lichtblick use: ``@mcap/core``'s indexed
reader (zstd chunks, the summary), every schema's FileDescriptorSet loaded with protobufjs (as
their protobuf message parser does) and every message decoded, the image channels as
``foxglove.CompressedImage`` with PNG data. Node and the packages come from
``.ci/setup/40-mcap-js.sh`` (CI runs it); without them the test says how to get them."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.support.recording import K, frame, one_of_each

HERE = Path(__file__).parent


def test_recording_opens_with_the_foxglove_mcap_reader(tmp_path: Path) -> None:
    if shutil.which("node") is None or not (HERE / "node_modules" / "@mcap" / "core").is_dir():
        pytest.skip("node or tests/foxglove/node_modules missing: run .ci/setup/40-mcap-js.sh")
    from services.recorder.core import Recording

    path = tmp_path / "run.mcap"
    rec = Recording(path, chunk_bytes=8 * 1024)  # several chunks
    for i in range(40):
        rec.write(K.edge_frame(1 + i % 4), frame(1 + i % 4, 30.0 * i, delivery_ms=30.0 * i + 3,
                                                 seed=i), log_ns=i)
    for i, (key, payload) in enumerate(one_of_each(t_ms=1500.0)):
        rec.write(key, payload, log_ns=100 + i)
    rec.close()
    r = subprocess.run(["node", str(HERE / "read_mcap.mjs"), str(path)], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    doc = json.loads(r.stdout)
    counts = doc["counts"]
    assert doc["messages"] == sum(counts.values()) == 41 * 4 + 2 * 2 + 4 + 1
    assert counts["/site1/cam1/image foxglove.CompressedImage"] == 11
    assert counts["/site1/cam2/calibration foxglove.CameraCalibration"] == 10
    assert counts["/tf foxglove.FrameTransform"] == 42
    for name in ("Frame", "Decision", "Render", "Quality", "Outcome"):
        assert any(k.endswith(f"aoi3d.v1.{name}") for k in counts), (name, counts)
