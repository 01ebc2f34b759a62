"""The services that read the dataset (camera: frames, dispatcher: cameras and box) say what is
wrong with it in one log line and exit 2 before serving — no traceback, no half-started server.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from aoi3d.scene import SceneConfig, generate_dataset
from services.kit.ports import SERVICE_PORTS
from tests.support.ports import block
from tests.support.timeouts import timeout_scale

SCALE = timeout_scale()
_PORTS = block("dataset-errors-service")
PORT_OFFSET = _PORTS.rest_offset
SMALL = SceneConfig(width=16, height=12, fps=10, duration_s=0.5, n_train=3, spp=1,
                    rotor_rpm=120.0, framing="rotor")


@pytest.fixture(scope="module")
def intact(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return generate_dataset(tmp_path_factory.mktemp("intact") / "scene", SMALL).root


def run_service(name: str, dataset: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, AOI3D_DATASET=str(dataset), AOI3D_ZENOH_MODE="client",
               AOI3D_ZENOH_CONNECT="tcp/127.0.0.1:9",  # never reached: it fails first
               **{f"AOI3D_{name.upper()}_PORT": str(SERVICE_PORTS[name] + PORT_OFFSET)})
    return subprocess.run([sys.executable, "-m", f"services.{name}"], env=env, text=True,
                          capture_output=True, timeout=120 * SCALE)


def test_camera_with_a_missing_frame_logs_one_line_and_exits(intact: Path, tmp_path: Path
                                                            ) -> None:
    root = tmp_path / "scene"
    shutil.copytree(intact, root)
    (root / "frames/cam02/0003.png").unlink()
    done = run_service("camera", root)
    out = done.stdout + done.stderr
    assert done.returncode == 2, out
    lines = [line for line in out.splitlines() if line.strip()]
    assert len(lines) == 1 and "ERROR" in lines[0], out
    assert f"{root}: 1 frame file(s) missing" in lines[0] and "cam02/0003.png" in lines[0]
    assert "aoi3d scene generate" in lines[0] and "Traceback" not in out


@pytest.mark.parametrize("name", ["camera", "dispatcher"])
def test_a_transforms_file_that_is_not_json_is_one_line(intact: Path, tmp_path: Path,
                                                        name: str) -> None:
    root = tmp_path / "scene"
    shutil.copytree(intact, root)
    (root / "transforms_test.json").write_text("{")
    done = run_service(name, root)
    out = done.stdout + done.stderr
    assert done.returncode == 2, out
    lines = [line for line in out.splitlines() if line.strip()]
    assert len(lines) == 1, out
    assert f"{root / 'transforms_test.json'} is not valid JSON" in lines[0]
    assert "regenerate it: aoi3d scene generate" in lines[0] and "Traceback" not in out
