"""The follow-up paper's two baselines (arXiv 2509.17282) in the radiance field: the
weighted-sum loss (``FieldConfig.age_weight_tau_ms``) and the timeliness embedding
(``GridConfig.age_features``), on a tiny analytic scene."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from aoi3d.field import DenseGridField, FieldTrainer, GridConfig, TrainView, field_config
from aoi3d.scene.camera import Camera, look_at

BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
RED = np.array([0.9, 0.2, 0.1])
BLUE = np.array([0.1, 0.2, 0.9])
AZIMUTHS = (0.0, 90.0, 180.0, 270.0)


def _camera(azimuth_deg: float, size: int = 16) -> Camera:
    az, el = math.radians(azimuth_deg), math.radians(20.0)
    eye = 3.0 * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
    return Camera(look_at(eye, (0, 0, 0)), fx=size, fy=size, cx=size / 2, cy=size / 2,
                  width=size, height=size)


def _sphere(camera: Camera, colour: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The image of a sphere of radius 0.5 of ``colour`` over a background of the direction,
    and the mask of the sphere's pixels."""
    o, d = (a.astype(np.float64) for a in camera.rays())
    b = (o * d).sum(-1)
    hit = b * b - ((o * o).sum(-1) - 0.25) > 0
    image = np.where(hit[..., None], colour, 0.5 + 0.4 * d).astype(np.float32)
    return image, hit


def _views(colour: np.ndarray, age_ms: float | None) -> list[TrainView]:
    return [TrainView(cam, _sphere(cam, colour)[0], age_ms=age_ms)
            for cam in (_camera(a) for a in AZIMUTHS)]


def _cfg(**overrides) -> GridConfig:
    base = dict(grid_sizes=(12,), upsample_steps=(), batch_rays=256, samples_coarse=16,
                samples_fine=16, fine_from_step=0, occupancy_from_step=10_000,
                background_size=(8, 16))
    base.update(overrides)
    return GridConfig(**base)


def _train(cfg: GridConfig, views: list[TrainView], steps: int) -> FieldTrainer:
    trainer = FieldTrainer(cfg, BOX, device="cpu", seed=3)
    trainer.set_views(views)
    trainer.step(steps)
    return trainer


def _sphere_error(trainer: FieldTrainer, colour: np.ndarray) -> float:
    """Mean absolute error of the novel view's sphere pixels against ``colour``."""
    cam = _camera(45.0)
    _, hit = _sphere(cam, colour)
    return float(np.abs(trainer.render(cam)[hit] - colour).mean())


# --- configs ---------------------------------------------------------------------------------
def test_configs_say_whether_they_use_the_age() -> None:
    assert not GridConfig().uses_age and not GridConfig().takes_age
    assert GridConfig(age_features=2).takes_age and GridConfig(age_features=2).uses_age
    assert GridConfig(age_weight_tau_ms=60).uses_age and not GridConfig(
        age_weight_tau_ms=60).takes_age
    assert field_config("ngp", age_weight_tau_ms=60.0).uses_age  # any backend weights its loss
    for bad in (0, -1.0, math.inf, True, "60"):
        with pytest.raises(ValueError, match="age_weight_tau_ms"):
            GridConfig(age_weight_tau_ms=bad)
    with pytest.raises(ValueError, match="age_features"):
        GridConfig(age_features=-1)
    with pytest.raises(ValueError, match="age_scale_ms"):
        GridConfig(age_features=1, age_scale_ms=0.0)
    with pytest.raises(TypeError):  # only the grid takes the age as an input
        field_config("ngp", age_features=2)
    with pytest.raises(ValueError, match="age_ms"):
        TrainView(_camera(0.0), np.zeros((16, 16, 3), np.uint8), age_ms=-1.0)
    # a config that uses ages refuses views without one; the plain one takes both
    trainer = FieldTrainer(_cfg(age_weight_tau_ms=50.0), BOX, device="cpu")
    with pytest.raises(ValueError, match="age_ms"):
        trainer.set_views(_views(RED, None))
    FieldTrainer(_cfg(), BOX, device="cpu").set_views(_views(RED, None))


