"""The synthetic turbine scene: camera, rig, renderer, dataset on disk, CLI."""

from __future__ import annotations

import json
import math
from io import BytesIO

import numpy as np
import pytest
from PIL import Image

from aoi3d.scene import (
    Camera,
    SceneConfig,
    TurbineScene,
    ensure_dataset,
    generate_dataset,
    load_dataset,
    look_at,
    place_cameras,
    to_uint8,
)
from aoi3d.scene import turbine as T

TINY = SceneConfig(width=24, height=18, fps=10, duration_s=0.5, n_train=4, rotor_rpm=40.0, spp=2)
"""5 frames per camera; 40 rpm × 0.5 s = one blade pass per loop (seamless)."""


def _camera(eye, target, width=24, height=18, fx=20.0) -> Camera:
    return Camera(
        c2w=look_at(eye, target),
        fx=fx,
        fy=fx,
        cx=width / 2,
        cy=height / 2,
        width=width,
        height=height,
    )


def _misses_box(origins: np.ndarray, dirs: np.ndarray, aabb: np.ndarray) -> np.ndarray:
    """Slab test: True where the ray never meets the box (with a small safety margin)."""
    lo, hi = aabb[0] - 1e-3, aabb[1] + 1e-3
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - origins) / dirs, (hi - origins) / dirs
    t_near = np.nanmax(np.minimum(t1, t2), axis=-1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=-1)
    return (t_far < t_near) | (t_far < 0)


# --- camera ----------------------------------------------------------------------------------
def test_camera_rays_are_unit_and_pass_through_pixel_centres():
    cam = _camera((3.0, -4.0, 1.5), (0.0, 0.0, 1.0))
    origins, dirs = cam.rays()
    assert origins.shape == dirs.shape == (18, 24, 3)
    assert origins.dtype == dirs.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0, atol=1e-6)
    np.testing.assert_allclose(origins, np.broadcast_to(cam.position, origins.shape), atol=1e-6)
    uv, depth = cam.project((origins + 2.0 * dirs).reshape(-1, 3))
    assert np.all(depth > 0)
    jj, ii = np.mgrid[0:18, 0:24]
    expected = np.stack([ii + 0.5, jj + 0.5], axis=-1).reshape(-1, 2)
    np.testing.assert_allclose(uv, expected, atol=1e-4)


def test_look_at_is_opengl_and_rigid():
    c2w = look_at((0.0, -5.0, 1.0), (0.0, 0.0, 1.0))
    np.testing.assert_allclose(-c2w[:3, 2], [0.0, 1.0, 0.0], atol=1e-12)  # looks along −z
    np.testing.assert_allclose(c2w[:3, 1], [0.0, 0.0, 1.0], atol=1e-12)  # y up
    np.testing.assert_allclose(c2w[:3, 0], [1.0, 0.0, 0.0], atol=1e-12)  # x right
    _camera((0.0, -5.0, 1.0), (0.0, 0.0, 1.0)).validate()
    with pytest.raises(ValueError):
        look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0))  # straight down: parallel to up


def test_validate_rejects_nan_and_non_rigid_poses():
    good = look_at((0.0, -5.0, 1.0), (0.0, 0.0, 1.0))
    kw = dict(fx=20.0, fy=20.0, cx=12.0, cy=9.0, width=24, height=18)
    Camera(c2w=good, **kw).validate()
    nan = good.copy()
    nan[0, 3] = np.nan
    scaled = good.copy()
    scaled[:3, :3] *= 1.01
    reflected = good.copy()
    reflected[:3, 0] *= -1.0
    sheared = good.copy()
    sheared[:3, 1] += 0.05 * sheared[:3, 0]
    bottom = good.copy()
    bottom[3, 0] = 0.5
    for bad, what in [
        (nan, "non-finite"),
        (scaled, "orthonormal"),
        (reflected, "determinant"),
        (sheared, "orthonormal"),
        (bottom, "last row"),
    ]:
        with pytest.raises(ValueError, match=what):
            Camera(c2w=bad, **kw).validate()
    with pytest.raises(ValueError, match="focal"):
        Camera(c2w=good, **{**kw, "fx": 0.0}).validate()
    with pytest.raises(ValueError, match="4×4"):
        Camera(c2w=np.eye(3), **kw)


