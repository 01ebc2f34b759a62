"""The time-aware field (``flow``, aoi3d/field/flow.py, issue 41) on a tiny analytic scene: a
sphere moving at a constant velocity, seen by cameras whose frames have different ages."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from aoi3d.field import (
    BACKENDS,
    FieldTrainer,
    FlowConfig,
    FlowField,
    GridConfig,
    TrainView,
    field_config,
    native,
)
from aoi3d.field.carry import Reconstruction, WarmStart
from aoi3d.field.encodings import vertex_coords
from aoi3d.field.flow import trilinear
from aoi3d.field.native_flow import trilinear4
from aoi3d.scene.camera import Camera, look_at

BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
SPEED = np.array([2.0, 0.0, 0.0])
"""The sphere's velocity, world units per second: 60 ms move it 0.12, about a voxel."""
RADIUS = 0.3
AGES_MS = (30.0, 60.0, 90.0, 120.0)
AZIMUTHS = (0.0, 60.0, 120.0, 180.0, 240.0, 300.0)


def _camera(azimuth_deg: float, size: int = 20) -> Camera:
    az, el = math.radians(azimuth_deg), math.radians(20.0)
    eye = 3.0 * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
    return Camera(look_at(eye, (0, 0, 0)), fx=size, fy=size, cx=size / 2, cy=size / 2,
                  width=size, height=size)


def _image(camera: Camera, time_ms: float) -> np.ndarray:
    """The moving sphere at ``time_ms`` (0: the decision's time) over a background of the
    direction."""
    o, d = (a.astype(np.float64) for a in camera.rays())
    oc = o - SPEED * time_ms / 1000.0
    b = (oc * d).sum(-1)
    hit = b * b - ((oc * oc).sum(-1) - RADIUS ** 2) > 0
    return np.where(hit[..., None], np.array([0.9, 0.3, 0.1]), 0.5 + 0.4 * d).astype(np.float32)


def _views(ages: tuple[float, ...] = AGES_MS) -> list[TrainView]:
    """Every camera's frames at every age: each frame shows the sphere where it was then."""
    return [TrainView(_camera(az), _image(_camera(az), -a), age_ms=a)
            for az in AZIMUTHS for a in ages]


TINY = dict(grid_sizes=(16,), upsample_steps=(), batch_rays=384, samples_coarse=24,
            samples_fine=24, fine_from_step=0, occupancy_from_step=10_000,
            background_size=(8, 16), tune_malloc=False)


def _flow(**overrides) -> FlowConfig:
    return FlowConfig(**{**TINY, "flow_size": 4, "lr_flow": 0.05, **overrides})


def _train(cfg: GridConfig, views: list[TrainView], steps: int, seed: int = 0) -> FieldTrainer:
    trainer = FieldTrainer(cfg, BOX, device="cpu", seed=seed)
    trainer.set_views(views)
    trainer.step(steps)
    return trainer


def _psnr(image: np.ndarray, truth: np.ndarray) -> float:
    return -10.0 * math.log10(float(np.mean((image - truth) ** 2)))


