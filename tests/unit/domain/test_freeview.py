"""Free views and exports, the pure parts: the pose check (one for REST and Zenoh), the camera
it makes, the viewer's axes and colours, and the snapshot's render, point cloud, mesh and PLY
(read back with trimesh, a library made for it)."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest

from aoi3d.field import FieldTrainer, GridConfig, TrainView
from aoi3d.field.snapshot import ModelSnapshot, ply_bytes
from aoi3d.freeview import (
    PoseError,
    aoi_colour,
    c2w_from_viser,
    check_pose,
    check_size,
    free_camera,
    frustum_fov_aspect,
    parse_c2w,
    viser_pose,
)
from aoi3d.scene import SceneConfig, SceneDataset, generate_dataset
from aoi3d.scene.camera import look_at

AABB = np.array([[-2.0, -2.0, 0.0], [2.0, 2.0, 3.0]])


def pose(eye, target=(0.0, 0.0, 1.0)) -> np.ndarray:
    return look_at(np.asarray(eye, float), np.asarray(target, float), np.array([0.0, 0.0, 1.0]))


def test_parse_and_check_accept_a_rigid_pose_near_the_box() -> None:
    c2w = pose((0.0, -4.0, 1.5))
    text = ",".join(f"{v:.6f}" for v in c2w.ravel())
    assert np.allclose(check_pose(text, AABB), c2w, atol=1e-5)
    assert np.allclose(check_pose(c2w, AABB.ravel()), c2w)
    assert np.allclose(parse_c2w(" ".join(map(str, c2w.ravel()))), c2w)


@pytest.mark.parametrize(("value", "says"), [
    ("1,2,3", "16 numbers"),
    (",".join(["1"] * 15 + ["nan"]), "finite"),
    ("a,b", "16 numbers separated"),
    (",".join(map(str, np.diag([2.0, 2.0, 2.0, 1.0]).ravel())), "orthonormal"),
    (",".join(map(str, np.diag([1.0, 1.0, -1.0, 1.0]).ravel())), "reflection"),
    (",".join(map(str, [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 1, 1])), "last row"),
    (",".join(map(str, [1, 0, 0, 500, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1])), "box diagonals"),
])
def test_a_bad_pose_says_why(value: str, says: str) -> None:
    with pytest.raises(PoseError, match=says):
        check_pose(value, AABB)


def test_size_and_free_camera() -> None:
    assert check_size(64, 48) == (64, 48)
    for w, h in ((4, 48), (64, 5000)):
        with pytest.raises(PoseError, match="pixels"):
            check_size(w, h)
    cam = free_camera(pose((0.0, -4.0, 1.5)), 64, 48, fov_y=math.radians(60))
    cam.validate()
    fov, aspect = frustum_fov_aspect(cam)
    assert fov == pytest.approx(math.radians(60)) and aspect == pytest.approx(64 / 48)
    like = free_camera(pose((0.0, -4.0, 1.5)), 32, 32, like=cam)
    assert frustum_fov_aspect(like)[0] == pytest.approx(math.radians(60))


def test_viser_axes_round_trip_and_look_the_same_way() -> None:
    c2w = pose((3.0, -2.0, 2.0))
    cam = free_camera(c2w, 32, 24)
    wxyz, position = viser_pose(cam)
    assert np.allclose(c2w_from_viser(wxyz, position), c2w, atol=1e-9)
    # OpenCV +z (the viewer's forward) is OpenGL −z (the camera's forward)
    from aoi3d.freeview import wxyz_to_matrix
    assert np.allclose(wxyz_to_matrix(wxyz)[:, 2], -c2w[:3, 2])


def test_aoi_colours_go_green_yellow_red_with_gamma() -> None:
    assert aoi_colour(0.0, 100.0) == (46, 204, 64)
    assert aoi_colour(100.0, 100.0) == (255, 220, 0)
    assert aoi_colour(500.0, 100.0) == (230, 30, 30)
    assert aoi_colour(float("nan"), 100.0) == (128, 128, 128)
    assert aoi_colour(50.0, None) == aoi_colour(50.0, 100.0)  # no Γ: 100 ms stands in


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[FieldTrainer, SceneDataset]:
    cfg = SceneConfig(width=32, height=24, fps=10, duration_s=0.4, n_train=6, rotor_rpm=0.0,
                      spp=1)
    ds = generate_dataset(tmp_path_factory.mktemp("scene") / "s", cfg, processes=1)
    grid = GridConfig(batch_rays=256, samples_coarse=24, samples_fine=24, fine_from_step=0,
                      grid_sizes=(24,), upsample_steps=(), background_size=(4, 8),
                      tune_malloc=False)
    trainer = FieldTrainer(grid, np.asarray(ds.aabb), device="cpu", seed=0)
    trainer.set_views([TrainView(camera=ds.cameras[c], image=ds.frame(c, 0))
                       for c in range(len(ds.cameras)) if c != ds.heldout_id])
    trainer.step(150)
    return trainer, ds


def test_snapshot_renders_as_the_trainer_and_stays_put_while_it_trains(trained) -> None:
    trainer, ds = trained
    cam = ds.cameras[ds.heldout_id]
    snap = ModelSnapshot(trainer)
    before = snap.render(cam)
    assert np.array_equal(before, trainer.render(cam))
    twin = trainer.fork()
    twin.step(5)
    assert np.array_equal(snap.render(cam), before)
    other = free_camera(pose((3.0, 3.0, 2.0)), 40, 30, like=cam)
    img = snap.render(other)
    assert img.shape == (30, 40, 3) and not np.array_equal(img[:24, :32], before)


def test_point_cloud_and_mesh_ply_read_back_with_trimesh(trained) -> None:
    trimesh = pytest.importorskip("trimesh")
    trainer, ds = trained
    snap = ModelSnapshot(trainer)
    cloud = snap.point_cloud(resolution=64)
    pc = trimesh.load(io.BytesIO(ply_bytes(cloud)), file_type="ply")
    assert isinstance(pc, trimesh.PointCloud)
    assert len(pc.vertices) >= 1000
    lo, hi = np.asarray(ds.aabb)
    assert np.all(pc.vertices >= lo - 1e-5) and np.all(pc.vertices <= hi + 1e-5)
    colours = np.asarray(pc.colors)[:, :3]
    assert colours.shape == (len(pc.vertices), 3) and len(np.unique(colours, axis=0)) > 10
    mesh = trimesh.load(io.BytesIO(ply_bytes(snap.mesh(resolution=32))), file_type="ply")
    assert isinstance(mesh, trimesh.Trimesh) and len(mesh.faces) > 100
    with pytest.raises(ValueError, match="resolution"):
        snap.point_cloud(resolution=4)


def test_token_bucket_allows_bursts_then_the_rate() -> None:
    from services.dispatcher.views import TokenBucket, ViewRefused

    bucket = TokenBucket(rate_per_s=2.0, burst=3)
    assert [bucket.take(0.0) for _ in range(4)] == [True, True, True, False]
    assert not bucket.take(0.2)  # 0.4 of a token back
    assert bucket.take(0.5)      # a whole one by now
    assert [bucket.take(100.0) for _ in range(4)] == [True, True, True, False]  # capped
    assert ViewRefused("rate_limited", "x").status == 429
    assert ViewRefused("bad_request", "x").status == 422