# --- weighted sum ----------------------------------------------------------------------------
def test_weighted_sum_with_equal_ages_is_the_plain_loss() -> None:
    views = _views(RED, 60.0)
    plain = _train(_cfg(), views, 20)
    weighted = _train(_cfg(age_weight_tau_ms=50.0), views, 20)
    assert weighted.step(1) == pytest.approx(plain.step(1), rel=1e-5)
    torch.testing.assert_close(weighted.field.grid, plain.field.grid, atol=1e-5, rtol=1e-4)
    # ...and with different ages it is not: the old frames count less
    mixed = _views(RED, 30.0) + _views(BLUE, 300.0)
    a = _train(_cfg(), mixed, 20).field.grid
    b = _train(_cfg(age_weight_tau_ms=50.0), mixed, 20).field.grid
    assert not torch.allclose(a, b, atol=1e-3)


def test_weighted_sum_follows_the_young_frames() -> None:
    # The same cameras show a red sphere in frames 30 ms old and a blue one in frames 300 ms
    # old: the plain loss averages them, the weighted sum (τ = 30 ms: weight e^−9 for the
    # old) renders the young red sphere.
    views = _views(RED, 30.0) + _views(BLUE, 300.0)
    plain = _train(_cfg(), views, 200)
    weighted = _train(_cfg(age_weight_tau_ms=30.0), views, 200)
    assert _sphere_error(weighted, RED) < 0.1 < _sphere_error(plain, RED)
    # Σ w·e / Σ w: the ages shift out, however old the frames (no all-zero weights)
    ancient = _views(RED, 1e6) + _views(BLUE, 1e6 + 270.0)
    assert _sphere_error(_train(_cfg(age_weight_tau_ms=30.0), ancient, 200), RED) < 0.1


# --- timeliness embedding --------------------------------------------------------------------
def test_embedded_field_with_the_age_ignored_is_the_plain_field() -> None:
    torch.manual_seed(0)
    plain = DenseGridField(_cfg(), BOX)
    embedded = DenseGridField(_cfg(age_features=3), BOX)
    with torch.no_grad():
        plain.grid.normal_()
        embedded.grid.copy_(plain.grid)
        embedded.age_grid.normal_()  # whatever the residuals hold
    points = torch.rand(500, 3) * 2 - 1
    dirs = torch.nn.functional.normalize(torch.randn(500, 3), dim=1)
    for a, b in zip(embedded.query(points, dirs), plain.query(points, dirs), strict=True):
        torch.testing.assert_close(a, b)  # no age (a novel view): age 0
    for a, b in zip(embedded.query_aged(points, dirs, torch.zeros(500)),
                    plain.query(points, dirs), strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    aged = embedded.query_aged(points, dirs, torch.full((500,), 120.0))
    assert not torch.allclose(aged[0], plain.query(points, dirs)[0], atol=1e-3)
    phi = embedded.age_embedding(torch.tensor([0.0, 150.0, 300.0, 900.0]))
    assert phi.shape == (4, 3) and torch.all(phi[0] == 0)
    torch.testing.assert_close(phi[3], phi[2])  # ages beyond age_scale_ms count as it
    # trained on frames of age 0 only, the residuals get no gradient: the plain grid's run
    views = _views(RED, 0.0)
    trained = _train(_cfg(age_features=2), views, 30)
    reference = _train(_cfg(), views, 30)
    assert torch.count_nonzero(trained.field.age_grid) == 0
    torch.testing.assert_close(trained.field.grid, reference.field.grid, atol=1e-4, rtol=1e-4)


def test_embedded_field_renders_the_present() -> None:
    # Red sphere at age 0, blue at 300 ms: the embedding puts the difference in its residuals
    # and the novel view (age 0) shows red; the plain grid shows a mix.
    views = _views(RED, 0.0) + _views(BLUE, 300.0)
    embedded = _train(_cfg(age_features=2, age_scale_ms=300.0), views, 200)
    plain = _train(_cfg(), views, 200)
    assert _sphere_error(embedded, RED) < 0.1 < _sphere_error(plain, RED)
    assert torch.count_nonzero(embedded.field.age_grid) > 0
    # the residuals are resampled with the grid when it is refined
    grown = _train(_cfg(age_features=1, grid_sizes=(8, 12), upsample_steps=(5,)), views, 10)
    assert grown.field.age_grid.shape == (grown.field.grid.shape[0], 4)
