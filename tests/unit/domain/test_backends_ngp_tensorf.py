"""The ``ngp``, ``tensorf`` and ``nerf`` backends: hashing, encoding, gather, occupancy, VM
upsampling and a reduced-config smoke test of each on a tiny analytic scene."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from aoi3d.field import BACKENDS, FieldTrainer, TrainView, field_config
from aoi3d.field.background import latlong_background
from aoi3d.field.nerf import NerfMlpConfig, positional_encoding
from aoi3d.field.ngp import NgpConfig, NgpField
from aoi3d.field.tensorf import VM_MODES, TensorfConfig, TensorfField
from aoi3d.scene.camera import Camera, look_at

BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
FLAT_BOX = np.array([[-2.0, -2.0, -0.05], [2.0, 2.0, 2.7]])  # the turbine's proportions


# --- a tiny analytic scene: a sphere in the box, a background of the direction --------------
def _camera(azimuth_deg: float, elevation_deg: float = 20.0, size: int = 16) -> Camera:
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    eye = 3.0 * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
    return Camera(
        look_at(eye, (0, 0, 0)), fx=size, fy=size, cx=size / 2, cy=size / 2, width=size, height=size
    )


def _image(camera: Camera, radius: float) -> np.ndarray:
    o, d = (a.astype(np.float64) for a in camera.rays())
    b = (o * d).sum(-1)
    hit = (b * b - ((o * o).sum(-1) - radius**2) > 0)[..., None]
    return np.where(hit, np.array([0.9, 0.2, 0.1]), 0.5 + 0.4 * d).astype(np.float32)


def _views(azimuths: list[float], radius: float = 0.5) -> list[TrainView]:
    views = []
    for az in azimuths:
        cam = _camera(az)
        views.append(TrainView(cam, (_image(cam, radius) * 255).round().astype(np.uint8)))
    return views


SMALL = dict(batch_rays=256, samples_coarse=16, samples_fine=32, fine_from_step=10)
TINY = {
    "ngp": NgpConfig(
        **SMALL,
        n_levels=4,
        features=2,
        log2_table_size=10,
        base_resolution=4,
        max_resolution=32,
        hidden=16,
        geo_features=7,
        background_size=(8, 16),
        occupancy_size=8,
        occupancy_from_step=10,
        occupancy_every=4,
    ),
    "tensorf": TensorfConfig(
        **SMALL,
        grid_sizes=(8, 16),
        upsample_steps=(12,),
        density_components=2,
        app_components=4,
        decoder_hidden=16,
        background_size=(8, 16),
        mask_from_step=10,
        mask_every=4,
    ),
    "nerf": NerfMlpConfig(**SMALL, layers=2, width=32, frequencies=3, background_size=(8, 16)),
}


@pytest.fixture(autouse=True)
def _one_thread() -> object:
    """Tiny tensors: one thread is faster, and two crawl when another process holds a core."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# --- registration -----------------------------------------------------------------------------
def test_backends_are_registered_by_name() -> None:
    assert BACKENDS["ngp"] is NgpConfig
    assert BACKENDS["tensorf"] is TensorfConfig
    assert BACKENDS["nerf"] is NerfMlpConfig
    cfg = field_config("nerf", batch_rays=64)
    assert isinstance(cfg, NerfMlpConfig) and cfg.batch_rays == 64
    assert (cfg.layers, cfg.width, cfg.frequencies) == (4, 128, 6)
    assert cfg.samples_coarse == cfg.samples_fine == 32


def test_config_validation() -> None:
    with pytest.raises(ValueError, match="log2_table_size"):
        NgpConfig(log2_table_size=40)
    with pytest.raises(ValueError, match="base_resolution"):
        NgpConfig(base_resolution=64, max_resolution=32)
    with pytest.raises(ValueError, match="view_dependent"):
        NgpConfig(colour_mlp=False, view_dependent=True)
    with pytest.raises(ValueError, match="occupancy_fraction"):
        NgpConfig(occupancy_fraction=0.0)
    with pytest.raises(ValueError, match="upsample_steps"):
        TensorfConfig(grid_sizes=(8, 16), upsample_steps=())
    with pytest.raises(ValueError, match="mask_alpha"):
        TensorfConfig(mask_alpha=1.0)
    with pytest.raises(ValueError, match="frequencies"):
        NerfMlpConfig(frequencies=-1)
    with pytest.raises(ValueError, match="batch_rays"):
        NgpConfig(batch_rays=0)


