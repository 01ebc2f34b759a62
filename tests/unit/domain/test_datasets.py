"""Dataset layouts: DyNeRF videos, D-NeRF / nerfstudio JSON, layout detection, export, CLI."""

from __future__ import annotations

import importlib.util
import json
import math
import shutil
import threading
from io import BytesIO
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from aoi3d.scene import (
    Camera,
    DNeRFDataset,
    DyNeRFDataset,
    SceneConfig,
    SceneDataset,
    detect_layout,
    export_dnerf,
    export_dynerf,
    generate_dataset,
    load_dnerf,
    load_dynerf,
    look_at,
    open_dataset,
)
from aoi3d.scene import dynerf as dy
from aoi3d.scene.dnerf import focus_aabb
from aoi3d.scene.media import PngCache, replace_dir, target_size

TINY = SceneConfig(width=24, height=18, fps=10, duration_s=0.5, n_train=4, rotor_rpm=40.0, spp=2)
"""5 cameras × 5 frames of 24×18 (even sides: H.264 yuv420p needs them)."""
EXPORTED = [0, 1, 3]
"""The cameras written to the DyNeRF fixture: cam02 is missing on purpose."""
MIN_PSNR_DB = 28.0
"""H.264 at crf 15 on these 24×18 frames measures 31.7–34 dB; yuv420p's chroma subsampling,
not the crf, dominates at this size (crf 0 gives 32.8 dB)."""

needs_ffmpeg = pytest.mark.skipif(
    importlib.util.find_spec("imageio_ffmpeg") is None,
    reason="imageio-ffmpeg (the DyNeRF reader's video dependency) is not installed",
)


def psnr_db(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(255.0**2 / mse)


def png_pixels(data: bytes) -> np.ndarray:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    with Image.open(BytesIO(data)) as img:
        return np.asarray(img.convert("RGB"))


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory: pytest.TempPathFactory) -> SceneDataset:
    return generate_dataset(tmp_path_factory.mktemp("syn") / "turbine", TINY)


@pytest.fixture(scope="module")
def dynerf_dir(synthetic: SceneDataset, tmp_path_factory: pytest.TempPathFactory) -> Path:
    if importlib.util.find_spec("imageio_ffmpeg") is None:
        pytest.skip("imageio-ffmpeg is not installed")
    return export_dynerf(synthetic, tmp_path_factory.mktemp("dy") / "scene", camera_ids=EXPORTED)