def test_camera_dict_round_trip_and_equality():
    cam = _camera((1.0, -4.0, 2.0), (0.0, 0.0, 1.0))
    back = Camera.from_dict(json.loads(json.dumps(cam.to_dict())))
    assert back == cam and hash(back) == hash(cam)
    assert back != _camera((1.0, -4.0, 2.1), (0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="lacks"):
        Camera.from_dict({"c2w": np.eye(4).tolist()})


# --- config ----------------------------------------------------------------------------------
def test_scene_config_defaults_and_validation():
    cfg = SceneConfig()
    assert (cfg.width, cfg.height, cfg.fps, cfg.duration_s) == (96, 72, 30, 10.0)
    assert (cfg.n_train, cfg.rotor_rpm, cfg.spp, cfg.n_frames) == (18, 18.0, 3, 300)
    assert cfg.seamless and cfg.blade_passes == pytest.approx(9.0)
    odd = SceneConfig(duration_s=2.0)
    assert not odd.seamless and odd.seamless_rpm() == pytest.approx((10.0, 20.0))
    for bad in [
        dict(width=0),
        dict(spp=0),
        dict(fps=7, duration_s=0.5),  # 3.5 frames
        dict(duration_s=float("nan")),
        dict(rotor_rpm=float("inf")),
        dict(seed=-1),
        dict(width=9.5),
    ]:
        with pytest.raises(ValueError):
            SceneConfig(**bad)
    assert SceneConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="unknown"):
        SceneConfig.from_dict({"wdth": 3})
    assert cfg.config_hash == SceneConfig().config_hash
    assert cfg.config_hash != SceneConfig(seed=1).config_hash


# --- rig -------------------------------------------------------------------------------------
@pytest.mark.parametrize("n_train", [18, 5, 1])
def test_rig_poses_are_rigid_and_look_at_the_turbine(n_train):
    cfg = SceneConfig(width=24, height=18, n_train=n_train)
    rig = place_cameras(cfg)
    assert len(rig) == n_train + 1
    turbine = np.array(
        [
            [0.0, 0.0, 0.02],  # tower foot
            [0.0, 0.0, 0.8],
            T.HUB_CENTRE,
            T.NACELLE_HI,
            T.HUB_CENTRE + np.array([T.BLADE_TIP, 0.0, 0.0]),
            T.HUB_CENTRE - np.array([T.BLADE_TIP, 0.0, 0.0]),
            T.HUB_CENTRE - np.array([0.0, 0.0, T.BLADE_TIP]),
        ]
    )
    for cam in rig:
        cam.validate()
        assert (cam.width, cam.height) == (24, 18)
        assert np.linalg.norm(cam.position[:2]) > math.hypot(2.0, 2.0)  # outside the box
        uv, depth = cam.project(turbine)
        assert np.all(depth > 0)
        assert np.all((uv[:, 0] > 0) & (uv[:, 0] < 24) & (uv[:, 1] > 0) & (uv[:, 1] < 18)), uv
        # The turbine (foot to hub) fills a good part of the image height.
        assert uv[0, 1] - uv[2, 1] > 0.4 * 18
    held_out = rig[0].position
    gaps = [np.linalg.norm(held_out - cam.position) for cam in rig[1:]]
    assert min(gaps) > 0.2, "camera 0 must not coincide with a training camera"
    # Camera 0 sits in the middle of the arc: within the azimuth range of the training rig.
    az = [math.atan2(c.position[1], c.position[0]) for c in rig]
    if n_train > 1:
        assert min(az[1:]) < az[0] < max(az[1:])


def test_rig_training_cameras_span_an_arc_of_about_180_degrees():
    rig = place_cameras(SceneConfig(width=24, height=18))
    az = np.degrees([math.atan2(c.position[1], c.position[0]) for c in rig[1:]])
    assert 150 < az.max() - az.min() <= 180
    assert len({tuple(np.round(c.position, 6)) for c in rig}) == len(rig)


# --- rendering -------------------------------------------------------------------------------
def test_render_is_deterministic_and_seeded():
    cam = place_cameras(TINY)[0]
    a = TurbineScene(TINY).render(cam, 0.13)
    b = TurbineScene(TINY).render(cam, 0.13)
    assert a.dtype == np.float32 and a.shape == (18, 24, 3)
    assert a.min() >= 0.0 and a.max() <= 1.0
    np.testing.assert_array_equal(a, b)
    other = TurbineScene(SceneConfig(**{**TINY.to_dict(), "seed": 7})).render(cam, 0.13)
    assert not np.array_equal(a, other), "the seed drives the texture noise"


