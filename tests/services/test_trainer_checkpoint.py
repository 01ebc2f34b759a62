"""Trainer checkpoints (issue 11, failure 6): the model is saved atomically while it trains,
a restarted trainer resumes from it when backend and scene match, and a reset or a new
backend starts fresh — also after a restart."""

from __future__ import annotations

from pathlib import Path

from fastapi.testclient import TestClient

from aoi3d.clock import SimClock
from aoi3d.scene import SceneDataset
from services.kit.bus import MemoryBus
from services.trainer.app import create_app
from tests.services.test_trainer import (
    KEYS,
    SMALL_GRID,
    dataset,  # noqa: F401  (module fixture)
    decision_payload,
    make_settings,
    metric,
    publish_frames,
    wait_for,
)


def trainer(ds: SceneDataset, ckpt_dir: Path, **kw) -> TestClient:
    settings = make_settings(checkpoint_dir=ckpt_dir, checkpoint_period_s=0.2, **kw)
    clock = SimClock(settings.common.epoch_s, settings.common.time_scale)
    return TestClient(create_app(settings, bus=MemoryBus(), clock=clock, dataset=ds,
                                 field_config=SMALL_GRID))


def train_a_while(client: TestClient, ds: SceneDataset) -> int:
    bus = client.app.state.bus
    assert client.put("/carry", json={"carry": "warm"}).status_code == 200
    publish_frames(bus, ds, 0.0)
    bus.publish(KEYS.decision, decision_payload(1, 100.0, [(1, 0.0), (2, 0.0), (3, 0.0)]))
    wait_for(lambda: metric(client, "aoi3d_trainer_checkpoints_total") >= 2,
             what="two checkpoints written")
    return client.get("/status").json()["steps"]


def test_a_restarted_trainer_resumes_from_its_checkpoint(dataset: SceneDataset,  # noqa: F811
                                                          tmp_path: Path) -> None:
    with trainer(dataset, tmp_path) as first:
        trained = train_a_while(first, dataset)
    path = tmp_path / f"{KEYS.run_id}.trainer.pt"
    assert path.is_file() and not path.with_suffix(".tmp").exists()
    assert trained > 0
    # the process is gone; a new one (same run, backend, scene) goes on from the checkpoint
    with trainer(dataset, tmp_path) as second:
        steps = second.get("/status").json()["steps"]
        assert steps >= 1 and second.app.state.worker.resumed_steps == steps
        # a reset starts fresh and drops the checkpoint, so a restart does not bring it back
        assert second.post("/reset").status_code == 200
        assert not path.exists()
    with trainer(dataset, tmp_path) as third:
        assert third.get("/status").json()["steps"] == 0


def test_a_checkpoint_of_another_backend_is_not_resumed(dataset: SceneDataset,  # noqa: F811
                                                         tmp_path: Path) -> None:
    with trainer(dataset, tmp_path) as first:
        train_a_while(first, dataset)
    with trainer(dataset, tmp_path, backend="nerf") as other:
        assert other.get("/status").json()["steps"] == 0
        assert other.app.state.worker.resumed_steps == 0


def test_a_torn_checkpoint_starts_fresh(dataset: SceneDataset, tmp_path: Path) -> None:  # noqa: F811
    (tmp_path / f"{KEYS.run_id}.trainer.pt").write_bytes(b"not a checkpoint")
    with trainer(dataset, tmp_path) as client:
        assert client.get("/status").json()["steps"] == 0
        assert client.get("/readyz").status_code == 200
