"""The carry modes (aoi3d.field.carry): one implementation for the experiments and the trainer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from aoi3d.experiment import EpisodeConfig, plan_episode, run_plan
from aoi3d.field import FieldTrainer, GridConfig, TrainView
from aoi3d.field.carry import CARRY_MODES, Reconstruction, check_carry
from aoi3d.scene import SceneConfig, SceneDataset, generate_dataset
from tests.unit.test_experiment import TINY_FIELD

N_TRAIN = 4
TINY = GridConfig(batch_rays=64, samples_coarse=12, samples_fine=12, fine_from_step=0,
                  grid_sizes=(10,), upsample_steps=(), background_size=(4, 8),
                  tune_malloc=False, num_threads=None)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> SceneDataset:
    cfg = SceneConfig(width=24, height=18, fps=30, duration_s=0.5, n_train=N_TRAIN,
                      rotor_rpm=80.0, spp=1)
    return generate_dataset(tmp_path_factory.mktemp("scene") / "tiny", cfg, workers=1)


def views(ds: SceneDataset, frame: int, cams=(1, 2, 3, 4)) -> list[TrainView]:
    return [TrainView(ds.cameras[c], ds.frame(c, frame)) for c in cams]


def trainer(ds: SceneDataset) -> FieldTrainer:
    return FieldTrainer(TINY, ds.aabb, device="cpu", seed=5)


def params(t: FieldTrainer) -> list[torch.Tensor]:
    return [p.detach().clone() for p in t.field.parameters()]


def test_fork_is_independent_of_its_source(dataset: SceneDataset) -> None:
    base = trainer(dataset)
    base.set_views(views(dataset, 0))
    base.step(5)
    before, steps, image = params(base), base.steps, base.render(dataset.cameras[0])
    twin = base.fork()
    assert twin.steps == steps
    np.testing.assert_array_equal(twin.render(dataset.cameras[0]), image)  # same model
    twin.set_views(views(dataset, 10, (1, 2)))
    twin.step(5)
    assert twin.steps == steps + 5
    assert not np.array_equal(twin.render(dataset.cameras[0]), image)  # it moved
    for a, b in zip(before, params(base), strict=True):  # the source did not
        assert torch.equal(a, b)
    assert base.steps == steps and base.n_views == 4
    # the source trains on exactly as if the fork never happened
    other = trainer(dataset)
    other.set_views(views(dataset, 0))
    other.step(5)
    other.step(3)
    base.step(3)
    np.testing.assert_array_equal(base.render(dataset.cameras[0]),
                                  other.render(dataset.cameras[0]))


def test_fresh_renders_a_new_model_trained_on_the_decision_only(dataset: SceneDataset) -> None:
    rec = Reconstruction(trainer(dataset), "fresh", render_steps=6)
    assert not rec.trains_in_background
    rec.set_views(views(dataset, 0))
    assert math.isnan(rec.train(50))  # nothing in the background
    out = rec.render_decision(dataset.cameras[0])
    assert (out.steps, out.render_steps, out.n_views) == (6, 6, 4)
    # the same as training a new model on those frames from scratch
    ref = trainer(dataset)
    ref.set_views(views(dataset, 0))
    ref.step(6)
    np.testing.assert_array_equal(out.image, ref.render(dataset.cameras[0]))
    # an empty decision trains nothing: the untrained model
    empty = rec.render_decision(dataset.cameras[0], [])
    assert empty.render_steps == 0 and math.isnan(empty.loss)
    np.testing.assert_array_equal(empty.image, trainer(dataset).render(dataset.cameras[0]))


def test_fork_renders_from_the_warm_model_and_keeps_it(dataset: SceneDataset) -> None:
    rec = Reconstruction(trainer(dataset), "fork", render_steps=4)
    rec.set_views(views(dataset, 0))
    rec.train(7)
    warm = rec.trainer.render(dataset.cameras[0])
    out = rec.render_decision(dataset.cameras[0], views(dataset, 5, (2, 3)))
    assert (out.steps, out.render_steps, out.n_views) == (11, 4, 2)
    assert not np.array_equal(out.image, warm)
    assert rec.trainer.steps == 7 and rec.trainer.n_views == 4
    np.testing.assert_array_equal(rec.trainer.render(dataset.cameras[0]), warm)


def test_warm_renders_the_model_as_it_is(dataset: SceneDataset) -> None:
    rec = Reconstruction(trainer(dataset), "warm", render_steps=0)
    rec.set_views(views(dataset, 0))
    rec.train(3)
    out = rec.render_decision(dataset.cameras[0])
    assert (out.steps, out.render_steps) == (3, 0)
    np.testing.assert_array_equal(out.image, rec.trainer.render(dataset.cameras[0]))


def test_check_carry_refuses_unknown_modes_and_missing_budgets() -> None:
    assert set(CARRY_MODES) == {"fresh", "warm", "fork"}
    for carry, steps in (("cold", 10), ("fresh", 0), ("fork", 0), ("warm", -1), ("fork", 2.5)):
        with pytest.raises(ValueError):
            check_carry(carry, steps)
    check_carry("warm", 0)


def test_episode_fork_trains_every_decision_and_each_scored_copy(
        dataset: SceneDataset) -> None:
    cfg = EpisodeConfig(dataset=str(dataset.root), field=dict(TINY_FIELD), warmup_ms=90,
                        scored_ms=60, score_every=1, steps_per_epoch=2, carry="fork",
                        render_steps=3, lpips=False, delay="const:10")
    plan = plan_episode(cfg, dataset, "all", seed=1)
    assert all(d.train for d in plan.decisions)
    result, png = run_plan(plan, dataset)
    trained = [d for d in plan.decisions if d.cameras]
    scored = [d for d in trained if d.scored]
    assert result.train_steps == 2 * len(trained) + 3 * len(scored)
    # each scored render: the warm model's steps so far plus its own three
    for e in result.epochs:
        before = sum(1 for d in trained if d.decision_ms <= e.decision_ms)
        assert e.steps == 2 * before + 3
    assert png
    with pytest.raises(ValueError, match="render_steps"):
        cfg.with_(carry="fresh", render_steps=3)
    with pytest.raises(ValueError, match="render_steps"):
        cfg.with_(render_steps=0)


def test_building_a_trainer_changes_no_process_wide_setting(dataset: SceneDataset) -> None:
    from dataclasses import replace

    before = torch.get_num_threads()
    other = 1 if before != 1 else 2
    FieldTrainer(replace(TINY, num_threads=other, tune_malloc=True), dataset.aabb,
                 device="cpu", seed=0)
    assert torch.get_num_threads() == before  # the entry points call configure_process
    from aoi3d.field.process import configure_process

    try:
        configure_process(other)
        assert torch.get_num_threads() == other
        with pytest.raises(ValueError, match="num_threads"):
            configure_process(0)
    finally:
        torch.set_num_threads(before)


def test_set_carry_changes_the_mode_in_place_or_nothing(dataset: SceneDataset) -> None:
    rec = Reconstruction(trainer(dataset), "fresh", render_steps=3)
    rec.set_views(views(dataset, 0))
    rec.set_carry("warm", 0)
    assert (rec.carry, rec.render_steps, rec.trainer.n_views) == ("warm", 0, 4)
    with pytest.raises(ValueError):
        rec.set_carry("fork", 0)
    assert (rec.carry, rec.render_steps) == ("warm", 0)