def test_blades_move_while_the_static_ground_does_not():
    cfg = SceneConfig(width=48, height=36, spp=2)
    scene = TurbineScene(cfg)
    cam = place_cameras(cfg)[0]
    a, b = scene.render(cam, 0.0), scene.render(cam, 0.5)
    changed = np.any(a != b, axis=-1)
    assert changed.sum() > 20, "the blades must move between frames"
    # Everything that changed lies inside the projected rotor disc (plus a pixel).
    uv_hub, depth = cam.project(T.HUB_CENTRE[None])
    r_px = cam.fx * (T.BLADE_TIP + 0.05) / (depth[0] - 0.2) + 1.5
    jj, ii = np.nonzero(changed)
    dist = np.hypot(ii + 0.5 - uv_hub[0, 0], jj + 0.5 - uv_hub[0, 1])
    assert np.all(dist <= r_px)
    # A pixel whose ray lands on the textured ground square away from the turbine never changes.
    origins, dirs = cam.rays()
    j, i = cam.height - 1, 2
    t = -origins[j, i, 2] / dirs[j, i, 2]
    ground = origins[j, i] + t * dirs[j, i]
    assert t > 0 and np.all(np.abs(ground[:2]) < 2.0)
    frames = scene.render_times(cam, np.linspace(0.0, 1.0, 7))
    assert np.all(frames[:, j, i] == frames[0, j, i])