# --- the config ------------------------------------------------------------------------------
def test_the_config_is_a_backend_that_takes_the_age_and_time() -> None:
    assert BACKENDS["flow"] is FlowConfig and isinstance(field_config("flow"), FlowConfig)
    cfg = FlowConfig()
    assert cfg.takes_age and cfg.uses_age and cfg.time_aware
    assert not GridConfig().time_aware and not GridConfig(age_features=2).time_aware
    for bad in ({"flow_size": 1}, {"flow_size": 2.5}, {"lr_flow": 0.0},
                {"lr_flow": math.nan}, {"flow_max_ms": -1.0}, {"age_features": 2}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            FlowConfig(**bad)  # type: ignore[arg-type]
    # it needs each frame's age, as the timeliness embedding does
    trainer = FieldTrainer(_flow(), BOX, device="cpu")
    with pytest.raises(ValueError, match="age_ms"):
        trainer.set_views([TrainView(_camera(0.0), _image(_camera(0.0), 0.0))])


# --- what it is for: a moving scene ----------------------------------------------------------
def test_it_places_a_moving_sphere_at_any_time_where_the_static_grid_cannot() -> None:
    """Frames 30–120 ms old: the static grid averages them; the flow field learns the velocity
    and renders the sphere where it is at the decision's time and 60 ms later (the display
    time), a time no frame shows."""
    views = _views()
    grid = _train(GridConfig(**TINY), views, 200)
    flow = _train(_flow(), views, 200)
    novel = _camera(30.0)
    for ahead in (0.0, 60.0):
        truth = _image(novel, ahead)
        static = _psnr(grid.render(novel, ahead_ms=ahead), truth)
        moving = _psnr(flow.render(novel, ahead_ms=ahead), truth)
        assert moving > static + 2.0, (ahead, static, moving)
    assert not np.array_equal(flow.render(novel), flow.render(novel, ahead_ms=60.0))
    np.testing.assert_array_equal(grid.render(novel), grid.render(novel, ahead_ms=60.0))
    field = flow.field
    assert isinstance(field, FlowField)
    with torch.no_grad():
        v = field.velocity(torch.zeros(1, 3))[0].numpy()
    # along the motion, at least half the speed (the smoothness prior holds it back a little)
    assert 1.0 < v[0] < 3.0 and abs(v[1]) < 0.5 and abs(v[2]) < 0.5, v


def test_frames_of_one_age_teach_no_motion_and_give_the_grid() -> None:
    """Every frame of one age: a·v is a constant offset, the velocity gets no gradient and
    the field trains exactly as the static grid does (the same draws, the same numbers)."""
    views = _views((60.0,))
    grid = _train(GridConfig(**TINY), views, 15)
    flow = _train(_flow(), views, 15)
    assert torch.count_nonzero(flow.field.flow) == 0  # type: ignore[arg-type]
    torch.testing.assert_close(flow.field.grid, grid.field.grid, atol=1e-5, rtol=1e-5)
    np.testing.assert_allclose(flow.render(_camera(30.0), ahead_ms=40.0),
                               grid.render(_camera(30.0)), atol=1e-5)


# --- the gradients ---------------------------------------------------------------------------
def test_the_torch_interpolation_is_differentiable_in_the_points() -> None:
    g = torch.Generator().manual_seed(0)
    shape = (5, 4, 6)
    aabb = torch.tensor([[-1.0, -0.5, 0.0], [1.0, 0.5, 2.0]])
    table = torch.randn(math.prod(shape), 4, generator=g, dtype=torch.float64)
    points = (torch.rand(40, 3, generator=g, dtype=torch.float64) * 1.6
              + torch.tensor([-0.8, -0.4, 0.2], dtype=torch.float64)).requires_grad_()

    def f(p: torch.Tensor) -> torch.Tensor:
        return trilinear(table, shape, vertex_coords(p, aabb.double(), shape))

    assert torch.autograd.gradcheck(f, (points,))


@pytest.mark.skipif(not native.available(), reason="no C compiler: torch path only")
def test_the_kernels_match_the_torch_interpolation() -> None:
    g = torch.Generator().manual_seed(1)
    shape = (5, 4, 6)
    aabb = torch.tensor([[-1.0, -0.5, 0.0], [1.0, 0.5, 2.0]])
    table = torch.randn(math.prod(shape), 4, generator=g)
    points = (torch.rand(300, 3, generator=g) * torch.tensor([2.4, 1.2, 2.4])
              + torch.tensor([-1.2, -0.6, -0.2]))  # some outside: clamped, no gradient there
    fused = trilinear4(table, points, aabb, shape)
    assert fused is not None
    reference = trilinear(table, shape, vertex_coords(points, aabb, shape))
    torch.testing.assert_close(fused, reference, atol=1e-5, rtol=1e-5)


@pytest.mark.skipif(not native.available(), reason="no C compiler: torch path only")
def test_the_fused_step_is_the_autograd_step(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without autograd where the kernels run (FlowField.train_step): the same draws, loss and
    parameters — the velocity grid's gradient included — as the torch code under autograd,
    through occupancy and exploration."""
    cfg = _flow(occupancy_from_step=5, explore_empty=0.3)

    def train() -> tuple[FieldTrainer, list[float]]:
        trainer = FieldTrainer(cfg, BOX, device="cpu", seed=0)
        trainer.set_views(_views())
        return trainer, [trainer.step() for _ in range(20)]

    calls: list[bool] = []
    fused_step = FlowField.train_step

    def counted(self, *args, **kwargs):
        out = fused_step(self, *args, **kwargs)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(FlowField, "train_step", counted)
    fused, fused_losses = train()
    assert calls == [True] * 20
    monkeypatch.setattr(FlowField, "train_step", lambda self, *a, **k: None)
    autograd, autograd_losses = train()
    # float rounding order differs; Adam (eps 1e-15) lets it grow a little over the steps
    np.testing.assert_allclose(fused_losses, autograd_losses, rtol=1e-3, atol=1e-7)
    assert torch.equal(fused._generator.get_state(), autograd._generator.get_state())
    assert torch.count_nonzero(fused.field.flow) > 0  # type: ignore[arg-type]
    for a, b in zip(fused.field.parameters(), autograd.field.parameters(), strict=True):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-3)


# --- determinism -----------------------------------------------------------------------------
def test_same_seed_same_field_other_seed_differs() -> None:
    views = _views()
    a, b, c = (_train(_flow(), views, 10, seed=s) for s in (4, 4, 5))
    for x, y in zip(a.field.parameters(), b.field.parameters(), strict=True):
        assert torch.equal(x, y)
    assert not torch.equal(a.field.flow, c.field.flow)  # type: ignore[arg-type]
    np.testing.assert_array_equal(a.render(_camera(30.0), ahead_ms=50.0),
                                  b.render(_camera(30.0), ahead_ms=50.0))


# --- carrying the model to a later time ------------------------------------------------------
def _moving_model() -> FieldTrainer:
    """A trained flow model, its velocity set to the sphere's exactly."""
    trainer = _train(_flow(), _views(), 60)
    with torch.no_grad():
        trainer.field.flow[:, :3] = torch.tensor(SPEED, dtype=torch.float32)  # type: ignore[index]
    return trainer


def test_advance_moves_the_grid_along_the_flow_and_its_moments_with_it() -> None:
    trainer = _moving_model()
    novel = _camera(30.0)
    ahead = trainer.render(novel, ahead_ms=50.0)
    moments = trainer._optimizer.state[trainer.field.grid]["exp_avg"].clone()
    assert trainer.advance(50.0)
    now = trainer.render(novel)  # the reference time is now 50 ms later
    assert np.abs(now - ahead).mean() < 0.01  # a resampling's blur apart
    assert not torch.equal(trainer._optimizer.state[trainer.field.grid]["exp_avg"], moments)
    assert not trainer.advance(0.0)
    static = _train(GridConfig(**TINY), _views((30.0,)), 5)
    before = static.render(novel)
    assert not static.advance(50.0)  # a static field stands for every time
    np.testing.assert_array_equal(static.render(novel), before)
    with pytest.raises(ValueError, match="finite"):
        trainer.render(novel, ahead_ms=math.inf)


def test_the_stream_carry_advances_a_warm_start_to_its_decision() -> None:
    """A warm start 90 ms after the previous decision moves the model 90 ms along its flow
    before training; the display-time render is the same model taken later."""
    rec = Reconstruction(FieldTrainer(_flow(), BOX, device="cpu", seed=0), "stream", 5,
                         WarmStart(cold_steps=30))
    moved: list[float] = []
    advance = rec.trainer.advance

    def spy(dt_ms: float) -> bool:
        moved.append(dt_ms)
        return advance(dt_ms)

    rec.trainer.advance = spy  # type: ignore[method-assign]
    novel = _camera(30.0)
    first = rec.render_decision(novel, _views(), time_ms=1000.0)
    assert not first.warm and moved == []
    second = rec.render_decision(novel, _views(), time_ms=1090.0)
    assert second.warm and moved == [90.0]
    shown = rec.render_at(novel, 40.0)
    assert not np.array_equal(shown, second.image)
    np.testing.assert_array_equal(shown, rec.trainer.render(novel, ahead_ms=40.0))


# --- the episode on the virtual clock --------------------------------------------------------
def test_an_episode_scores_the_flow_field_at_its_display_time(dataset) -> None:
    """run_plan renders a time-aware field again at the display time and scores that render;
    a static field's display score is its decision-time render against the later truth."""
    from aoi3d.experiment import EpisodeConfig, plan_episode, run_plan
    from aoi3d.quality import psnr
    from tests.support.tiny import TINY_FIELD

    shown: dict[str, list[float]] = {}
    again: dict[str, list[float]] = {}
    for backend in ("grid", "flow"):
        cfg = EpisodeConfig(dataset=str(dataset.root), backend=backend, field=dict(TINY_FIELD),
                            carry="fresh", steps_per_epoch=15, warmup_ms=300, scored_ms=300,
                            score_every=5, lpips=False, delay="exp:60", time_scale=1.0)
        plan = plan_episode(cfg, dataset, "mat:130", seed=3)
        images: list[np.ndarray] = []
        result, _ = run_plan(plan, dataset,
                             on_render=lambda d, image, out=images: out.append(image))
        assert len(images) == len(result.epochs) >= 2
        shown[backend] = [e.psnr_display_db for e in result.epochs]
        again[backend] = [
            psnr(image, dataset.frame(dataset.heldout_id,
                                      dataset.frame_index(e.display_ms + plan.scene_offset_ms)))
            for image, e in zip(images, result.epochs, strict=True)]
    np.testing.assert_allclose(shown["grid"], again["grid"], rtol=1e-6)
    assert not np.allclose(shown["flow"], again["flow"], rtol=1e-6)  # rendered again, later


def test_bench_scale_runs_the_flow_field_beside_the_grid() -> None:
    from bench.scale import parse_config

    assert parse_config("2x1") == (2, 1, None, None, None)
    assert parse_config("2x1:stream@25") == (2, 1, "stream", 25, None)
    assert parse_config("2x1:stream@16:flow") == (2, 1, "stream", 16, "flow")