# --- the hash function and the encoding -------------------------------------------------------
# --- shared pieces ----------------------------------------------------------------------------
def test_positional_encoding() -> None:
    x = torch.tensor([[0.25, -0.5, 1.0]])
    out = positional_encoding(x, 2)
    assert out.shape == (1, 15)
    expected = [0.25, -0.5, 1.0]
    angles = [math.pi * s * v for s in (1, 2) for v in (0.25, -0.5, 1.0)]
    expected += [math.sin(a) for a in angles] + [math.cos(a) for a in angles]
    torch.testing.assert_close(out[0], torch.tensor(expected), atol=1e-6, rtol=1e-6)
    assert torch.equal(positional_encoding(x, 0), x)


@pytest.mark.parametrize("name", ["ngp", "tensorf", "nerf"])
def test_background_is_the_shared_lat_long_map(name: str) -> None:
    field = TINY[name].build(BOX)
    with torch.no_grad():
        field.env.normal_(generator=torch.Generator().manual_seed(3))
    dirs = torch.nn.functional.normalize(torch.randn(10, 3), dim=1)
    torch.testing.assert_close(field.background(dirs), latlong_background(field.env, dirs, 2))


# --- smoke tests: every backend trains, renders, keeps its state, repeats itself ------------
@pytest.mark.parametrize("name", ["ngp", "tensorf", "nerf"])
def test_backend_trains_renders_and_is_deterministic(name: str) -> None:
    cfg = TINY[name]
    views = _views([0, 60, 120, 180, 240, 300])
    trainer = FieldTrainer(cfg, BOX, device="cpu", seed=0)
    trainer.set_views(views)
    losses = [trainer.step() for _ in range(4)]
    for _ in range(4):
        losses.append(trainer.step(5))
    assert trainer.steps == 24
    assert np.mean(losses[-2:]) < 0.6 * np.mean(losses[:2])
    image = trainer.render(_camera(30.0))
    assert image.shape == (16, 16, 3) and image.dtype == np.float32
    assert image.min() >= 0.0 and image.max() <= 1.0
    truth = _image(_camera(30.0), 0.5)
    untrained = FieldTrainer(cfg, BOX, device="cpu").render(_camera(30.0))
    assert np.mean((image - truth) ** 2) < 0.6 * np.mean((untrained - truth) ** 2)

    # set_views keeps the parameters; training goes on from them.
    before = {k: v.detach().clone() for k, v in trainer.field.state_dict().items()}
    params = list(trainer.field.parameters())
    trainer.set_views(views[:3])
    assert all(a is b for a, b in zip(params, trainer.field.parameters(), strict=True))
    after = trainer.field.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)
    trainer.step(2)
    assert trainer.steps == 26 and trainer.n_views == 3

    # The same seed repeats the run exactly; another init seed does not.
    runs = []
    for c in (cfg, cfg, replace(cfg, init_seed=1)):
        t = FieldTrainer(c, BOX, device="cpu", seed=0)
        t.set_views(views)
        runs.append((t.step(6), t.render(_camera(90.0))))
    assert runs[0][0] == runs[1][0]
    np.testing.assert_array_equal(runs[0][1], runs[1][1])
    assert runs[0][0] != runs[2][0]


# --- the ngp occupancy grid -------------------------------------------------------------------
def test_ngp_occupancy_skips_empty_space_after_training() -> None:
    # An empty-ish scene: a small sphere; the opacity loss clears the fog around it.
    cfg = replace(TINY["ngp"], occupancy_from_step=20, occupancy_every=5, lr_mlp=0.01, lr_table=0.1)
    trainer = FieldTrainer(cfg, BOX, device="cpu", seed=0)
    trainer.set_views(_views([0, 45, 90, 135, 180, 225, 270, 315], radius=0.3))
    trainer.step(19)
    field = trainer.field
    assert isinstance(field, NgpField)
    assert field.occupancy is None and field.occupied(torch.zeros(1, 3)) is None
    trainer.step(61)
    occupancy = field.occupancy
    assert occupancy is not None and occupancy.shape == (8, 8, 8)
    assert occupancy.float().mean() < 0.5  # most of the box is skipped …
    probe = torch.tensor([[0.0, 0.0, 0.0], [0.9, 0.9, 0.9], [-0.9, 0.9, -0.9]])
    assert field.occupied(probe).tolist() == [True, False, False]  # … the sphere is not
    with torch.no_grad():
        sigma = field.density(torch.tensor([[0.9, 0.9, 0.9]]))[0]
    assert float(sigma) < field.sigma_min


