"""Every run on record, and replayed: ``aoi3d up --record`` on a small scene (real processes,
real Zenoh on 127.0.0.1), a second recording started and stopped over REST, then ``aoi3d
replay --json`` of the first under its own policy (mat:70, deterministic) and the live
default carry (stream: each worker's chain of jobs rebuilt): every selection the same, every
score within 1e-3 — and a counterfactual policy on the same arrivals."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import uuid
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from tests.support.pipeline import HTTP, SCALE, assert_clean_exit, handle, stop_pipeline, wait_for
from tests.support.ports import block

pytestmark = [pytest.mark.integration, pytest.mark.slow]

PIPE = handle("recording")
_PORTS = block("recording")



@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from aoi3d.scene import SceneConfig, generate_dataset

    path = tmp_path_factory.mktemp("scene") / "turbine"
    generate_dataset(path, SceneConfig(width=48, height=36, duration_s=2.0, spp=2,
                                       rotor_rpm=15.0))
    return path


def topics_and_schemas(path: Path) -> dict[str, str]:
    out = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, _message, decoded in reader.iter_decoded_messages():
            assert decoded is not None
            out[channel.topic] = schema.name
    return out


def test_record_a_live_run_and_replay_it(small_dataset: Path, tmp_path: Path) -> None:
    run_id = f"rec{uuid.uuid4().hex[:8]}"
    first, second = tmp_path / "run.mcap", tmp_path / "later.mcap"
    cmd = ["--dataset", str(small_dataset), "--run-id", run_id, "--log-dir",
           str(tmp_path / "logs"), "--time-scale", "0.1", "--workers", "1", "--record", str(first)]
    # the live default carry (stream): the replay rebuilds the worker's chain of jobs
    env = {k: v for k, v in os.environ.items()
           if k not in ("AOI3D_DISPATCHER_CARRY", "AOI3D_DISPATCHER_RENDER_STEPS")}
    env.update(AOI3D_FILES_ROOTS=str(tmp_path),
               AOI3D_SCHEDULER_POLICY="mat:70")
    up = PIPE.start(cmd, env=env, output=subprocess.PIPE)
    try:
        wait_for("the recorder", lambda: HTTP.get(PIPE.url("recorder", "/recording")).json()
                 ["recording"], timeout_s=120)
        # ten renders scored while the recording runs (the metrics service may have scored
        # some before the recorder started), so ten decisions or more are on record
        def scored() -> int:
            return HTTP.get(PIPE.url("metrics", "/quality")).json()["summary"]["scored_total"]

        # the recorder can be up before the metrics service on a busy machine
        before = wait_for("the metrics service", lambda: scored() + 1, timeout_s=120) - 1
        wait_for("ten scored renders", lambda: scored() >= before + 10, timeout_s=180)
        wait_for("a hundred recorded messages", lambda: HTTP.get(PIPE.url("recorder", "/recording"))
                 .json()["messages"] > 100, timeout_s=120)
        r = HTTP.post(PIPE.url("recorder", "/recording/stop"))
        assert r.status_code == 200 and r.json()["state"] == "stopped", r.text
        assert r.json()["messages"] > 100
        r = HTTP.post(PIPE.url("recorder", "/recording/start"), json={"path": str(second)})
        assert r.status_code == 200, r.text
        wait_for("the second recording", lambda: HTTP.get(PIPE.url("recorder", "/recording"))
                 .json()["messages"] > 20)
    finally:
        out = stop_pipeline(up)
    assert_clean_exit(up, out, run_id)

    # both files are whole MCAPs (the second finished by the shutdown), every message decodes
    topics = topics_and_schemas(first)
    assert topics["/site1/cam1/image"] == "foxglove.CompressedImage"
    assert topics["/site1/cam1/calibration"] == "foxglove.CameraCalibration"
    assert topics["/tf"] == "foxglove.FrameTransform"
    for name in ("delivery", "truth", "decision", "render", "quality"):
        assert topics[f"/site1/{name}"].startswith("aoi3d.v1."), topics
    assert "/site1/decision" in topics_and_schemas(second)

    r = subprocess.run([sys.executable, "-m", "aoi3d_cli", "replay", str(first), "--json",
                        "--max-renders", "4", "--policy", "all"],
                       capture_output=True, text=True, timeout=600 * SCALE)
    assert r.returncode == 0, r.stderr[-3000:]
    doc = json.loads(r.stdout)
    assert doc["recorded_policies"] == ["mat:70"]
    assert doc["decisions"] >= 10
    assert doc["selections_equal"] == doc["decisions"], doc
    assert doc["rendered"] >= 3, doc
    # --record starts the recorder before anything flows: the worker's chain is on record from
    # its first job (frames included), so every render is reproduced (measured: 0.0)
    chains = doc["chains"]["recorded"]
    assert (chains["gaps"], chains["skipped"], doc["not_exact"]) == (0, 0, 0), doc
    assert doc["max_abs_score_diff"] is not None and doc["max_abs_score_diff"] <= 1e-3, doc
    recorded, every = doc["counterfactual"]
    assert (recorded["policy"], every["policy"]) == ("recorded", "all")
    # an epoch whose counterfactual selection names a frame delivered before the recorder
    # subscribed cannot be rebuilt: both policies rebuild the first epochs both can
    assert 1 <= every["n"] == recorded["n"] == doc["rendered"] <= doc["paired_epochs"], doc
    assert every["cameras_used"] >= recorded["cameras_used"]
    assert math.isfinite(every["psnr_db"]) and every["psnr_db_vs_recorded"]["n"] == every["n"]
