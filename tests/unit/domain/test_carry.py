"""The carry modes (aoi3d.field.carry): one implementation for the experiments and the live
workers."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from aoi3d.experiment import EpisodeConfig, plan_episode, run_plan
from aoi3d.field import FieldTrainer, GridConfig, TrainView
from aoi3d.field.carry import (
    BACKGROUND_MODES,
    CARRY_MODES,
    FINETUNE_MODES,
    Reconstruction,
    WarmStart,
    changed_cells,
    check_carry,
)
from aoi3d.scene import SceneConfig, SceneDataset, generate_dataset
from tests.support.tiny import TINY_FIELD

ROOT = Path(__file__).resolve().parents[3]
N_TRAIN = 4
TINY = GridConfig(batch_rays=64, samples_coarse=12, samples_fine=12, fine_from_step=0,
                  grid_sizes=(10,), upsample_steps=(), background_size=(4, 8),
                  tune_malloc=False, num_threads=None)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> SceneDataset:
    cfg = SceneConfig(width=24, height=18, fps=30, duration_s=0.5, n_train=N_TRAIN,
                      rotor_rpm=80.0, spp=1)
    return generate_dataset(tmp_path_factory.mktemp("scene") / "tiny", cfg, processes=1)


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
    assert set(CARRY_MODES) == {"fresh", "warm", "fork", "stream"}
    for carry, steps in (("cold", 10), ("fresh", 0), ("fork", 0), ("warm", -1), ("fork", 2.5),
                         ("stream", 0)):
        with pytest.raises(ValueError):
            check_carry(carry, steps)
    assert check_carry("warm", 0) == "warm" and check_carry("stream", 5) == "stream"


def test_the_modes_are_spelled_once() -> None:
    # the one definition (CarryMode), what every list and every API schema takes
    assert CARRY_MODES == ("fork", "fresh", "stream", "warm")
    assert {"fork", "warm"} == BACKGROUND_MODES and {"fork", "stream"} == FINETUNE_MODES
    from services.dispatcher.app import CarryRequest
    from services.dispatcher.settings import Settings

    for model in (CarryRequest, Settings):
        assert model.model_json_schema()["properties"]["carry"]["enum"] == list(CARRY_MODES)
    spelled = []
    for package in ("aoi3d", "aoi3d_cli", "services", "bench"):
        for path in (ROOT / package).rglob("*.py"):
            text = path.read_text()
            if re.search(r'"fork",\s*"fresh"|"fresh",\s*"fork"|"warm",\s*"fork"', text):
                spelled.append(path.relative_to(ROOT).as_posix())
    assert spelled == ["aoi3d/field/carry.py"]


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


def test_stream_starts_cold_then_warm_from_the_previous_model(dataset: SceneDataset) -> None:
    ws = WarmStart(cold_steps=8, max_gap_ms=100.0)
    rec = Reconstruction(trainer(dataset), "stream", render_steps=3, warm_start=ws)
    assert not rec.trains_in_background
    cam = dataset.cameras[0]
    first = rec.render_decision(cam, views(dataset, 0), time_ms=0.0)
    assert (first.warm, first.render_steps, first.steps) == (False, 8, 8)
    # the cold start is the fresh reconstruction with the cold budget
    ref = trainer(dataset)
    ref.set_views(views(dataset, 0))
    ref.step(8)
    np.testing.assert_array_equal(first.image, ref.render(cam))
    # the next decision starts from that model: the schedule held at cold − warm, 3 steps more
    before = params(rec.trainer)
    second = rec.render_decision(cam, views(dataset, 1), time_ms=33.3)
    assert (second.warm, second.render_steps, second.steps) == (True, 3, 8)
    assert any(not torch.equal(a, b) for a, b in zip(before, params(rec.trainer), strict=True))
    # and differs from a fresh 3-step model on those frames (it kept what it had learned)
    fresh = trainer(dataset)
    fresh.set_views(views(dataset, 1))
    fresh.step(3)
    assert not np.array_equal(second.image, fresh.render(cam))
    # too old (beyond max_gap_ms, either way), no time, or an empty decision: cold again
    assert not rec.is_warm(33.3 + 101.0) and not rec.is_warm(None)
    assert rec.is_warm(33.3 + 99.0) and rec.is_warm(0.0)
    third = rec.render_decision(cam, views(dataset, 2), time_ms=500.0)
    assert (third.warm, third.render_steps) == (False, 8)
    empty = rec.render_decision(cam, [], time_ms=530.0)
    assert (empty.warm, empty.render_steps, empty.n_views) == (False, 0, 0)
    assert not rec.is_warm(560.0)  # an empty decision leaves no model to start from


def test_the_stream_gap_leaves_out_the_time_the_job_took(dataset: SceneDataset) -> None:
    """A cold start slower than max_gap_ms must not leave its worker cold for good: the gap
    to the next decision is counted without the time the last job took (ready)."""
    ws = WarmStart(cold_steps=4, max_gap_ms=100.0)
    rec = Reconstruction(trainer(dataset), "stream", render_steps=2, warm_start=ws)
    cam = dataset.cameras[0]
    rec.render_decision(cam, views(dataset, 0), time_ms=0.0)
    assert not rec.is_warm(330.0)  # its job's time not told: all of the gap counts
    rec.ready(300.0)  # the cold job took 300 ms
    assert rec.is_warm(330.0) and not rec.is_warm(401.0)
    second = rec.render_decision(cam, views(dataset, 1), time_ms=330.0)
    assert second.warm and not rec.is_warm(330.0 + 101.0)  # a new job: its own time again


def test_stream_focuses_on_the_changed_pixels(dataset: SceneDataset) -> None:
    t = trainer(dataset)
    t.set_views(views(dataset, 0))
    n = 4 * dataset.width * dataset.height
    with pytest.raises(ValueError, match="outside"):
        t.set_focus(torch.tensor([n]), 0.5)
    with pytest.raises(ValueError, match="fraction"):
        t.set_focus(torch.tensor([0]), 1.5)
    # every ray from one pixel: the step's loss is that pixel's error alone
    t.set_focus(torch.tensor([7]), 1.0)
    target = torch.as_tensor(views(dataset, 0)[0].image.reshape(-1, 3)[7] / 255.0)
    seen = []
    real_step = t.field.train_step

    def spy(rays, options, tgt, optimizer):
        seen.append(tgt.clone())
        return real_step(rays, options, tgt, optimizer)

    t.field.train_step = spy
    t.step(2)
    assert seen and all(torch.allclose(x, target.expand_as(x).float()) for x in seen)
    t.set_views(views(dataset, 1))  # a new decision drops the focus
    seen.clear()
    t.step(1)
    assert not torch.allclose(seen[0], seen[0][:1].expand_as(seen[0]))
    # the stream carry's focus: the pixels that changed since the camera's last frame
    rec = Reconstruction(trainer(dataset), "stream", 2, WarmStart(cold_steps=2, focus=1.0))
    rec.render_decision(dataset.cameras[0], views(dataset, 0), time_ms=0.0)
    changes = rec._changes(views(dataset, 3))
    assert len(changes) == 4 and any(m.any() for _, m in changes)
    assert not any(m.all() for _, m in changes)
    same = rec._changes(views(dataset, 0))
    assert all(not m.any() for _, m in same)  # nothing moved: nothing to focus on


def test_changed_cells_is_the_hull_of_the_change(dataset: SceneDataset) -> None:
    cams = [dataset.cameras[c] for c in (1, 2)]
    h, w = dataset.height, dataset.width
    box = np.asarray(dataset.aabb)
    centre = torch.tensor(box.mean(axis=0), dtype=torch.float32)
    behind = torch.tensor(cams[0].position - 10.0 * (box.mean(axis=0) - cams[0].position),
                          dtype=torch.float32)
    points = torch.stack([centre, behind])
    everything = [(c, np.ones((h, w), dtype=bool)) for c in cams]
    nothing = [(c, np.zeros((h, w), dtype=bool)) for c in cams]
    assert changed_cells(points, everything).tolist()[0] is True
    assert changed_cells(points, nothing).tolist() == [False, False]
    # one view that sees it unchanged is enough to keep it
    assert changed_cells(points, [everything[0], nothing[1]]).tolist()[0] is False
    # a point no view sees is never marked
    assert changed_cells(points[1:], everything[:1]).tolist() == [False]
    assert changed_cells(points, []).tolist() == [False, False]


def test_forget_resets_the_marked_vertices_and_their_moments(dataset: SceneDataset) -> None:
    t = trainer(dataset)
    t.set_views(views(dataset, 0))
    t.step(5)
    grid = t.field.grid.detach().clone()
    state = t._optimizer.state[t.field.grid]
    n = t.forget(lambda p: p[:, 0] < float(np.asarray(dataset.aabb)[:, 0].mean()))
    after = t.field.grid.detach()
    assert 0 < n < grid.shape[0]
    reset = (after != grid).any(dim=1)
    assert int(reset.sum()) <= n
    first = after[~torch.isclose(after, grid).all(dim=1)]
    if len(first):
        assert torch.allclose(first[:, 1:], torch.zeros_like(first[:, 1:]))
    rows = (after[:, 1:] == 0).all(dim=1) & torch.isclose(after[:, 0], after[0, 0])
    assert int(rows.sum()) >= n
    assert float(state["exp_avg"][rows].abs().sum()) == 0.0
    assert float(state["exp_avg_sq"][rows].abs().sum()) == 0.0
    assert t.forget(lambda p: torch.zeros(len(p), dtype=torch.bool)) == 0


def test_episode_stream_scores_warm_decisions(dataset: SceneDataset) -> None:
    cfg = EpisodeConfig(dataset=str(dataset.root), field=dict(TINY_FIELD), warmup_ms=90,
                        scored_ms=90, score_every=1, steps_per_epoch=4, carry="stream",
                        render_steps=2, lpips=False, delay="const:10")
    plan = plan_episode(cfg, dataset, "all", seed=1)
    assert all(d.train == d.scored for d in plan.decisions)  # nothing in the background
    result, _ = run_plan(plan, dataset)
    scored = [d for d in plan.decisions if d.scored and d.cameras]
    assert result.train_steps == 2 * len(scored) + 2
    assert len(result.epochs) == len(scored) >= 2