def test_culled_render_equals_brute_force():
    """The fast path (static layer + culled blades) is bit-identical to intersecting every
    sample ray with every blade."""
    cfg = SceneConfig(width=32, height=24, spp=2)
    fast, brute = TurbineScene(cfg), TurbineScene(cfg, _cull=False)
    rig = place_cameras(cfg)
    times = [0.0, 0.37, 1.21, 2.9]
    for cam in (rig[0], rig[1], rig[len(rig) // 3]):
        np.testing.assert_array_equal(fast.render_times(cam, times), brute.render_times(cam, times))


def test_loop_is_seamless_with_three_identical_blades():
    scene = TurbineScene(TINY)
    cam = place_cameras(TINY)[0]
    start, end = scene.render(cam, 0.0), scene.render(cam, TINY.duration_s)  # one blade pass
    assert np.mean(np.abs(start - end)) < 1e-4
    assert not np.array_equal(start, scene.render(cam, TINY.duration_s / 2))


def test_outside_the_box_colour_depends_on_direction_only():
    cfg = SceneConfig(width=40, height=30, spp=1)
    scene = TurbineScene(cfg)
    # Same orientation, two positions, wide field of view: many rays pass beside the box,
    # some above the horizon (sky), some below it (distant ground).
    c2w = look_at((4.5, -4.5, 1.0), (0.0, 0.0, 0.6))
    moved = c2w.copy()
    moved[:3, 3] += (0.6, -0.9, 0.5)
    cams = [
        Camera(c2w=m, fx=12.0, fy=12.0, cx=20.0, cy=15.0, width=40, height=30) for m in (c2w, moved)
    ]
    images = [scene.render(cam, 0.3) for cam in cams]
    rays = [cam.rays() for cam in cams]
    np.testing.assert_allclose(rays[0][1], rays[1][1], atol=1e-6)  # same directions
    out = _misses_box(*rays[0], scene.aabb) & _misses_box(*rays[1], scene.aabb)
    dz = rays[0][1][..., 2]
    assert (out & (dz > 0.02)).sum() > 20 and (out & (dz < -0.02)).sum() > 20
    np.testing.assert_allclose(images[0][out], images[1][out], atol=1e-6)
    np.testing.assert_allclose(images[0][out], scene.background(rays[0][1][out]), atol=1e-5)
    # ... and the rays that do meet the scene see it differently from the two positions.
    assert np.abs(images[0][~out] - images[1][~out]).max() > 0.1
    # The background itself: sky above, ground below, continuous at the horizon.
    sky, far = scene.background(np.array([[0.0, 0.6, 0.8], [0.0, 0.6, -0.8]]))
    assert sky[2] > sky[1] and far[1] > far[2]
    eps = 1e-7
    h = scene.background(np.array([[1.0, 0.0, eps], [1.0, 0.0, -eps]]))
    np.testing.assert_allclose(h[0], h[1], atol=1e-3)


def test_anti_aliasing_averages_stratified_samples():
    """spp = 3 at W×H is the 3×3 block mean of spp = 1 at 3W×3H (same sample positions), and
    edges get intermediate colours."""
    lo_cfg = SceneConfig(width=24, height=18, spp=3)
    hi_cfg = SceneConfig(width=72, height=54, spp=1)
    cam = place_cameras(lo_cfg)[0]
    cam_hi = Camera(
        c2w=cam.c2w, fx=3 * cam.fx, fy=3 * cam.fy, cx=3 * cam.cx, cy=3 * cam.cy, width=72, height=54
    )
    lo = TurbineScene(lo_cfg).render(cam, 0.2)
    hi = TurbineScene(hi_cfg).render(cam_hi, 0.2)
    blocks = hi.reshape(18, 3, 24, 3, 3)
    mean = blocks.mean(axis=(1, 3))
    assert np.mean(np.abs(lo - mean) < 1e-4) > 0.99
    spread = blocks.max(axis=(1, 3)) - blocks.min(axis=(1, 3))
    edges = spread.max(axis=-1) > 0.3
    assert edges.sum() >= 10, "the scene has sharp edges"
    assert np.all(lo[edges] > blocks.min(axis=(1, 3))[edges] - 1e-6)
    assert np.all(lo[edges] < blocks.max(axis=(1, 3))[edges] + 1e-6)
    strictly_between = (lo[edges] > blocks.min(axis=(1, 3))[edges] + 0.05) & (
        lo[edges] < blocks.max(axis=(1, 3))[edges] - 0.05
    )
    assert strictly_between.any(axis=-1).mean() > 0.5
    aliased = TurbineScene(SceneConfig(width=24, height=18, spp=1)).render(cam, 0.2)
    assert len(np.unique(to_uint8(lo).reshape(-1, 3), axis=0)) > len(
        np.unique(to_uint8(aliased).reshape(-1, 3), axis=0)
    )


def test_render_rejects_bad_input():
    scene = TurbineScene(TINY)
    cam = place_cameras(TINY)[0]
    with pytest.raises(ValueError):
        scene.render(cam, float("nan"))
    bad = np.array(cam.c2w)
    bad[:3, :3] *= 2.0
    with pytest.raises(ValueError):
        scene.render(Camera(c2w=bad, fx=20.0, fy=20.0, cx=12, cy=9, width=24, height=18), 0.0)


# --- dataset ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    return generate_dataset(tmp_path_factory.mktemp("scene") / "tiny", TINY)


def test_dataset_round_trip(tiny_dataset):
    ds = tiny_dataset
    rig = place_cameras(TINY)
    assert ds.cameras == rig and ds.heldout_id == 0 and ds.train_ids == [1, 2, 3, 4]
    assert (ds.fps, ds.n_frames, ds.width, ds.height) == (10, 5, 24, 18)
    np.testing.assert_array_equal(ds.aabb, TurbineScene(TINY).aabb)
    assert ds.config == TINY.to_dict() and ds.config_hash == TINY.config_hash
    assert ds.scene_config() == TINY
    # The files themselves (D-NeRF / nerfstudio style).
    train = json.loads((ds.root / "transforms_train.json").read_text())
    test = json.loads((ds.root / "transforms_test.json").read_text())
    assert train["w"] == 24 and train["h"] == 18
    assert train["fl_x"] == pytest.approx(rig[1].fx) and train["cy"] == pytest.approx(9.0)
    assert train["camera_angle_x"] == pytest.approx(2 * math.atan(12 / rig[1].fx))
    assert {f["camera_id"] for f in train["frames"]} == {1, 2, 3, 4}
    assert {f["camera_id"] for f in test["frames"]} == {0}
    assert len(train["frames"]) == 4 * 5 and len(test["frames"]) == 5
    for frame in train["frames"] + test["frames"]:
        assert frame["file_path"].endswith(".png") and (ds.root / frame["file_path"]).is_file()
        assert 0.0 <= frame["time"] <= 1.0
        assert frame["time"] == pytest.approx(frame["frame_index"] / 5)
        np.testing.assert_array_equal(frame["transform_matrix"], rig[frame["camera_id"]].c2w)
    meta = train["aoi3d"]
    assert (meta["fps"], meta["n_frames"], meta["config_hash"]) == (10, 5, TINY.config_hash)
    # Frames: PNG bytes as stored, decoding to the renderer's output.
    scene = TurbineScene(TINY)
    for cam_id, k in [(0, 0), (0, 3), (2, 1), (4, 4)]:
        png = ds.frame_png(cam_id, k)
        assert png == (ds.root / f"frames/cam{cam_id:02d}/{k:04d}.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        img = ds.frame(cam_id, k)
        assert img.dtype == np.uint8 and img.shape == (18, 24, 3)
        np.testing.assert_array_equal(np.asarray(Image.open(BytesIO(png))), img)
        np.testing.assert_array_equal(img, to_uint8(scene.render(rig[cam_id], k / 10)))
    with pytest.raises(ValueError):
        ds.frame(5, 0)
    with pytest.raises(ValueError):
        ds.frame(0, 5)


def test_dataset_timing_loops(tiny_dataset):
    ds = tiny_dataset  # 10 fps, 5 frames: a 500 ms loop
    assert ds.duration_ms == 500.0
    assert [ds.frame_index(t) for t in (0, 99.9, 100, 499, 500, 730)] == [0, 0, 1, 4, 0, 2]
    assert all(ds.frame_index(k * 100.0) == k % 5 for k in range(12))
    assert all(ds.frame_index(k * 1000.0 / 30.0 * 3) == k % 5 for k in range(12))
    assert ds.scene_time_ms(730.0) == 200.0
    assert ds.scene_time_ms(1499.0) == 400.0


def test_load_dataset_works_from_json_alone(tiny_dataset, tmp_path):
    copy = tmp_path / "json-only"
    copy.mkdir()
    for name in ("transforms_train.json", "transforms_test.json"):
        (copy / name).write_bytes((tiny_dataset.root / name).read_bytes())
    ds = load_dataset(copy)
    assert ds.cameras == tiny_dataset.cameras and ds.n_frames == 5
    assert ds.missing_frames() == 5 * 5


def test_load_dataset_errors(tmp_path, tiny_dataset):
    with pytest.raises(FileNotFoundError):
        load_dataset(tmp_path / "nothing")
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "transforms_train.json").write_text("{not json")
    (broken / "transforms_test.json").write_text("{}")
    with pytest.raises(ValueError):
        load_dataset(broken)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    for name in ("transforms_train.json", "transforms_test.json"):
        doc = json.loads((tiny_dataset.root / name).read_text())
        doc.pop("aoi3d")
        (foreign / name).write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="aoi3d"):
        load_dataset(foreign)


def test_ensure_dataset_caches_by_config(tmp_path):
    path = tmp_path / "scene"
    calls: list[tuple[int, int]] = []
    first = ensure_dataset(path, TINY, progress=lambda d, t: calls.append((d, t)))
    assert calls and calls[-1] == (25, 25)
    stamp = (path / "transforms_train.json").stat().st_mtime_ns
    calls.clear()
    again = ensure_dataset(path, TINY, progress=lambda d, t: calls.append((d, t)))
    assert calls == [] and again.config_hash == first.config_hash
    assert (path / "transforms_train.json").stat().st_mtime_ns == stamp
    # Another config → regenerated in place.
    before = first.frame_png(0, 0)
    other = SceneConfig(**{**TINY.to_dict(), "seed": 3})
    redone = ensure_dataset(path, other, progress=lambda d, t: calls.append((d, t)))
    assert calls and redone.config_hash == other.config_hash != first.config_hash
    assert redone.frame_png(0, 0) != before, "another texture seed, other pixels"
    assert load_dataset(path).config_hash == other.config_hash
    # A missing frame also triggers regeneration.
    (path / "frames/cam01/0002.png").unlink()
    calls.clear()
    ensure_dataset(path, other, progress=lambda d, t: calls.append((d, t)))
    assert calls and (path / "frames/cam01/0002.png").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"], "no temp dirs left"


def test_generation_is_atomic_and_deterministic(tmp_path):
    path = tmp_path / "scene"

    def interrupt(done: int, total: int) -> None:
        if done >= 10:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        generate_dataset(path, TINY, progress=interrupt)
    assert not path.exists(), "an interrupted generation must not look complete"
    assert list(tmp_path.iterdir()) == []
    a = generate_dataset(tmp_path / "a", TINY)
    b = generate_dataset(tmp_path / "b", TINY)
    files = sorted(p.relative_to(a.root) for p in a.root.rglob("*") if p.is_file())
    assert len(files) == 5 * 5 + 2
    for rel in files:
        assert (a.root / rel).read_bytes() == (b.root / rel).read_bytes(), rel


def test_parallel_generation_matches_serial(tmp_path, tiny_dataset):
    cfg = SceneConfig(**{**TINY.to_dict(), "n_train": 2})
    serial = generate_dataset(tmp_path / "serial", cfg)
    parallel = generate_dataset(tmp_path / "parallel", cfg, processes=2)
    for cam_id in range(3):
        for k in range(5):
            assert serial.frame_png(cam_id, k) == parallel.frame_png(cam_id, k)


def test_generate_refuses_to_replace_a_foreign_directory(tmp_path):
    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "thesis.tex").write_text("do not delete")
    with pytest.raises(FileExistsError):
        generate_dataset(precious, TINY)
    with pytest.raises(FileExistsError):
        ensure_dataset(precious, TINY)
    assert (precious / "thesis.tex").read_text() == "do not delete"


