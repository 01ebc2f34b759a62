"""The rig file (issue 31): YAML or JSON, validated, every error naming its field; poses in any
of the conventions a ROS user has; the view, box and working size the dispatcher uses; and
``aoi3d up --rig`` running the ingest service in the camera's slot."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from aoi3d.rigfile import RigError, convert_pose, load_rig, quaternion_matrix, rig_from_dict
from aoi3d.scene import look_at
from services.supervisor import Supervisor, UpConfig
from tests.support.ingest import C2W, INTR, rig_doc


def errors(doc) -> str:
    with pytest.raises(RigError) as info:
        rig_from_dict(doc, "rig.yaml")
    return str(info.value)


def test_a_valid_rig_gives_ids_view_box_and_size() -> None:
    rig = rig_from_dict(rig_doc(size=[12, 9]))
    assert rig.ids() == {"truth": 0, "cam1": 1, "cam2": 2}
    assert [c.name for c in rig.train] == ["cam1", "cam2"]
    view = rig.view_camera()
    assert (view.width, view.height, view.fx, view.cx) == (12, 9, 10.0, 6.0)
    np.testing.assert_allclose(view.c2w, C2W)
    assert rig.working_size == (12, 9) and rig.scene_box.tolist() == [-2, -2, -1, 2, 2, 2]
    assert rig.cameras[2].kind == "compressed" and rig.cameras[1].kind == "raw"
    assert rig.time_scale == 1.0 and rig.pose_tolerance_s == 0.05
    assert rig.clock.offset_s == 0.0


def test_yaml_and_json_files_load(tmp_path: Path) -> None:
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig_doc()))
    (tmp_path / "rig.json").write_text(json.dumps(rig_doc()))
    assert load_rig(tmp_path / "rig.yaml") == load_rig(tmp_path / "rig.json")
    (tmp_path / "bad.yaml").write_text("cameras: [\n")
    with pytest.raises(RigError, match="not valid YAML"):
        load_rig(tmp_path / "bad.yaml")
    with pytest.raises(RigError, match="cannot read"):
        load_rig(tmp_path / "missing.yaml")


@pytest.mark.parametrize("change,field", [
    (lambda d: d["cameras"][1]["intrinsics"].update(fx=5.0), "cameras[1].intrinsics"),
    (lambda d: d["cameras"][2]["intrinsics"].pop("fy"), "cameras[2].intrinsics"),
    (lambda d: d["cameras"][1]["pose"].update(c2w=[1.0] * 16), "cameras[1].pose"),
    (lambda d: d["cameras"][0]["pose"].update(c2w=[1.0] * 15), "cameras[0].pose.c2w"),
    (lambda d: d["cameras"][0]["pose"].update(c2w=(2 * np.eye(4)).ravel().tolist()),
     "cameras[0].pose.c2w"),
    (lambda d: d["cameras"][1]["pose"].update(type="Twist"), "cameras[1].pose.type"),
    (lambda d: d["cameras"][1].update(image="/a/*/b"), "cameras[1].image"),
    (lambda d: d["cameras"][1].update(name="cam2"), "cameras: names must differ"),
    (lambda d: d.update(truth="nobody"), "truth: no camera is named"),
    (lambda d: d.update(truth="cam1"), "truth: the truth camera"),
    (lambda d: d.update(aabb=[0, 0, 0, 1, 1]), "aabb"),
    (lambda d: d.update(aabb=[0, 0, 0, 1, -1, 1]), "aabb"),
    (lambda d: d.update(source={"format": "ros1"}), "source.format"),
    (lambda d: d.update(source={"format": "rmw_zenoh", "namespace": "x"}), "source"),
    (lambda d: d.update(clock={"offset_s": "sometimes"}), "clock.offset_s"),
    (lambda d: d.update(time_scale=0), "time_scale"),
    (lambda d: d.update(size=[4, 4]), "size"),
    (lambda d: d.update(colour="red"), "colour"),
    (lambda d: d["cameras"][1].update(extra=1), "cameras[1].extra"),
])
def test_errors_name_the_field(change, field: str) -> None:
    doc = rig_doc()
    change(doc)
    text = errors(doc)
    assert field in text, text
    assert text.startswith("rig.yaml: ")


def test_without_a_truth_camera_the_view_is_the_first_cameras_or_given() -> None:
    doc = rig_doc()
    doc.pop("truth")
    rig = rig_from_dict(doc)
    assert rig.ids() == {"truth": 1, "cam1": 2, "cam2": 3}
    np.testing.assert_allclose(rig.view_camera().c2w, C2W)
    doc["cameras"] = doc["cameras"][1:]  # the first now has pose and intrinsics on topics
    assert "view:" in errors(doc)
    doc["view"] = {"intrinsics": INTR, "pose": {"c2w": C2W.ravel().tolist()}}
    assert rig_from_dict(doc).view_camera().width == INTR["width"]


def test_pose_conventions() -> None:
    gl = look_at((1.0, -3.0, 2.0), (0.0, 0.0, 0.5))
    optical = gl @ np.diag([1.0, -1.0, -1.0, 1.0])
    np.testing.assert_allclose(convert_pose(optical, "optical"), gl, atol=1e-12)
    np.testing.assert_allclose(convert_pose(gl, "opengl"), gl)
    # a body frame (x forward, y left, z up) looks along its +x
    body = np.eye(4)
    body[:3, :3] = np.column_stack([-gl[:3, 2], -gl[:3, 0], gl[:3, 1]])
    body[:3, 3] = gl[:3, 3]
    np.testing.assert_allclose(convert_pose(body, "body"), gl, atol=1e-12)
    # position + quaternion (x, y, z, w): 90° about z
    m = quaternion_matrix([1, 2, 3], [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    np.testing.assert_allclose(m[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    assert m[:3, 3].tolist() == [1, 2, 3]
    doc = rig_doc()
    doc["cameras"][0]["pose"] = {"position": gl[:3, 3].tolist(),
                                 "orientation": _quat(optical[:3, :3]), "convention": "optical"}
    np.testing.assert_allclose(rig_from_dict(doc).view_camera().c2w, gl, atol=1e-9)
    # an extrinsic: the pose topic gives the body, the camera sits 0.1 forward of it
    spec = rig_from_dict(rig_doc()).cameras[1].pose.model_copy(update={
        "extrinsic": np.eye(4).ravel().tolist()})
    np.testing.assert_allclose(spec.to_gl(optical), gl, atol=1e-12)


def _quat(r: np.ndarray) -> list[float]:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(r).as_quat().tolist()


def test_up_with_a_rig_runs_the_ingest_in_the_cameras_slot(tmp_path: Path) -> None:
    cfg = UpConfig(rig=tmp_path / "rig.yaml", delay="exp:60", cameras=2, port_offset=100,
                   log_dir=tmp_path)
    children = {c.name: c for c in Supervisor(cfg).children}
    cam = children["camera"]
    assert cam.argv == [sys.executable, "-m", "services.ingest"]
    assert cam.env["AOI3D_RIG"] == str((tmp_path / "rig.yaml").resolve())
    assert cam.env["AOI3D_INGEST_PORT"] == "8201"
    assert cam.env["AOI3D_INGEST_THROUGH_NETWORK"] == "true"
    assert cam.env["AOI3D_NETWORK_DELAY"] == "exp:60"
    plain = {c.name: c for c in Supervisor(UpConfig(log_dir=tmp_path)).children}
    assert plain["camera"].argv[-1] == "services.camera"
    assert plain["camera"].env.get("AOI3D_RIG") == os.environ.get("AOI3D_RIG")


def test_the_compose_rig_override_runs_the_ingest_in_the_cameras_slot() -> None:
    """compose.rig.yaml checked as data against compose.yaml and the settings it sets (`make
    compose-test` runs it: tests/containers/test_compose_rig.py)."""
    from services.ingest.settings import Settings as IngestSettings
    from services.metrics.settings import Settings as MetricsSettings

    root = Path(__file__).resolve().parents[3]
    base = yaml.safe_load((root / "compose.yaml").read_text())["services"]
    rig = yaml.safe_load((root / "compose.rig.yaml").read_text())["services"]
    assert set(rig) <= set(base)
    assert rig["camera"]["command"] == ["python", "-m", "services.ingest"]
    for name in ("camera", "dispatcher"):
        assert rig[name]["environment"]["AOI3D_RIG"] == "/rig/rig.yaml"
        assert any(v.endswith(":/rig/rig.yaml:ro") for v in rig[name]["volumes"])
    for var in rig["camera"]["environment"]:
        if var.startswith("AOI3D_INGEST_"):
            assert var.removeprefix("AOI3D_INGEST_").lower() in IngestSettings.model_fields
    (var,) = rig["metrics"]["environment"]
    assert var.removeprefix("AOI3D_METRICS_").lower() in MetricsSettings.model_fields
