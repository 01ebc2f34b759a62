"""The radiance field: rays, sampler, volume renderer, grid, optimizer and trainer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from aoi3d.field import (
    BACKENDS,
    DenseGridField,
    FieldTrainer,
    GridConfig,
    LazyAdam,
    TrainView,
    camera_rays,
    field_config,
    native,
    ray_aabb,
    sample_uniform,
    volume_render,
)
from aoi3d.scene.camera import Camera, look_at

BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
SPHERE_RADIUS = 0.5
SPHERE_RGB = np.array([0.9, 0.2, 0.1])


# --- a tiny analytic scene: a red sphere in the box, a background of the direction ----------
def _camera(azimuth_deg: float, elevation_deg: float = 20.0, size: int = 16) -> Camera:
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    eye = 3.0 * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
    return Camera(
        look_at(eye, (0, 0, 0)), fx=size, fy=size, cx=size / 2, cy=size / 2, width=size, height=size
    )


def _background(dirs: np.ndarray) -> np.ndarray:
    return 0.5 + 0.4 * dirs


def _image(camera: Camera) -> np.ndarray:
    o, d = (a.astype(np.float64) for a in camera.rays())
    b = (o * d).sum(-1)
    disc = b * b - ((o * o).sum(-1) - SPHERE_RADIUS**2)
    hit = (disc > 0)[..., None]
    return np.where(hit, SPHERE_RGB, _background(d)).astype(np.float32)


def _views(azimuths: list[float]) -> list[TrainView]:
    views = []
    for az in azimuths:
        cam = _camera(az)
        views.append(TrainView(cam, (_image(cam) * 255).round().astype(np.uint8)))
    return views


def _tiny_cfg(**overrides) -> GridConfig:
    base = dict(
        grid_sizes=(8, 16),
        upsample_steps=(15,),
        batch_rays=256,
        samples_coarse=16,
        samples_fine=32,
        fine_from_step=15,
        occupancy_from_step=10,
        occupancy_every=5,
        background_size=(8, 16),
        num_threads=None,
    )
    base.update(overrides)
    return GridConfig(**base)


# --- volume rendering -------------------------------------------------------------------------
def test_opaque_slab_gives_its_colour_and_no_transmittance() -> None:
    # One ray, 10 samples of 0.1: the slab fills samples 3..6 (length 0.4) with σ = 50.
    sigma = torch.zeros(10)
    sigma[3:7] = 50.0
    rgb = torch.tensor([0.2, 0.6, 0.9]).expand(10, 3).clone()
    deltas = torch.full((10,), 0.1)
    bg = torch.tensor([[1.0, 0.0, 0.0]])
    out = volume_render(sigma, rgb, deltas, torch.zeros(10, dtype=torch.long), bg)
    t_exit = math.exp(-50.0 * 0.4)
    expected = (1 - t_exit) * np.array([0.2, 0.6, 0.9]) + t_exit * np.array([1.0, 0.0, 0.0])
    assert out.transmittance.item() == pytest.approx(t_exit, rel=1e-4)
    np.testing.assert_allclose(out.rgb[0].numpy(), expected, atol=1e-6)
    assert out.weights[:3].abs().max() == 0  # empty samples before the slab weigh nothing
    assert out.weights.sum().item() == pytest.approx(1 - t_exit, abs=1e-6)


def test_two_samples_match_the_hand_computed_sum() -> None:
    s1, s2, d1, d2 = 2.0, 5.0, 0.3, 0.2
    c1, c2, bg = np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0])
    a1, a2 = 1 - math.exp(-s1 * d1), 1 - math.exp(-s2 * d2)
    expected = a1 * c1 + (1 - a1) * a2 * c2 + (1 - a1) * (1 - a2) * bg
    out = volume_render(
        torch.tensor([s1, s2]),
        torch.tensor(np.stack([c1, c2]), dtype=torch.float32),
        torch.tensor([d1, d2]),
        torch.zeros(2, dtype=torch.long),
        torch.tensor(bg[None], dtype=torch.float32),
    )
    np.testing.assert_allclose(out.rgb[0].numpy(), expected, atol=1e-6)
    assert out.transmittance.item() == pytest.approx((1 - a1) * (1 - a2), rel=1e-6)


def test_empty_ray_gives_the_background_and_rays_stay_separate() -> None:
    # Ray 0: opaque; ray 1: no samples at all; ray 2: one faint sample.
    sigma = torch.tensor([100.0, 100.0, 0.5])
    rgb = torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 1.0]])
    deltas = torch.tensor([0.5, 0.5, 0.1])
    ray_index = torch.tensor([0, 0, 2])
    bg = torch.tensor([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6], [0.0, 0.0, 0.0]])
    out = volume_render(sigma, rgb, deltas, ray_index, bg)
    np.testing.assert_allclose(out.rgb[1].numpy(), [0.4, 0.5, 0.6], atol=1e-7)
    assert out.transmittance[1].item() == 1.0
    np.testing.assert_allclose(out.rgb[0].numpy(), [0.0, 1.0, 0.0], atol=1e-6)
    faint = 1 - math.exp(-0.05)  # ray 2 does not see ray 0's density
    np.testing.assert_allclose(out.rgb[2].numpy(), [faint] * 3, atol=1e-6)


def test_volume_render_gradients() -> None:
    torch.manual_seed(0)
    sigma = torch.rand(6, dtype=torch.float64, requires_grad=True)
    rgb = torch.rand(6, 3, dtype=torch.float64, requires_grad=True)
    deltas = torch.rand(6, dtype=torch.float64)
    bg = torch.rand(3, 3, dtype=torch.float64, requires_grad=True)
    ray_index = torch.tensor([0, 0, 0, 2, 2, 2])
    torch.autograd.gradcheck(
        lambda s, c, b: volume_render(s, c, deltas, ray_index, b).rgb, (sigma, rgb, bg)
    )


def test_volume_render_rejects_bad_shapes() -> None:
    with pytest.raises(ValueError, match="shapes"):
        volume_render(
            torch.zeros(3),
            torch.zeros(3, 3),
            torch.zeros(2),
            torch.zeros(3, dtype=torch.long),
            torch.zeros(1, 3),
        )


# --- rays, box, sampler ---------------------------------------------------------------------
def test_ray_aabb_hits_misses_and_inside() -> None:
    box = torch.tensor(BOX, dtype=torch.float32)
    origins = torch.tensor([[-3.0, 0, 0], [-3.0, 5.0, 0], [0.0, 0, 0], [0.5, -3.0, 0.5]])
    dirs = torch.tensor([[1.0, 0, 0], [1.0, 0, 0], [0.0, 0, 1.0], [0.0, 1.0, 0.0]])
    t_near, t_far = ray_aabb(origins, dirs, box)
    assert t_near[0].item() == pytest.approx(2.0) and t_far[0].item() == pytest.approx(4.0)
    assert t_far[1] <= t_near[1]  # misses
    assert t_near[2].item() == 0.0 and t_far[2].item() == pytest.approx(1.0)  # starts inside
    assert t_near[3].item() == pytest.approx(2.0) and t_far[3].item() == pytest.approx(4.0)
    diag = torch.nn.functional.normalize(torch.tensor([[1.0, 1.0, 1.0]]), dim=1)
    t_near, t_far = ray_aabb(torch.tensor([[-2.0, -2.0, -2.0]]), diag, box)
    assert t_near.item() == pytest.approx(math.sqrt(3)) and t_far.item() == pytest.approx(
        3 * math.sqrt(3)
    )


def test_samples_cover_the_chord_inside_the_box() -> None:
    box = torch.tensor(BOX, dtype=torch.float32)
    origins = torch.tensor([[-3.0, 0.1, 0.2], [-3.0, 5.0, 0.0], [-3.0, -0.3, 0.4]])
    dirs = torch.tensor([[1.0, 0, 0], [1.0, 0, 0], [1.0, 0.0, 0.0]])
    t_near, t_far = ray_aabb(origins, dirs, box)
    for jitter in (None, torch.tensor([0.0, 0.5, 0.999])):
        s = sample_uniform(origins, dirs, t_near, t_far, step=0.3, jitter=jitter)
        assert s.n_rays == 3
        assert not (s.ray_index == 1).any()  # the miss has no samples
        assert bool((s.ray_index[1:] >= s.ray_index[:-1]).all())
        for r in (0, 2):
            assert s.deltas[s.ray_index == r].sum().item() == pytest.approx(2.0, abs=1e-5)
        assert bool((s.points >= -1 - 1e-5).all() and (s.points <= 1 + 1e-5).all())
    with pytest.raises(ValueError, match="step"):
        sample_uniform(origins, dirs, t_near, t_far, step=0.0)


def test_camera_rays_are_the_cameras_pixels() -> None:
    cam = _camera(30.0)
    o, d = camera_rays(cam)
    ref_o, ref_d = cam.rays()
    assert o.shape == (16 * 16, 3) and d.dtype == torch.float32
    np.testing.assert_allclose(d.numpy(), ref_d.reshape(-1, 3))
    np.testing.assert_allclose(o.numpy(), ref_o.reshape(-1, 3))


# --- the grid --------------------------------------------------------------------------------
def test_occupancy_skips_empty_voxels_only() -> None:
    cfg = _tiny_cfg(grid_sizes=(9,), upsample_steps=(), occupancy_from_step=0)
    field = DenseGridField(cfg, BOX)
    with torch.no_grad():
        field.grid[:, 0] = -20.0  # empty everywhere …
        field.grid[4 * 81 + 4 * 9 + 4, 0] = 5.0  # … but the centre vertex
    field.refresh_occupancy()
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.3, -0.3], [0.9, 0.9, 0.9], [-0.9, 0.0, 0.0]])
    assert field.occupied(pts).tolist() == [True, True, False, False]
    assert DenseGridField(_tiny_cfg(), BOX).occupied(pts) is None  # before occupancy_from_step


def test_background_is_the_env_map_of_the_direction() -> None:
    field = DenseGridField(_tiny_cfg(background_size=(5, 8)), BOX)
    with torch.no_grad():
        field.env.zero_()
        field.env[0] = 3.0  # the zenith row
        field.env[2, 0] = -3.0  # horizon, azimuth 0 (+x)
    dirs = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    bg = field.background(dirs)
    sig = torch.sigmoid(torch.tensor([3.0, -3.0, 0.0]))
    torch.testing.assert_close(bg[:, 0], sig)


def test_config_validation() -> None:
    with pytest.raises(ValueError, match="upsample_steps"):
        GridConfig(grid_sizes=(8, 16), upsample_steps=())
    with pytest.raises(ValueError, match="init_density"):
        GridConfig(init_density=0.0)
    with pytest.raises(ValueError, match="batch_rays"):
        GridConfig(batch_rays=0)
    with pytest.raises(ValueError, match="unknown field backend 'nope'"):
        field_config("nope")
    assert isinstance(field_config("grid", batch_rays=64), GridConfig)
    assert BACKENDS["grid"] is GridConfig


# --- the optimizer ---------------------------------------------------------------------------
def test_lazy_adam_equals_adam_on_dense_and_on_fully_touched_sparse_grads() -> None:
    torch.manual_seed(3)
    start = torch.randn(6, 4)
    grads = [torch.randn(6, 4) for _ in range(5)]
    ref = start.clone().requires_grad_()
    dense = start.clone().requires_grad_()
    sparse = start.clone().requires_grad_()
    opt_ref = torch.optim.Adam([ref], lr=0.1, betas=(0.9, 0.99), eps=1e-15)
    opt_dense = LazyAdam([dense], lr=0.1)
    opt_sparse = LazyAdam([sparse], lr=0.1)
    for g in grads:
        ref.grad, dense.grad = g.clone(), g.clone()
        sparse.grad = g.to_sparse(1)
        for opt in (opt_ref, opt_dense, opt_sparse):
            opt.step()
    torch.testing.assert_close(dense, ref)
    torch.testing.assert_close(sparse, ref)


def test_lazy_adam_leaves_untouched_rows_alone() -> None:
    p = torch.zeros(4, 2, requires_grad=True)
    opt = LazyAdam([p], lr=0.5)
    p.grad = torch.sparse_coo_tensor(
        torch.tensor([[1, 1]]), torch.ones(2, 2), (4, 2), check_invariants=True
    )
    opt.step()  # duplicate rows are summed (coalesced)
    assert p[[0, 2, 3]].abs().max() == 0
    torch.testing.assert_close(p[1].detach(), torch.full((2,), -0.5))


def test_lazy_adam_update_takes_rows_and_values_as_step_takes_the_sparse_grad() -> None:
    torch.manual_seed(4)
    start = torch.randn(6, 4)
    rows, values = torch.tensor([0, 2, 5]), torch.randn(3, 4)
    by_step = start.clone().requires_grad_()
    by_update = start.clone().requires_grad_()
    other = torch.zeros(2, requires_grad=True)
    opt_step, opt_update = LazyAdam([by_step], lr=0.1), LazyAdam([by_update, other], lr=0.1)
    for _ in range(3):
        by_step.grad = torch.sparse_coo_tensor(rows[None], values, (6, 4), check_invariants=True)
        opt_step.step()
        opt_update.update(by_update, (rows, values))
    torch.testing.assert_close(by_update, by_step, atol=0, rtol=0)
    assert other.abs().max() == 0  # a parameter not named is not stepped
    with pytest.raises(ValueError, match="not a parameter"):
        opt_update.update(torch.zeros(6, 4), (rows, values))


# --- the trainer -----------------------------------------------------------------------------
def test_the_grids_fused_step_is_the_autograd_step(monkeypatch: pytest.MonkeyPatch) -> None:
    """The grid trains without autograd where the kernels run (DenseGridField.train_step): the
    same random draws (the generator ends in the same state), the same loss and parameters up
    to float rounding, through occupancy, exploration and an upsampling."""
    if not native.available():
        pytest.skip("no C compiler: the grid has no fused step")
    cfg = _tiny_cfg(explore_empty=0.3)

    def train() -> tuple[FieldTrainer, list[float]]:
        trainer = FieldTrainer(cfg, BOX, device="cpu", seed=0)
        trainer.set_views(_views([0, 90, 180]))
        return trainer, [trainer.step() for _ in range(25)]

    calls = []
    fused_step = DenseGridField.train_step

    def counted(self, *args, **kwargs):
        out = fused_step(self, *args, **kwargs)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(DenseGridField, "train_step", counted)
    fused, fused_losses = train()
    assert calls == [True] * 25
    monkeypatch.setattr(DenseGridField, "train_step", lambda self, *a, **k: None)
    autograd, autograd_losses = train()
    np.testing.assert_allclose(fused_losses, autograd_losses, rtol=1e-4, atol=1e-7)
    assert torch.equal(fused._generator.get_state(), autograd._generator.get_state())
    for a, b in zip(fused.field.parameters(), autograd.field.parameters(), strict=True):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)
    assert fused.field.grid.shape[0] > 8 ** 3  # upsampled at step 15


def test_training_decreases_the_loss_and_renders_images() -> None:
    trainer = FieldTrainer(_tiny_cfg(), BOX, device="cpu", seed=0)
    assert trainer.device == torch.device("cpu")
    assert math.isnan(trainer.step())  # no views yet
    assert trainer.steps == 0
    trainer.set_views(_views([0, 60, 120, 180, 240, 300]))
    assert trainer.n_views == 6
    first = trainer.step()
    for _ in range(5):
        last = trainer.step(8)
    assert trainer.steps == 41
    assert trainer.field.shape == (16, 16, 16)  # upsampled at step 15
    assert last < 0.5 * first
    image = trainer.render(_camera(30.0))
    assert image.shape == (16, 16, 3) and image.dtype == np.float32
    assert image.min() >= 0.0 and image.max() <= 1.0
    truth = _image(_camera(30.0))
    untrained = FieldTrainer(_tiny_cfg(), BOX, device="cpu").render(_camera(30.0))
    assert np.mean((image - truth) ** 2) < 0.5 * np.mean((untrained - truth) ** 2)


def test_set_views_keeps_the_model_and_reset_restarts_it() -> None:
    trainer = FieldTrainer(_tiny_cfg(), BOX, device="cpu", seed=0)
    trainer.set_views(_views([0, 90, 180]))
    trainer.step(20)
    grid = trainer.field.grid
    before = grid.detach().clone()
    trainer.set_views(_views([45, 135]))
    assert trainer.field.grid is grid and torch.equal(grid.detach(), before)
    assert trainer.steps == 20 and trainer.n_views == 2
    trainer.step(2)
    assert not torch.equal(trainer.field.grid.detach(), before)  # training goes on
    trainer.set_views([])
    assert math.isnan(trainer.step()) and trainer.steps == 22
    trainer.reset()
    assert trainer.steps == 0 and trainer.field.shape == (8, 8, 8)
    fresh = FieldTrainer(_tiny_cfg(), BOX, device="cpu").field.grid
    assert torch.equal(trainer.field.grid.detach(), fresh.detach())


def test_same_seed_same_result_other_seed_differs() -> None:
    views = _views([0, 120, 240])
    runs = []
    for seed in (7, 7, 8):
        trainer = FieldTrainer(_tiny_cfg(), BOX, device="cpu", seed=seed)
        trainer.set_views(views)
        loss = trainer.step(25)
        runs.append((loss, trainer.render(_camera(60.0))))
    assert runs[0][0] == runs[1][0]
    np.testing.assert_array_equal(runs[0][1], runs[1][1])
    assert runs[0][0] != runs[2][0]


def test_views_are_checked() -> None:
    trainer = FieldTrainer(_tiny_cfg(), BOX, device="cpu")
    cam = _camera(0.0)
    with pytest.raises(ValueError, match="does not match"):
        trainer.set_views([TrainView(cam, np.zeros((8, 8, 3), np.uint8))])
    with pytest.raises(ValueError, match="dtype"):
        trainer.set_views([TrainView(cam, np.zeros((16, 16, 3), np.int64))])
    with pytest.raises(TypeError, match="TrainView"):
        trainer.set_views([cam])  # type: ignore[list-item]
    bad = Camera(np.diag([1.0, 1.0, -1.0, 1.0]), fx=16, fy=16, cx=8, cy=8, width=16, height=16)
    with pytest.raises(ValueError, match="determinant"):
        trainer.render(bad)
    with pytest.raises(ValueError, match="aabb"):
        FieldTrainer(_tiny_cfg(), np.array([[0, 0, 0], [1, -1, 1]]), device="cpu")