@pytest.fixture(scope="module")
def dnerf_dir(synthetic: SceneDataset, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return export_dnerf(synthetic, tmp_path_factory.mktemp("dn") / "scene")


def copy_of(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


# --- LLFF poses ------------------------------------------------------------------------------
def test_llff_axes_map_to_opengl_as_documented():
    # LLFF columns [down, right, back] = world x, y, z.
    pose = np.concatenate([np.eye(3), [[1.0], [2.0], [3.0]]], axis=1)
    c2w = dy.llff_to_opengl(pose)
    np.testing.assert_array_equal(c2w[:3, 0], [0.0, 1.0, 0.0])  # right = LLFF right
    np.testing.assert_array_equal(c2w[:3, 1], [-1.0, 0.0, 0.0])  # up = −down
    np.testing.assert_array_equal(c2w[:3, 2], [0.0, 0.0, 1.0])  # back = back
    np.testing.assert_array_equal(c2w[:3, 3], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(c2w[3], [0.0, 0.0, 0.0, 1.0])
    # And back again: an OpenGL look-at camera stores down = −up, right, back.
    gl = look_at((3.0, -4.0, 1.5), (0.0, 0.0, 1.0))
    llff = dy.opengl_to_llff(gl)
    np.testing.assert_allclose(llff[:, 0], -gl[:3, 1], atol=1e-15)
    np.testing.assert_allclose(llff[:, 1], gl[:3, 0], atol=1e-15)
    np.testing.assert_allclose(llff[:, 2], gl[:3, 2], atol=1e-15)
    np.testing.assert_allclose(dy.llff_to_opengl(llff), gl, atol=1e-15)


def test_llff_rejects_non_rotations():
    scaled = np.concatenate([2.0 * np.eye(3), np.zeros((3, 1))], axis=1)
    with pytest.raises(ValueError, match="not a rotation"):
        dy.llff_to_opengl(scaled)
    reflected = np.concatenate([np.diag([1.0, 1.0, -1.0]), np.zeros((3, 1))], axis=1)
    with pytest.raises(ValueError, match="determinant"):
        dy.llff_to_opengl(reflected)
    with pytest.raises(ValueError, match="3×4 or 3×5"):
        dy.llff_to_opengl(np.eye(4))
    # float32 storage noise is absorbed (projected onto the nearest rotation).
    noisy = np.concatenate([np.eye(3) + 1e-7, np.zeros((3, 1))], axis=1)
    dy.llff_to_opengl(noisy)


# --- DyNeRF ----------------------------------------------------------------------------------
@needs_ffmpeg
def test_dynerf_round_trip_with_a_missing_camera(synthetic: SceneDataset, dynerf_dir: Path):
    assert sorted(p.name for p in dynerf_dir.iterdir()) == [
        "cam00.mp4", "cam01.mp4", "cam03.mp4", "poses_bounds.npy"]
    rows = np.load(dynerf_dir / "poses_bounds.npy")
    assert rows.shape == (3, 17) and rows.dtype == np.float64
    hwf = rows[:, :15].reshape(3, 3, 5)[:, :, 4]
    np.testing.assert_allclose(hwf, [[18, 24, synthetic.cameras[i].fx] for i in EXPORTED])

    ds = load_dynerf(dynerf_dir)
    assert isinstance(ds, SceneDataset) and ds.layout == "dynerf"
    assert ds.camera_names == ("cam00", "cam01", "cam03")
    assert ds.heldout_id == 0 and ds.train_ids == [1, 2]
    assert (ds.n_frames, ds.fps, ds.width, ds.height) == (5, 10, 24, 18)
    for new_id, src_id in enumerate(EXPORTED):
        got, want = ds.cameras[new_id], synthetic.cameras[src_id]
        np.testing.assert_allclose(got.c2w, want.c2w, atol=1e-6, rtol=0)
        assert (got.fx, got.fy, got.cx, got.cy, got.width, got.height) == pytest.approx(
            (want.fx, want.fy, want.cx, want.cy, want.width, want.height), abs=1e-9)
        near, far = ds.bounds[new_id]
        assert (near, far) == pytest.approx(dy.aabb_depth_bounds(want, synthetic.aabb))
        for k in range(ds.n_frames):
            image = ds.frame(new_id, k)
            assert image.dtype == np.uint8 and image.shape == (18, 24, 3)
            assert psnr_db(image, synthetic.frame(src_id, k)) >= MIN_PSNR_DB, (new_id, k)
            np.testing.assert_array_equal(png_pixels(ds.frame_png(new_id, k)), image)
            assert ds.frame_time(new_id, k) == k / 5
    # The rotor turns in cam00 and cam03's views: each decoded frame is nearest to its own
    # source frame (none repeated, none out of order).
    for new_id, src_id in ((0, 0), (2, 3)):
        for k in range(ds.n_frames):
            errors = [psnr_db(ds.frame(new_id, k), synthetic.frame(src_id, j)) for j in range(5)]
            assert int(np.argmax(errors)) == k, (new_id, k, errors)
    assert ds.missing_frames() == 0
    assert ds.frame_path(2, 0) == dynerf_dir / "cam03.mp4"
    with pytest.raises(ValueError, match="camera_id"):
        ds.frame(3, 0)
    with pytest.raises(ValueError, match="frame_index"):
        ds.frame(0, 5)


@needs_ffmpeg
def test_dynerf_downscale_scales_the_intrinsics(synthetic: SceneDataset, dynerf_dir: Path):
    full = load_dynerf(dynerf_dir)
    for ds in (load_dynerf(dynerf_dir, downscale=2), load_dynerf(dynerf_dir, width=12)):
        assert (ds.width, ds.height) == (12, 9)
        for got, src in zip(ds.cameras, full.cameras, strict=True):
            assert (got.fx, got.fy) == pytest.approx((src.fx / 2, src.fy / 2))
            assert (got.cx, got.cy, got.width, got.height) == (6.0, 4.5, 12, 9)
            np.testing.assert_array_equal(got.c2w, src.c2w)
        image = ds.frame(1, 3)
        assert image.shape == (9, 12, 3)
        reference = np.asarray(Image.fromarray(synthetic.frame(1, 3)).resize(
            (12, 9), Image.Resampling.BOX))
        assert psnr_db(image, reference) >= MIN_PSNR_DB - 3
    with pytest.raises(ValueError, match="downscale or width"):
        load_dynerf(dynerf_dir, downscale=2, width=12)
    with pytest.raises(ValueError, match="downscale"):
        load_dynerf(dynerf_dir, downscale=0)


@needs_ffmpeg
def test_dynerf_heldout_camera(dynerf_dir: Path, tmp_path: Path):
    ds = load_dynerf(dynerf_dir, heldout=3)
    assert ds.camera_names == ("cam03", "cam00", "cam01") and ds.train_ids == [1, 2]
    np.testing.assert_array_equal(ds.cameras[0].c2w, load_dynerf(dynerf_dir).cameras[2].c2w)
    # Without cam00 the default held-out camera is missing: say so, and how to choose.
    no_cam00 = copy_of(dynerf_dir, tmp_path / "no-cam00")
    (no_cam00 / "cam00.mp4").unlink()
    np.save(no_cam00 / "poses_bounds.npy", np.load(dynerf_dir / "poses_bounds.npy")[1:])
    with pytest.raises(ValueError, match=r"cam00\.mp4 is missing.*heldout"):
        load_dynerf(no_cam00)
    assert load_dynerf(no_cam00, heldout=1).camera_names == ("cam01", "cam03")


@needs_ffmpeg
def test_dynerf_box_holds_every_frustum(dynerf_dir: Path):
    ds = load_dynerf(dynerf_dir)
    points = []
    for cam, (near, far) in zip(ds.cameras, ds.bounds, strict=True):
        u, v = np.meshgrid([0.0, cam.width], [0.0, cam.height])
        origins, dirs = cam.pixel_rays(u.ravel(), v.ravel())
        along = dirs @ -cam.c2w[:3, 2]  # depth per unit length of each corner ray
        for depth in (near, far):
            points.append(origins + dirs * (depth / along)[:, None])
    points = np.concatenate(points)
    np.testing.assert_allclose(ds.aabb, [points.min(0), points.max(0)], atol=1e-9)
    box = [[-1.0, -2.0, 0.0], [1.0, 2.0, 3.0]]
    np.testing.assert_array_equal(load_dynerf(dynerf_dir, aabb=box).aabb, box)
    with pytest.raises(ValueError, match="min < max"):
        load_dynerf(dynerf_dir, aabb=[[1.0, 0.0, 0.0], [0.0, 1.0, 1.0]])


@needs_ffmpeg
def test_dynerf_malformed_inputs_say_what_is_wrong(dynerf_dir: Path, tmp_path: Path):
    rows = np.load(dynerf_dir / "poses_bounds.npy")

    def variant(name: str) -> Path:
        return copy_of(dynerf_dir, tmp_path / name)

    wrong_shape = variant("shape")
    np.save(wrong_shape / "poses_bounds.npy", rows[:, :15])
    with pytest.raises(ValueError, match=r"N×17.*\(3, 15\)"):
        load_dynerf(wrong_shape)

    extra_row = variant("rows")
    np.save(extra_row / "poses_bounds.npy", np.concatenate([rows, rows[:1]]))
    with pytest.raises(ValueError, match=r"4 rows but there are 3 videos \(cam00.mp4, cam01"):
        load_dynerf(extra_row)

    no_poses = variant("no-poses")
    (no_poses / "poses_bounds.npy").unlink()
    with pytest.raises(FileNotFoundError, match=r"poses_bounds\.npy is missing"):
        load_dynerf(no_poses)

    no_videos = tmp_path / "no-videos"
    no_videos.mkdir()
    np.save(no_videos / "poses_bounds.npy", rows)
    with pytest.raises(FileNotFoundError, match=r"no camNN\.mp4"):
        load_dynerf(no_videos)

    broken = variant("broken")
    (broken / "cam01.mp4").write_bytes(b"not a video at all")
    with pytest.raises(ValueError, match=r"cam01\.mp4 is not a readable video"):
        load_dynerf(broken)

    bad_bounds = variant("bounds")
    swapped = rows.copy()
    swapped[:, 15], swapped[:, 16] = rows[:, 16], rows[:, 15]
    np.save(bad_bounds / "poses_bounds.npy", swapped)
    with pytest.raises(ValueError, match="0 < near < far"):
        load_dynerf(bad_bounds)

    aspect = variant("aspect")
    square = rows.copy()
    square[:, 4] = 24.0  # H in the hwf column: 24×24 poses for 24×18 videos
    np.save(aspect / "poses_bounds.npy", square)
    with pytest.raises(ValueError, match="aspect ratios differ"):
        load_dynerf(aspect)

    twice = variant("twice")
    shutil.copy(twice / "cam01.mp4", twice / "cam1.mp4")
    with pytest.raises(ValueError, match="same camera"):
        load_dynerf(twice)

    with pytest.raises(FileNotFoundError, match="not a directory"):
        load_dynerf(tmp_path / "nothing")
    with pytest.raises(ValueError, match="n_frames"):
        load_dynerf(dynerf_dir, n_frames=6)


@needs_ffmpeg
def test_dynerf_videos_of_different_lengths_use_the_shortest(
    synthetic: SceneDataset, dynerf_dir: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
):
    short = copy_of(dynerf_dir, tmp_path / "short")
    frames = [synthetic.frame(3, k) for k in range(3)]
    assert dy.encode_video(short / "cam03.mp4", frames, (24, 18), 10) == 3
    with caplog.at_level("WARNING", logger="aoi3d.scene.dynerf"):
        ds = load_dynerf(short)
    assert ds.n_frames == 3 and "differ in length" in caplog.text
    assert ds.video(0).shape == (3, 18, 24, 3)
    assert psnr_db(ds.frame(2, 2), synthetic.frame(3, 2)) >= MIN_PSNR_DB


@needs_ffmpeg
def test_dynerf_decodes_lazily_once_per_camera(dynerf_dir: Path,
                                               monkeypatch: pytest.MonkeyPatch):
    calls: list[str] = []
    real = dy.decode_video

    def counting(path, size=None, n_frames=None):
        calls.append(Path(path).name)
        return real(path, size, n_frames)

    monkeypatch.setattr(dy, "decode_video", counting)
    ds = load_dynerf(dynerf_dir, n_frames=4)
    assert ds.n_frames == 4 and ds.decoded_bytes == 0 and calls == []
    threads = [threading.Thread(target=ds.frame, args=(1, k)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert calls == ["cam01.mp4"], "concurrent first reads decode a camera once"
    assert ds.decoded_bytes == 4 * 18 * 24 * 3
    png = ds.frame_png(1, 2)
    assert ds.frame_png(1, 2) is png and len(ds.png_cache) == 1
    assert not ds.frame(1, 2).flags.writeable
    ds.preload(processes=2, png=True)
    assert sorted(calls) == ["cam00.mp4", "cam01.mp4", "cam03.mp4"]
    assert ds.decoded_bytes == 3 * 4 * 18 * 24 * 3 and len(ds.png_cache) == 3 * 4


@needs_ffmpeg
def test_dynerf_export_checks_its_input(synthetic: SceneDataset, tmp_path: Path):
    from dataclasses import replace

    cams = list(synthetic.cameras)
    cams[2] = Camera(c2w=cams[2].c2w, fx=cams[2].fx, fy=cams[2].fx * 1.1, cx=12.0, cy=9.0,
                     width=24, height=18)
    with pytest.raises(ValueError, match="one focal length"):
        export_dynerf(replace(synthetic, cameras=cams), tmp_path / "a")
    cams[2] = Camera(c2w=cams[2].c2w, fx=20.0, fy=20.0, cx=11.0, cy=9.0, width=24, height=18)
    with pytest.raises(ValueError, match="principal point"):
        export_dynerf(replace(synthetic, cameras=cams), tmp_path / "a")
    with pytest.raises(ValueError, match="not in the dataset"):
        export_dynerf(synthetic, tmp_path / "a", camera_ids=[7])
    with pytest.raises(ValueError, match="even"):
        dy.encode_video(tmp_path / "odd.mp4", [], (23, 18), 10)
    assert not (tmp_path / "a").exists(), "a failed export leaves nothing behind"
    out = export_dynerf(synthetic, tmp_path / "a", camera_ids=[0, 1], bounds=(0.5, 20.0))
    np.testing.assert_array_equal(np.load(out / "poses_bounds.npy")[:, 15:], [[0.5, 20.0]] * 2)
    with pytest.raises(FileExistsError, match="not empty"):
        export_dynerf(synthetic, out, camera_ids=[0, 1])
    export_dynerf(synthetic, out, camera_ids=[0, 2], overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == ["cam00.mp4", "cam02.mp4",
                                                      "poses_bounds.npy"]
    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "thesis.tex").write_text("keep")
    with pytest.raises(FileExistsError, match="not a dataset"):
        export_dynerf(synthetic, precious, overwrite=True)
    assert (precious / "thesis.tex").read_text() == "keep"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "precious"], "no temp dirs"


# --- D-NeRF / nerfstudio ---------------------------------------------------------------------
def test_dnerf_round_trip(synthetic: SceneDataset, dnerf_dir: Path):
    names = {p.name for p in dnerf_dir.iterdir()}
    assert names == {"train", "test", "transforms_train.json", "transforms_test.json",
                     "transforms_val.json"}
    train = json.loads((dnerf_dir / "transforms_train.json").read_text())
    first = train["frames"][0]
    assert first["file_path"] == "./train/c01_f0000" and first["time"] == 0.0
    assert train["camera_angle_x"] == pytest.approx(synthetic.cameras[1].camera_angle_x)
    with Image.open(dnerf_dir / "train/c01_f0000.png") as img:
        assert img.mode == "RGBA", "D-NeRF's loader expects RGBA"

    ds = open_dataset(dnerf_dir)
    assert isinstance(ds, DNeRFDataset) and ds.layout == "dnerf"
    assert ds.cameras == synthetic.cameras
    assert ds.heldout_id == 0 and ds.train_ids == [1, 2, 3, 4]
    assert ds.splits == ("test", "train", "train", "train", "train")
    assert (ds.n_frames, ds.fps, ds.width, ds.height) == (5, 10, 24, 18)
    np.testing.assert_array_equal(ds.aabb, synthetic.aabb)
    for cam_id in range(5):
        for k in range(5):
            np.testing.assert_array_equal(ds.frame(cam_id, k), synthetic.frame(cam_id, k))
            np.testing.assert_array_equal(png_pixels(ds.frame_png(cam_id, k)), ds.frame(cam_id, k))
            assert ds.frame_time(cam_id, k) == synthetic.frame_time(cam_id, k) == k / 5
    # RGB export: the PNG bytes are passed through unchanged.
    assert ds.missing_frames() == 0


def test_dnerf_rgb_export_passes_png_bytes_through(synthetic: SceneDataset, tmp_path: Path):
    out = export_dnerf(synthetic, tmp_path / "rgb", rgba=False)
    ds = load_dnerf(out)
    assert ds.frame_png(2, 3) == synthetic.frame_png(2, 3)
    assert len(ds.png_cache) == 0


def _write_rgba(path: Path, size: int, colour: tuple[int, int, int]) -> None:
    rgba = np.zeros((size, size, 4), dtype=np.uint8)
    rgba[..., :3] = colour
    rgba[: size // 2, :, 3] = 255  # top half opaque, bottom half transparent
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgba).save(path)


def _circle_pose(angle_deg: float) -> list[list[float]]:
    a = math.radians(angle_deg)
    return look_at((4.0 * math.cos(a), 4.0 * math.sin(a), 0.5), (0.0, 0.0, 0.0)).tolist()


def _monocular(root: Path) -> Path:
    """An original-D-NeRF-style monocular scene: one pose per time, RGBA, no camera ids."""
    splits = {"train": [(0, 0.0), (40, 0.5), (80, 1.0)], "test": [(20, 0.25), (60, 0.75)],
              "val": [(100, 0.1)]}
    for split, shots in splits.items():
        frames = []
        for i, (angle, time) in enumerate(shots):
            _write_rgba(root / split / f"r_{i:03d}.png", 8, (10 * i, 100, 200))
            frames.append({"file_path": f"./{split}/r_{i:03d}", "time": time,
                           "rotation": 0.1, "transform_matrix": _circle_pose(angle)})
        doc = {"camera_angle_x": 0.6911112070083618, "frames": frames}
        (root / f"transforms_{split}.json").write_text(json.dumps(doc))
    return root


def test_dnerf_monocular_scene_is_a_rig_of_single_frame_cameras(tmp_path: Path):
    root = _monocular(tmp_path / "lego")
    assert detect_layout(root) == "dnerf"
    ds = open_dataset(root)
    assert ds.n_frames == 1 and len(ds.cameras) == 6
    assert ds.heldout_id == 0 and ds.train_ids == [1, 2, 3]
    assert ds.splits == ("test", "train", "train", "train", "test", "val")
    assert ds.camera_names[:2] == ("test/r_000", "train/r_000")
    assert [ds.frame_time(i, 0) for i in range(6)] == [0.25, 0.0, 0.5, 1.0, 0.75, 0.1]
    np.testing.assert_allclose(ds.cameras[2].c2w, _circle_pose(40))
    fx = 4.0 / math.tan(0.6911112070083618 / 2)
    assert (ds.cameras[0].fx, ds.cameras[0].fy, ds.cameras[0].cx) == pytest.approx((fx, fx, 4))
    image = ds.frame(2, 0)  # train r_001: colour (10, 100, 200) on top, white below
    np.testing.assert_array_equal(image[:4], np.broadcast_to([10, 100, 200], (4, 8, 3)))
    np.testing.assert_array_equal(image[4:], np.full((4, 8, 3), 255))
    np.testing.assert_array_equal(png_pixels(ds.frame_png(2, 0)), image)
    # Cameras on a circle of radius ≈ 4 looking at the origin: the D-NeRF box.
    np.testing.assert_allclose(ds.aabb, [[-1.5] * 3, [1.5] * 3], atol=0.02)
    small = load_dnerf(root, downscale=2, heldout=1, background=(0, 0, 0))
    assert (small.width, small.height, small.cameras[0].fx) == (4, 4, pytest.approx(fx / 2))
    np.testing.assert_allclose(small.cameras[0].c2w, _circle_pose(60))
    np.testing.assert_array_equal(small.frame(2, 0)[2:], 0)
    with pytest.raises(ValueError, match="test split has 2 cameras"):
        load_dnerf(root, heldout=2)


def test_nerfstudio_single_file_with_camera_ids(tmp_path: Path):
    root = tmp_path / "ns"
    frames = []
    for cam_id in (4, 7):
        for k, time in enumerate((0.5, 0.0, 0.25)):  # out of order on purpose
            name = f"images/c{cam_id}_{k}.jpg"
            (root / "images").mkdir(parents=True, exist_ok=True)
            Image.new("RGB", (6, 4), (cam_id * 20, k * 50, 0)).save(root / name, quality=95)
            frames.append({"file_path": name, "time": time, "camera_id": cam_id,
                           "transform_matrix": _circle_pose(30 * cam_id)})
    doc = {"fl_x": 5.0, "fl_y": 5.5, "cx": 3.1, "cy": 2.0, "w": 6, "h": 4, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(doc))
    ds = open_dataset(root, heldout=7, aabb=[[-1, -1, -1], [1, 1, 1]])
    assert ds.camera_names == ("cam07", "cam04") and ds.train_ids == [1]
    assert ds.n_frames == 3 and ds.splits == ("all", "all")
    assert [ds.frame_time(1, k) for k in range(3)] == [0.0, 0.25, 0.5]
    assert ds.frame_relpath(1, 0) == "images/c4_1.jpg"
    cam = ds.cameras[1]
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (5.0, 5.5, 3.1, 2.0, 6, 4)
    assert abs(int(ds.frame(1, 0)[0, 0, 1]) - 50) <= 3  # JPEG: close, not exact
    png = ds.frame_png(1, 0)  # a JPEG is re-encoded as PNG
    np.testing.assert_array_equal(png_pixels(png), ds.frame(1, 0))
    assert open_dataset(root).camera_names == ("cam04", "cam07"), "default: lowest camera_id"


def test_dnerf_malformed_inputs_say_what_is_wrong(dnerf_dir: Path, tmp_path: Path):
    def variant(name: str, edit) -> Path:
        root = copy_of(dnerf_dir, tmp_path / name)
        doc = json.loads((root / "transforms_train.json").read_text())
        edit(doc)
        (root / "transforms_train.json").write_text(json.dumps(doc))
        return root

    def drop_matrix(doc):
        del doc["frames"][3]["transform_matrix"]

    with pytest.raises(ValueError, match=r"train\.json frame 3 lacks 'transform_matrix'"):
        load_dnerf(variant("matrix", drop_matrix))

    def drop_frame(doc):
        del doc["frames"][7]

    with pytest.raises(ValueError, match="different frame counts"):
        load_dnerf(variant("count", drop_frame))

    def distort(doc):
        doc["k1"] = 0.1

    with pytest.raises(ValueError, match="distortion"):
        load_dnerf(variant("distortion", distort))

    def move(doc):
        doc["frames"][1]["transform_matrix"] = _circle_pose(10)

    with pytest.raises(ValueError, match="different poses"):
        load_dnerf(variant("moving", move))

    def no_focal(doc):
        for key in ("fl_x", "fl_y", "camera_angle_x"):
            doc.pop(key)

    with pytest.raises(ValueError, match="no focal length"):
        load_dnerf(variant("focal", no_focal))

    def late(doc):
        doc["frames"][0]["time"] = 1.5

    with pytest.raises(ValueError, match=r"time must be in \[0, 1\]"):
        load_dnerf(variant("time", late))

    missing = copy_of(dnerf_dir, tmp_path / "missing")
    (missing / "train/c02_f0001.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"1 image file\(s\) missing.*c02_f0001.png"):
        load_dnerf(missing)
    no_train = copy_of(dnerf_dir, tmp_path / "no-train")
    (no_train / "transforms_train.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"transforms_train\.json is missing"):
        load_dnerf(no_train)
    shutil.copy(dnerf_dir / "transforms_train.json", no_train / "transforms_train.json")
    (no_train / "transforms_test.json").write_text("{oops")
    with pytest.raises(ValueError, match=r"transforms_test\.json is not valid JSON"):
        load_dnerf(no_train)
    with pytest.raises(FileNotFoundError, match="not a directory"):
        load_dnerf(tmp_path / "nowhere")
    with pytest.raises(ValueError, match="held-out camera_id 9"):
        load_dnerf(dnerf_dir, heldout=9)


# --- detection, the shared interface, helpers ------------------------------------------------
@needs_ffmpeg
def test_open_dataset_detects_each_layout(synthetic, dnerf_dir, dynerf_dir, tmp_path):
    assert detect_layout(synthetic.root) == "aoi3d"
    assert detect_layout(dnerf_dir) == "dnerf"
    assert detect_layout(dynerf_dir) == "dynerf"
    assert isinstance(open_dataset(dynerf_dir), DyNeRFDataset)
    own = open_dataset(synthetic.root)
    assert own.layout == "aoi3d" and own.cameras == synthetic.cameras
    assert own.camera_name(3) == "cam03" and own.scene_config() == TINY
    with pytest.raises(ValueError, match="no aoi3d scene config"):
        open_dataset(dnerf_dir).scene_config()
    box = [[-1.0, -1.0, 0.0], [1.0, 1.0, 2.0]]
    np.testing.assert_array_equal(open_dataset(synthetic.root, aabb=box).aabb, box)
    with pytest.raises(ValueError, match="downscale: not supported by the aoi3d layout"):
        open_dataset(synthetic.root, downscale=2)
    with pytest.raises(ValueError, match="unknown layout"):
        open_dataset(synthetic.root, layout="colmap")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match=r"poses_bounds\.npy"):
        detect_layout(tmp_path / "empty")
    with pytest.raises(FileNotFoundError, match="nothing does not exist"):
        open_dataset(tmp_path / "nothing")


@needs_ffmpeg
def test_every_layout_serves_the_camera_service_interface(synthetic, dnerf_dir, dynerf_dir):
    """What the camera worker uses: ids, timing, cameras, PNG frames of the camera's size."""
    for ds in (synthetic, open_dataset(dnerf_dir), open_dataset(dynerf_dir)):
        assert ds.heldout_id == 0 and ds.heldout_id not in ds.train_ids
        assert ds.train_ids == list(range(1, len(ds.train_ids) + 1))
        index = ds.frame_index(730.0)
        assert index == 2 and ds.scene_time_ms(730.0) == 200.0
        for n in (ds.heldout_id, *ds.train_ids):
            camera = ds.cameras[n]
            camera.validate()
            assert png_pixels(ds.frame_png(n, index)).shape == (camera.height, camera.width, 3)
        assert ds.aabb.shape == (2, 3) and np.all(ds.aabb[0] < ds.aabb[1])


def test_focus_box_needs_converging_axes():
    parallel = [Camera(c2w=look_at((x, -5.0, 0.0), (x, 0.0, 0.0)), fx=5, fy=5, cx=3, cy=2,
                       width=6, height=4) for x in (0.0, 1.0, 2.0)]
    with pytest.raises(ValueError, match="pass aabb"):
        focus_aabb(parallel)


def test_media_helpers(tmp_path: Path):
    assert target_size(2704, 2028) == (2704, 2028)
    assert target_size(2704, 2028, downscale=2) == (1352, 1014)
    assert target_size(2704, 2028, target_width=480) == (480, 360)
    with pytest.raises(ValueError):
        target_size(10, 10, target_width=0)
    cache = PngCache(max_bytes=10)
    assert cache.get((0, 0), lambda: b"12345678") == b"12345678"
    assert cache.get((0, 1), lambda: b"abcdefgh") == b"abcdefgh"
    assert len(cache) == 1 and cache.nbytes == 8, "over budget: served, not kept"
    with pytest.raises(RuntimeError), replace_dir(tmp_path / "out") as tmp:
        (tmp / "partial").write_text("x")
        raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == [], "an interrupted write leaves nothing"


# --- CLI -------------------------------------------------------------------------------------
@needs_ffmpeg
def test_cli_export_and_info_on_any_layout(synthetic: SceneDataset, tmp_path: Path):
    from typer.testing import CliRunner

    from aoi3d_cli import scene as scene_cli

    runner = CliRunner()
    for fmt in ("dynerf", "dnerf"):
        out = tmp_path / fmt
        result = runner.invoke(scene_cli.app, ["export", "--format", fmt, "--out", str(out),
                                               "--dataset", str(synthetic.root)])
        assert result.exit_code == 0, result.output
        assert f"wrote {fmt}" in result.output and detect_layout(out) == fmt
        info = runner.invoke(scene_cli.app, ["info", str(out)])
        assert info.exit_code == 0, info.output
        text = " ".join(info.output.split())  # rich wraps long lines
        assert f"{fmt} layout" in text and "5 cameras (held-out 0, train 1..4)" in text
        assert "held-out" in text and "cam04" in text
    small = runner.invoke(scene_cli.app, ["info", str(tmp_path / "dynerf"), "--downscale", "2"])
    assert small.exit_code == 0 and "12×9 px" in " ".join(small.output.split())
    # Convert a video dataset once into a smaller lossless one.
    result = runner.invoke(scene_cli.app, ["export", "--format", "dnerf", "--out",
                                           str(tmp_path / "small"), "--dataset",
                                           str(tmp_path / "dynerf"), "--width", "12"])
    assert result.exit_code == 0, result.output
    small_ds = open_dataset(tmp_path / "small")
    assert (small_ds.width, small_ds.height, small_ds.n_frames) == (12, 9, 5)
    again = runner.invoke(scene_cli.app, ["export", "--format", "dnerf", "--out",
                                          str(tmp_path / "dnerf"), "--dataset",
                                          str(synthetic.root)])
    assert again.exit_code == 1 and "not empty" in " ".join(again.output.split())
    bad = runner.invoke(scene_cli.app, ["export", "--format", "colmap", "--out",
                                        str(tmp_path / "x"), "--dataset", str(synthetic.root)])
    assert bad.exit_code != 0 and not (tmp_path / "x").exists()
    missing = runner.invoke(scene_cli.app, ["info", str(tmp_path / "nothing")])
    assert missing.exit_code == 1 and "nothing does not exist" in " ".join(missing.output.split())
