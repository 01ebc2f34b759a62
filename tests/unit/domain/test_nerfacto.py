"""The trainer's sampler seam (Field.render_rays, aux losses, appearance rows) and nerfacto."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
import torch

from aoi3d.field import BACKENDS, FieldTrainer, GridConfig, TrainView, field_config
from aoi3d.field.base import Field, FieldConfig
from aoi3d.field.grid import DenseGridField
from aoi3d.field.nerfacto import (
    NerfactoConfig,
    NerfactoField,
    distortion_loss,
    interlevel_loss,
    sample_pdf,
    weights_from_density,
)
from aoi3d.field.rays import RayBundle, camera_rays, ray_aabb
from aoi3d.field.render import RenderOptions, RenderResult, render_uniform
from aoi3d.scene.camera import Camera, look_at

BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


@pytest.fixture(autouse=True)
def _one_thread():  # tiny tensors: a second thread only waits (the machine has 2 busy cores)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


SPHERE_RADIUS = 0.5
SPHERE_RGB = np.array([0.9, 0.2, 0.1])


# --- a tiny analytic scene: a red sphere in the box, a background of the direction ----------
def _camera(azimuth_deg: float, elevation_deg: float = 20.0, size: int = 16) -> Camera:
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    eye = 3.0 * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
    return Camera(
        look_at(eye, (0, 0, 0)), fx=size, fy=size, cx=size / 2, cy=size / 2, width=size, height=size
    )


def _image(camera: Camera) -> np.ndarray:
    o, d = (a.astype(np.float64) for a in camera.rays())
    b = (o * d).sum(-1)
    disc = b * b - ((o * o).sum(-1) - SPHERE_RADIUS**2)
    hit = (disc > 0)[..., None]
    return np.where(hit, SPHERE_RGB, 0.5 + 0.4 * d).astype(np.float32)


def _views(azimuths: list[float], ids: list[int | None] | None = None) -> list[TrainView]:
    ids = ids if ids is not None else [None] * len(azimuths)
    out = []
    for az, appearance_id in zip(azimuths, ids, strict=True):
        cam = _camera(az)
        image = (_image(cam) * 255).round().astype(np.uint8)
        out.append(TrainView(cam, image, appearance_id))
    return out


def _tiny(**overrides: Any) -> NerfactoConfig:
    base: dict[str, Any] = dict(
        levels=4,
        features_per_level=2,
        log2_table_size=12,
        base_resolution=4,
        max_resolution=32,
        hidden_dim=16,
        geo_features=7,
        color_hidden_dim=16,
        appearance_dim=4,
        proposal_samples=(16,),
        fine_samples=8,
        proposal_levels=3,
        proposal_log2_table_size=10,
        proposal_base_resolution=4,
        proposal_max_resolutions=(16,),
        proposal_anneal_steps=10,
        batch_rays=128,
        background_size=(8, 16),
        appearance_slots=8,
        lr_field=3e-2,
        lr_proposal=3e-2,
    )
    base.update(overrides)
    return NerfactoConfig(**base)


def _rays(camera: Camera, appearance: torch.Tensor | None = None) -> RayBundle:
    o, d = camera_rays(camera)
    t_near, t_far = ray_aabb(o, d, torch.tensor(BOX, dtype=torch.float32))
    return RayBundle(o, d, t_near, t_far, appearance)


# --- the seam ------------------------------------------------------------------------------
class _AuxField(DenseGridField):
    """The grid field plus a parameter that only an aux loss (x − 3)² trains; records what the
    trainer passes to ``render_rays``."""

    def __init__(self, cfg: GridConfig, aabb: np.ndarray) -> None:
        super().__init__(cfg, aabb)
        self.x = torch.nn.Parameter(torch.zeros(()))
        self.seen: list[tuple[RayBundle, RenderOptions, bool]] = []

    def param_groups(self) -> list[dict[str, Any]]:
        return [*super().param_groups(), {"params": [self.x], "lr": 0.1}]

    def render_rays(self, rays: RayBundle, options: RenderOptions) -> RenderResult:
        self.seen.append((rays, options, self.training))
        out = super().render_rays(rays, options)
        return RenderResult(
            out.rgb,
            out.transmittance,
            out.weights,
            out.sample_rgb,
            out.ray_index,
            out.opacity,
            (self.x - 3.0) ** 2,
        )


class _AuxConfig(GridConfig):
    def build(self, aabb: np.ndarray) -> Field:
        return _AuxField(self, aabb)


def _grid_cfg(cls: type[GridConfig] = GridConfig, **overrides: Any) -> GridConfig:
    base: dict[str, Any] = dict(
        grid_sizes=(8,),
        upsample_steps=(),
        batch_rays=64,
        samples_coarse=16,
        samples_fine=16,
        background_size=(8, 16),
    )
    base.update(overrides)
    return cls(**base)


def test_a_fields_aux_loss_reaches_the_optimizer_and_rows_reach_the_field() -> None:
    trainer = FieldTrainer(_grid_cfg(_AuxConfig), BOX, device="cpu", seed=0)
    views = _views([0, 120, 240], ids=[5, None, 5])
    trainer.set_views(views)
    trainer.step(30)
    field = trainer.field
    assert isinstance(field, _AuxField)
    assert abs(field.x.item() - 3.0) < 1.0  # moved from 0 towards 3 by the aux loss alone
    rays, options, training = field.seen[-1]
    assert training and options.jitter is not None and options.generator is not None
    assert rays.n_rays == 64 and rays.appearance is not None
    # ids 5 share a row; the view without an id is keyed by its camera and gets another one.
    row5, row_cam = trainer.appearance_row(views[0]), trainer.appearance_row(views[1])
    assert row5 == trainer.appearance_row(views[2]) and row5 != row_cam
    assert set(rays.appearance.tolist()) <= {row5, row_cam}
    trainer.render(_camera(60.0))
    rays, options, training = field.seen[-1]
    assert not training and rays.appearance is None and options.jitter is None


def test_default_render_rays_is_the_uniform_renderer() -> None:
    field = DenseGridField(_grid_cfg(), BOX)
    with torch.no_grad():
        field.grid.normal_(generator=torch.Generator().manual_seed(1))
    rays = _rays(_camera(30.0))
    jitter = torch.rand(rays.n_rays, generator=torch.Generator().manual_seed(2))
    new = field.render_rays(rays, RenderOptions(0.1, jitter))
    old = render_uniform(field, rays, RenderOptions(0.1, jitter))
    assert new.aux_loss is None
    torch.testing.assert_close(new.rgb, old.rgb, rtol=0, atol=0)
    torch.testing.assert_close(new.weights, old.weights, rtol=0, atol=0)


def test_ray_bundle_checks_shapes_and_indexes() -> None:
    rays = _rays(_camera(0.0), torch.arange(256))
    part = rays[torch.tensor([3, 5])]
    assert part.n_rays == 2 and part.appearance.tolist() == [3, 5]
    assert rays[10:12].t_near.shape == (2,)
    with pytest.raises(ValueError, match="appearance"):
        RayBundle(rays.origins, rays.dirs, rays.t_near, rays.t_far, torch.zeros(3))
    with pytest.raises(TypeError, match="appearance_id"):
        TrainView(_camera(0.0), np.zeros((16, 16, 3), np.uint8), appearance_id="cam1")  # type: ignore[arg-type]


def test_appearance_rows_survive_set_views_and_recycle_least_recently_used() -> None:
    trainer = FieldTrainer(_tiny(appearance_slots=3), BOX, device="cpu", seed=0)
    views = _views([0, 90, 180], ids=[11, 12, 13])
    trainer.set_views(views)
    rows = [trainer.appearance_row(v) for v in views]
    assert sorted(rows) == [0, 1, 2]
    trainer.step(10)
    field = trainer.field
    assert isinstance(field, NerfactoField)
    table = field.appearance.detach().clone()
    assert table.abs().sum() > 0  # trained
    # Id 13 comes back in another frame of the same camera, id 14 is new: it takes the row of
    # the least recently used id outside the set (11); 12 and 13 keep theirs and their values.
    later = _views([180, 270], ids=[13, 14])
    trainer.set_views(later)
    assert trainer.appearance_row(later[0]) == rows[2]
    assert trainer.appearance_row(later[1]) == rows[0]
    assert trainer.appearance_row(views[0]) is None
    assert trainer.appearance_row(views[1]) == rows[1]
    torch.testing.assert_close(field.appearance.detach()[rows[1:]], table[rows[1:]])
    assert field.appearance.detach()[rows[0]].abs().sum() == 0  # recycled row reset
    assert not bool(field.appearance_used[rows[0]])
    with pytest.raises(ValueError, match="appearance_slots"):
        trainer.set_views(_views([0, 60, 120, 180], ids=[1, 2, 3, 4]))
    assert trainer.n_views == 2  # the failed call changed nothing


def test_novel_views_use_the_mean_of_the_trained_embeddings() -> None:
    field = NerfactoField(_tiny(), BOX)
    pts = torch.rand(5, 3) - 0.5
    dirs = torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    zero = field.query(pts, dirs)[1]
    with torch.no_grad():
        field.appearance[1] = 1.0
        field.appearance[2] = 3.0
        field.appearance[4] = 100.0  # never trained: left out
    torch.testing.assert_close(field.query(pts, dirs)[1], zero)  # nothing trained yet: zero
    field.appearance_used[[1, 2]] = True
    torch.testing.assert_close(field.neutral_appearance(), torch.full((4,), 2.0))
    mean_rgb = field._field(pts, dirs, torch.full((4,), 2.0))[1]
    torch.testing.assert_close(field.query(pts, dirs)[1], mean_rgb)


# --- proposal sampling -----------------------------------------------------------------------
def test_sample_pdf_concentrates_where_the_weight_is() -> None:
    near, far = torch.tensor([[1.0], [0.0]]), torch.tensor([[3.0], [10.0]])
    edges = near + (far - near) * torch.linspace(0, 1, 11)[None]
    weights = torch.zeros(2, 10)
    weights[0, 7] = 1.0  # ray 0: everything in bin 7 = [2.4, 2.6]
    weights[1] = 0.0  # ray 1: empty → uniform
    for jitter in (None, torch.tensor([0.0, 0.999])):
        new = sample_pdf(edges, weights, 32, jitter, padding=0.01)
        assert new.shape == (2, 33)
        assert bool((new[:, 1:] >= new[:, :-1]).all())  # sorted
        assert bool((new >= near).all() and (new <= far).all())
        inside = ((new[0] >= 2.4) & (new[0] <= 2.6)).float().mean().item()
        assert inside > 0.85  # padding 0.01 × 10 bins against weight 1: ≈ 91 %
        gaps = new[1].diff()
        assert gaps.max() - gaps.min() < 1e-4  # uniform histogram: evenly spaced
    with pytest.raises(ValueError, match="edges"):
        sample_pdf(edges[:, :-1], weights, 4)


def test_weights_from_density_match_the_volume_renderer() -> None:
    sigma = torch.tensor([[0.0, 2.0, 5.0, 1.0]])
    deltas = torch.tensor([[0.3, 0.2, 0.1, 0.4]])
    w = weights_from_density(sigma, deltas)
    alpha = 1 - torch.exp(-sigma * deltas)
    t = torch.cumprod(torch.cat([torch.ones(1, 1), 1 - alpha[:, :-1]], 1), 1)
    torch.testing.assert_close(w, t * alpha)


def test_interlevel_loss_is_zero_when_the_proposal_bounds_the_field() -> None:
    torch.manual_seed(0)
    fine_edges = torch.sort(torch.rand(4, 9), dim=1).values
    fine_w = torch.rand(4, 8) * 0.1
    # Same bins, proposal ≥ field: zero.
    assert interlevel_loss(fine_edges, fine_w, fine_edges, fine_w + 0.01).item() == 0.0
    # Coarse proposal bins covering [0, 1] whose weights sum all fine weights: zero.
    coarse = torch.linspace(0, 1, 3).expand(4, 3)
    bound = fine_w.sum(1, keepdim=True).expand(4, 2).clone().requires_grad_()
    assert interlevel_loss(fine_edges, fine_w, coarse, bound).item() == 0.0
    # A proposal that misses the field's mass is penalised, and only it gets the gradient.
    weak = (0.1 * bound.detach()).requires_grad_()
    field_w = fine_w.clone().requires_grad_()
    loss = interlevel_loss(fine_edges, field_w, coarse, weak)
    assert loss.item() > 0
    loss.backward()
    assert weak.grad is not None and bool((weak.grad <= 0).all()) and weak.grad.abs().sum() > 0
    assert field_w.grad is None


def test_distortion_loss_matches_the_double_sum() -> None:
    torch.manual_seed(1)
    edges = torch.sort(torch.rand(3, 7), dim=1).values
    w = torch.rand(3, 6)
    mid = 0.5 * (edges[:, 1:] + edges[:, :-1])
    ref = (w[:, :, None] * w[:, None, :] * (mid[:, :, None] - mid[:, None, :]).abs()).sum((1, 2))
    ref = ref + (w**2 * edges.diff(dim=1)).sum(1) / 3
    torch.testing.assert_close(distortion_loss(edges, w), ref.mean())
    # A single concentrated spike costs less than the same mass spread out.
    spike = torch.zeros(1, 6)
    spike[0, 2] = 1.0
    flat = torch.full((1, 6), 1 / 6)
    even = torch.linspace(0, 1, 7)[None]
    assert distortion_loss(even, spike) < distortion_loss(even, flat)


# --- the field's parts -------------------------------------------------------------------------
# --- nerfacto end to end ---------------------------------------------------------------------
def test_nerfacto_trains_renders_and_keeps_its_parameters_on_set_views() -> None:
    trainer = FieldTrainer(_tiny(), BOX, device="cpu", seed=0)
    trainer.set_views(_views([0, 60, 120, 180, 240, 300], ids=[1, 2, 3, 4, 5, 6]))
    first = trainer.step()
    for _ in range(5):
        last = trainer.step(10)
    assert trainer.steps == 51 and last < 0.5 * first
    image = trainer.render(_camera(30.0))
    assert image.shape == (16, 16, 3) and image.dtype == np.float32
    assert image.min() >= 0.0 and image.max() <= 1.0
    truth = _image(_camera(30.0))
    untrained = FieldTrainer(_tiny(), BOX, device="cpu").render(_camera(30.0))
    assert np.mean((image - truth) ** 2) < 0.5 * np.mean((untrained - truth) ** 2)
    field = trainer.field
    before = {k: v.detach().clone() for k, v in field.state_dict().items()}
    trainer.set_views(_views([30, 90], ids=[1, 7]))
    assert trainer.field is field
    for k, v in field.state_dict().items():
        torch.testing.assert_close(v, before[k], rtol=0, atol=0)
    assert trainer.step(2) > 0


def test_nerfacto_aux_loss_and_outputs() -> None:
    field = NerfactoField(_tiny(distortion_loss_weight=0.01), BOX)
    rays = _rays(_camera(0.0), torch.zeros(256, dtype=torch.long))
    gen = torch.Generator().manual_seed(0)
    jitter = torch.rand(256, generator=gen)
    field.train()
    out = field.render_rays(rays, RenderOptions(0.1, jitter, generator=gen))
    hits = int((rays.t_far > rays.t_near).sum())
    assert out.rgb.shape == (256, 3) and out.weights.shape == (hits * 8,)
    assert bool((out.ray_index[1:] >= out.ray_index[:-1]).all())
    assert out.aux_loss is not None and out.aux_loss.ndim == 0 and out.aux_loss.item() >= 0
    out.aux_loss.backward()
    assert field.proposals[0].encoding.table.grad is not None
    field.eval()
    with torch.no_grad():
        assert field.render_rays(rays, RenderOptions(0.1)).aux_loss is None
    # A bundle that misses the box: background only.
    miss = RayBundle(
        torch.tensor([[5.0, 5.0, 5.0]]),
        torch.tensor([[1.0, 0.0, 0.0]]),
        torch.tensor([1.0]),
        torch.tensor([0.5]),
    )
    with torch.no_grad():
        out = field.render_rays(miss, RenderOptions(0.1))
    torch.testing.assert_close(out.rgb, field.background(miss.dirs))


def test_nerfacto_same_seed_same_result_other_seed_differs() -> None:
    views = _views([0, 120, 240])
    runs = []
    for seed in (7, 7, 8):
        trainer = FieldTrainer(_tiny(), BOX, device="cpu", seed=seed)
        trainer.set_views(views)
        loss = trainer.step(12)
        runs.append((loss, trainer.render(_camera(60.0))))
    assert runs[0][0] == runs[1][0]
    np.testing.assert_array_equal(runs[0][1], runs[1][1])
    assert runs[0][0] != runs[2][0]


def test_nerfacto_is_registered_and_validates() -> None:
    assert BACKENDS["nerfacto"] is NerfactoConfig
    cfg = field_config("nerfacto", fine_samples=8)
    assert isinstance(cfg, NerfactoConfig) and isinstance(cfg, FieldConfig)
    with pytest.raises(ValueError, match="proposal_max_resolutions"):
        NerfactoConfig(proposal_samples=(32, 16), proposal_max_resolutions=(64,))
    with pytest.raises(ValueError, match="max_resolution"):
        NerfactoConfig(base_resolution=64, max_resolution=32)
    with pytest.raises(ValueError, match="appearance_slots"):
        NerfactoConfig(appearance_slots=0)
    assert NerfactoConfig().anneal_exponent(0) == 0.0
    assert NerfactoConfig().anneal_exponent(10**6) == 1.0