# --- CLI -------------------------------------------------------------------------------------
def test_cli_generate_and_info(tmp_path):
    from typer.testing import CliRunner

    from aoi3d_cli import scene as scene_cli

    runner = CliRunner()
    out = tmp_path / "cli"
    args = [
        "generate",
        "--out",
        str(out),
        "--width",
        "24",
        "--height",
        "18",
        "--fps",
        "10",
        "--duration-s",
        "0.5",
        "--rotor-rpm",
        "40",
        "--spp",
        "1",
        "--seed",
        "2",
    ]
    result = runner.invoke(scene_cli.app, args)
    assert result.exit_code == 0, result.output
    assert "wrote" in result.output and str(out) in result.output
    ds = load_dataset(out)
    assert ds.config["seed"] == 2 and ds.config["spp"] == 1 and ds.n_frames == 5
    result = runner.invoke(scene_cli.app, args)
    assert result.exit_code == 0 and "up to date" in result.output
    result = runner.invoke(scene_cli.app, [*args, "--force"])
    assert result.exit_code == 0 and "wrote" in result.output
    result = runner.invoke(scene_cli.app, ["info", str(out)])
    assert result.exit_code == 0, result.output
    assert "held-out" in result.output and "19 cameras" in result.output
    assert "aabb" in result.output
    bad = runner.invoke(
        scene_cli.app, ["generate", "--out", str(out), "--fps", "7", "--duration-s", "0.5"]
    )
    assert bad.exit_code != 0
    missing = runner.invoke(scene_cli.app, ["info", str(tmp_path / "nothing")])
    assert missing.exit_code == 1