def test_ngp_occupancy_estimate_decays_and_keeps_the_maximum() -> None:
    field = NgpField(TINY["ngp"], BOX)
    field.update_occupancy(fraction=1.0)  # every cell probed: σ ≈ init_density everywhere
    assert field.occupancy is not None and bool(field.occupancy.all())
    first = field.density_estimate.clone()
    torch.testing.assert_close(first, torch.full_like(first, 0.1), atol=0.01, rtol=0)
    with torch.no_grad():
        field.density_mlp[-1].bias[0] = -30.0  # the field empties everywhere
    for _ in range(3):
        field.update_occupancy(fraction=1.0)
    torch.testing.assert_close(field.density_estimate, first * 0.95**3)  # decays, max kept
    decay = math.log(field.sigma_min / 0.1) / math.log(0.95)
    for _ in range(math.ceil(decay)):
        field.update_occupancy(fraction=0.5)
    assert not bool(field.occupancy.any())


# --- tensorf: alpha mask and coarse-to-fine -----------------------------------------------------
def test_tensorf_vertex_density_is_the_query_at_the_vertices() -> None:
    field = TensorfField(replace(TINY["tensorf"], grid_sizes=(9,), upsample_steps=()), FLAT_BOX)
    axes = [
        torch.linspace(float(FLAT_BOX[0, a]), float(FLAT_BOX[1, a]), n)
        for a, n in enumerate(field.shape)
    ]
    vertices = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    with torch.no_grad():
        sigma = field.query(vertices, vertices)[0].view(field.shape)
    torch.testing.assert_close(field.vertex_density(), sigma, atol=1e-5, rtol=1e-5)


def test_tensorf_alpha_mask_keeps_only_dense_cells() -> None:
    cfg = replace(TINY["tensorf"], grid_sizes=(9,), upsample_steps=(), mask_from_step=0)
    field = TensorfField(cfg, BOX)
    with torch.no_grad():
        for plane in field.planes:
            plane.zero_()
        for line in field.lines:
            line.zero_()
        field.density_shift = -30.0  # empty …
        field.planes[0][4 * 9 + 4, 0] = 10.0  # … but the centre vertex: plane xy × line z
        field.lines[0][4, 0] = 10.0
    assert field.on_step(0) is False
    points = torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.3, -0.3], [0.9, 0.9, 0.9], [-0.9, 0, 0]])
    assert field.occupied(points).tolist() == [True, True, False, False]
    assert field.alpha_mask is not None and field.alpha_mask.shape == (8, 8, 8)


def _smooth_components(field: TensorfField) -> None:
    """Planes and lines set to smooth functions of the vertex positions (a real density)."""
    with torch.no_grad():
        for m, (u, v, w) in enumerate(VM_MODES):
            nu, nv, nw = field.shape[u], field.shape[v], field.shape[w]
            ch = torch.arange(field.planes[m].shape[1])
            gu = torch.linspace(-1, 1, nu)[:, None, None]
            gv = torch.linspace(-1, 1, nv)[None, :, None]
            plane = torch.sin(1.5 * gu + 0.7 * ch) * torch.cos(1.2 * gv - 0.3 * ch)
            field.planes[m].copy_(plane.reshape(nu * nv, -1))
            field.lines[m].copy_(torch.cos(1.3 * torch.linspace(-1, 1, nw)[:, None] + 0.5 * ch))


def test_tensorf_upsampling_keeps_the_function_and_the_rendered_image() -> None:
    cfg = replace(TINY["tensorf"], grid_sizes=(12, 24), upsample_steps=(1000,))
    trainer = FieldTrainer(cfg, BOX, device="cpu", seed=0)
    field = trainer.field
    assert isinstance(field, TensorfField) and field.shape == (12, 12, 12)
    _smooth_components(field)
    points = torch.rand(3000, 3, generator=torch.Generator().manual_seed(4)) * 2 - 1
    with torch.no_grad():
        sigma, rgb = field.query(points, points)
    before = trainer.render(_camera(45.0))
    field.resize(24)
    assert field.shape == (24, 24, 24) and field.planes[0].shape[0] == 24 * 24
    with torch.no_grad():
        sigma_up, rgb_up = field.query(points, points)
    # Interpolating the interpolant: ≈ 3 % at most (a half-cell shift gives 12–15 %).
    assert float(((sigma_up - sigma).abs() / sigma).max()) < 0.05
    assert float((rgb_up - rgb).abs().max()) < 2e-3
    after = trainer.render(_camera(45.0))
    assert np.abs(after - before).max() < 0.01


def test_tensorf_upsamples_at_its_steps_and_the_optimizer_follows() -> None:
    trainer = FieldTrainer(TINY["tensorf"], BOX, device="cpu", seed=0)
    trainer.set_views(_views([0, 120, 240]))
    trainer.step(12)
    assert trainer.field.shape == (8, 8, 8)
    trainer.step(1)  # on_step(12) upsamples and returns True: a new optimizer
    assert trainer.field.shape == (16, 16, 16)
    trainer.step(2)
    assert all(torch.isfinite(p).all() for p in trainer.field.parameters())
    trainer.reset()
    assert trainer.field.shape == (8, 8, 8)