# --- framing ---------------------------------------------------------------------------------
def test_rotor_framing_is_a_forward_facing_close_up_of_the_rotor():
    cfg = SceneConfig(width=48, height=36, spp=1, framing="rotor", rotor_rpm=6.0)
    rig = place_cameras(cfg)
    az = np.degrees([math.atan2(c.position[1], c.position[0]) for c in rig[1:]])
    assert 55 < az.max() - az.min() <= 65  # a 60° arc, as a DyNeRF-like rig
    for cam in rig:
        cam.validate()
        uv, depth = cam.project(np.array([T.HUB_CENTRE]))
        assert depth[0] > 0
        np.testing.assert_allclose(uv[0], [24.0, 18.0], atol=1.0)  # every camera aims at the hub
    # Everything the rotor cameras can see lies in the (smaller) rotor box.
    box = TurbineScene(cfg).aabb
    np.testing.assert_array_equal(box, T.ROTOR_AABB)
    tips = T.HUB_CENTRE + T.BLADE_TIP * np.array([[1, 0, 0], [-1, 0, 0], [0, 0, 1], [0, 0, -1.0]])
    assert np.all((tips >= box[0]) & (tips <= box[1]))
    # The blades are a large share of the pixels: at the same rotor speed a third of a second
    # changes about four times as many pixels as in the site framing (a few per cent there).
    site = SceneConfig(width=48, height=36, spp=1, rotor_rpm=6.0)

    def moved(c: SceneConfig) -> float:
        scene, cam = TurbineScene(c), place_cameras(c)[0]
        return float(np.any(scene.render(cam, 1.0) != scene.render(cam, 1.0 + 1 / 3), -1).mean())

    assert moved(cfg) > 0.1
    assert moved(cfg) > 3 * moved(site)


def test_framing_is_validated_and_keeps_the_site_hash():
    with pytest.raises(ValueError, match="framing must be one of"):
        SceneConfig(framing="aerial")
    site = SceneConfig()
    doc = {k: v for k, v in site.to_dict().items() if k != "framing"}
    payload = json.dumps({"scene_version": T.SCENE_VERSION, **doc}, sort_keys=True, default=float)
    import hashlib

    # Datasets generated before the framing existed keep their hash (no needless regeneration).
    assert site.config_hash == hashlib.sha256(payload.encode()).hexdigest()[:16]
    assert SceneConfig(framing="rotor").config_hash != site.config_hash
    assert SceneConfig.from_dict(SceneConfig(framing="rotor").to_dict()).framing == "rotor"
