"""The dispatcher's core and a reconstruction worker's core on their own: no bus, no server."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aoi3d.pool import Dispatcher, Report
from aoi3d.scene import SceneDataset
from services.dispatcher.core import DispatcherCore, RenderSettings
from services.kit.observe import Rejected
from services.kit.pb import aoi3d_pb2 as pb
from services.recon.core import JobFailed, ReconCore
from tests.support.dispatcher import (
    CONFIGS,
    N_TRAIN,
    decision_payload,
    frame_payload,
    trainer_scene,
)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> SceneDataset:
    """The dispatcher tests' scene (not the unit tests' tiny one)."""
    return trainer_scene(tmp_path_factory)


def make_core(ds: SceneDataset, pool: Dispatcher) -> DispatcherCore:
    return DispatcherCore(camera_ids=frozenset(range(1, N_TRAIN + 1)),
                       size=(ds.width, ds.height), skew_ms=1e9,
                       heldout=ds.cameras[ds.heldout_id], aabb=np.asarray(ds.aabb),
                       frames_per_camera=4, dispatcher=pool, site="north")


def test_a_decision_becomes_one_job_with_exactly_its_frames(dataset: SceneDataset) -> None:
    pool = Dispatcher()
    core = make_core(dataset, pool)
    for cam in (1, 2, 3):
        core.on_frame(frame_payload(dataset, cam, 0.0), now_ms=0.0)
    assert core.on_decision(decision_payload(4, 100.0, [(1, 0.0), (3, 0.0), (2, 700.0)]),
                            now_ms=100.0, now_s=1.0) is None  # no worker waits
    assert core.frames_missing == 1 and core.decision.n_missing == 1
    with pytest.raises(Rejected, match="stale_decision"):
        core.on_decision(decision_payload(4, 100.0, []), now_ms=100.0, now_s=1.1)
    pool.joined("w", 1.2)
    assignment = pool.request(Report("w", max_wait_s=1.0), 1.5)
    job = pb.WorkReply.FromString(
        core.job(assignment, 1.5, RenderSettings("grid", "fresh", 12, 3))).job
    assert job.decision.decision_id == 4 and job.site == "north"
    assert sorted(f.camera_id for f in job.frames) == [1, 3] and job.n_missing == 1
    assert (job.backend, job.carry, job.render_steps, job.seed) == ("grid", "fresh", 12, 3)
    assert list(job.aabb) == np.asarray(dataset.aabb).reshape(-1).tolist()

    # a worker's core turns it into a render of the held-out camera, from those frames
    out = ReconCore(worker_id="w", device="cpu", configs=CONFIGS).run(job)
    r = out.render
    assert (r.decision_id, r.site, r.worker_id, r.n_views, r.render_steps) == (4, "north", "w",
                                                                               2, 12)
    assert sorted(r.frame_generation_ms) == [0.0, 0.0] and math.isfinite(r.loss)
    # which frames, exactly: the cameras beside their generation times (a replay's key)
    assert list(r.frame_camera_ids) == [f.camera_id for f in job.frames]
    latest = core.on_render(r.SerializeToString(), now_s=2.0, now_ms=200.0)
    assert latest.decision_id == 4 and latest.worker_id == "w" and latest.age_s == 1.0


def test_a_stream_worker_starts_warm_from_its_last_job_and_cold_when_it_is_too_old(
        dataset: SceneDataset) -> None:
    pool = Dispatcher()
    core = make_core(dataset, pool)
    pool.joined("w", 0.0)
    recon = ReconCore(worker_id="w", device="cpu", configs=CONFIGS)
    settings = RenderSettings("grid", "stream", 3, 3, cold_steps=7, warm_max_gap_ms=200.0)
    outcomes, done = [], None
    for i, t in enumerate((100.0, 130.0, 1000.0)):
        for cam in (1, 2, 3):
            core.on_frame(frame_payload(dataset, cam, t - 10.0), now_ms=t)
        core.on_decision(decision_payload(i + 1, t, [(c, t - 10.0) for c in (1, 2, 3)]),
                         now_ms=t, now_s=float(i))
        assignment = pool.request(Report("w", done=done, rendered=done is not None,
                                         max_wait_s=1.0), float(i) + 0.5)
        job = pb.WorkReply.FromString(core.job(assignment, float(i) + 0.5, settings)).job
        assert (job.cold_steps, job.warm_max_gap_ms) == (7, 200.0)
        outcomes.append(recon.run(job).render)
        done = assignment.decision.key
    first, second, third = outcomes
    assert (first.warm_start, first.render_steps, first.carry) == (False, 7, "stream")
    assert (second.warm_start, second.render_steps) == (True, 3)  # 30 ms after the first
    assert (third.warm_start, third.render_steps) == (False, 7)  # 870 ms: too old


def test_a_time_aware_job_trains_on_its_frames_ages_and_renders_at_the_workers_clock(
        dataset: SceneDataset) -> None:
    """A ``flow`` job: each frame gets its age at the decision (else the field refuses it),
    and the render is taken at the scene time the worker's clock says when it is rendered —
    the display time; a static field's render is the decision's time whatever the clock."""
    pool = Dispatcher()
    core = make_core(dataset, pool)
    t = 400.0
    for cam, gen in ((1, 100.0), (2, 200.0), (3, 300.0), (4, 300.0)):
        core.on_frame(frame_payload(dataset, cam, gen), now_ms=t)
    core.on_decision(decision_payload(1, t, [(1, 100.0), (2, 200.0), (3, 300.0), (4, 300.0)]),
                     now_ms=t, now_s=0.0)
    pool.joined("w", 0.0)
    assignment = pool.request(Report("w", max_wait_s=1.0), 0.5)
    images = {}
    for backend in ("flow", "grid"):
        job = pb.WorkReply.FromString(
            core.job(assignment, 0.5, RenderSettings(backend, "fresh", 25, 3))).job
        for label, clock in (("decision", None), ("display", lambda: t + 250.0)):
            recon = ReconCore(worker_id="w", device="cpu", configs=CONFIGS)
            out = recon.run(job, now_ms=clock)
            assert out.render.n_views == 4 and out.render.backend == backend
            images[backend, label] = out.render.image.data
    assert images["flow", "decision"] != images["flow", "display"]
    assert images["grid", "decision"] == images["grid", "display"]


def test_settings_move_the_model_epoch_and_bad_jobs_fail_with_a_reason() -> None:
    render = RenderSettings("grid", "fresh", 12, 3).with_backend("ngp").reset()
    assert (render.backend, render.model_epoch) == ("ngp", 2)
    assert render.with_carry("warm", 20).model_epoch == 2  # a carry change keeps the models
    with pytest.raises(ValueError):
        render.with_backend("nope")
    with pytest.raises(ValueError):
        render.with_carry("fresh", 0)
    recon = ReconCore(worker_id="w", device="cpu", configs=CONFIGS)
    with pytest.raises(JobFailed) as err:
        recon.run(pb.Job(aabb=[0, 0, 0, -1, 1, 1]))
    assert err.value.reason == "bad_job"
    with pytest.raises(JobFailed) as err:
        recon.run(pb.Job(aabb=[0, 0, 0, 1, 1, 1]))  # no camera to render
    assert err.value.reason == "bad_job"


def test_a_gap_in_the_ids_received_is_told_not_received_and_bounded(
        dataset: SceneDataset) -> None:
    """The first decision of a dispatcher's life has no gap before it; later gaps end lost
    ``not_received``, at most MAX_NOT_RECEIVED per gap (a hostile id cannot make more)."""
    from services.dispatcher.core import MAX_NOT_RECEIVED

    pool = Dispatcher()
    core = make_core(dataset, pool)
    core.on_decision(decision_payload(50, 100.0, []), now_ms=100.0, now_s=1.0)
    assert pool.drain_ended() == []  # 1..49 were another dispatcher's (or never made)
    core.on_decision(decision_payload(53, 200.0, []), now_ms=200.0, now_s=1.1)
    ended = [(e.decision.decision_id, e.reason) for e in pool.drain_ended()]
    assert ended == [(51, "not_received"), (52, "not_received"), (50, "superseded")]
    core.on_decision(decision_payload(10**9, 300.0, []), now_ms=300.0, now_s=1.2)
    reasons = [e.reason for e in pool.drain_ended()]
    assert reasons.count("not_received") == MAX_NOT_RECEIVED


def test_the_reconstruction_trains_on_each_frames_own_pose(dataset: SceneDataset,
                                                            monkeypatch) -> None:
    """Poses travel with frames (issue 31): a moving robot's frame trains with the pose it
    carries, not the dataset rig's."""
    from aoi3d.field.carry import Reconstruction
    from aoi3d.scene import Camera, look_at
    from services.kit.codec import camera_to_pb, encode_frame, encode_png

    moved = Camera(c2w=look_at((0.7, -3.1, 1.9), (0.1, 0.0, 0.6)), fx=30.0, fy=31.0, cx=11.0,
                   cy=9.0, width=dataset.width, height=dataset.height)
    image = encode_png(np.zeros((dataset.height, dataset.width, 3), np.uint8))
    frame = pb.Frame.FromString(encode_frame(camera_id=1, sequence=1, generation_ms=0.0,
                                             scene_time_ms=0.0, camera=moved, image=image))
    pose, intr = camera_to_pb(dataset.cameras[dataset.heldout_id])
    job = pb.Job(decision=pb.Decision(decision_id=1, time_ms=0.0), frames=[frame],
                 backend="grid", carry="fresh", render_steps=1, seed=1, pose=pose,
                 intrinsics=intr, aabb=np.asarray(dataset.aabb).reshape(-1).tolist())
    seen = []
    original = Reconstruction.set_views
    monkeypatch.setattr(Reconstruction, "set_views",
                        lambda self, views, *time: (seen.extend(views),
                                                    original(self, views, *time))[1])
    ReconCore(worker_id="w", device="cpu", configs=CONFIGS).run(job)
    assert len(seen) == 1 and seen[0].camera == moved
    assert seen[0].camera != dataset.cameras[1]


def test_replay_rebuilds_the_job_from_the_cameras_the_render_names() -> None:
    """Every camera generates at k·C, so a live job that held one of three frames of 870 ms
    is named by its camera too (Render.frame_camera_ids): the replay takes that one, not the
    first of the selection with the same generation time (the one it took before, and a
    recording from before the field still gets)."""
    from services.kit.pb import aoi3d_pb2 as pb
    from services.recorder.arrivals import Arrival, Arrivals, job_frames

    def frame(cam: int, gen: float) -> pb.Frame:
        return pb.Frame(camera_id=cam, generation_ms=gen,
                        image=pb.Image(encoding=pb.IMAGE_ENCODING_PNG, data=b"png"))

    selected = [(1, 840.0), (9, 870.0), (10, 870.0), (14, 870.0)]
    arr = Arrivals([1, 9, 10, 14], [Arrival(c, g, g + 30.0, frame(c, g)) for c, g in selected])
    got = job_frames(selected, [870.0], arr, [10])
    assert [(f.camera_id, f.generation_ms) for f in got] == [(10, 870.0)]
    old = job_frames(selected, [870.0], arr)  # generation times only: the first that fits
    assert [(f.camera_id, f.generation_ms) for f in old] == [(9, 870.0)]


def test_the_job_trains_the_decisions_own_budget(dataset: SceneDataset) -> None:
    """A decision that carries a budget (a policy's '@<steps>') is a job of that many steps;
    one without is the pool's render_steps."""
    pool = Dispatcher()
    core = make_core(dataset, pool)
    core.on_frame(frame_payload(dataset, 1, 0.0), now_ms=0.0)
    pool.joined("w", 0.5)
    settings = RenderSettings("grid", "fresh", 12, 3)
    for decision_id, budget in ((1, None), (2, 40)):
        msg = pb.Decision.FromString(decision_payload(decision_id, 30.0 * decision_id,
                                                      [(1, 0.0)], policy="mat:70"))
        if budget is not None:
            msg.budget_steps = budget
        core.on_decision(msg.SerializeToString(), now_ms=30.0 * decision_id, now_s=1.0)
        assignment = pool.request(Report("w", max_wait_s=1.0), 1.5)
        job = pb.WorkReply.FromString(core.job(assignment, 1.5, settings)).job
        assert job.render_steps == (12 if budget is None else budget)
        pool.request(Report("w", done=assignment.decision.key, rendered=True), 1.6)


def test_the_model_is_snapshot_for_views_only_while_views_are_asked_for(
        dataset: SceneDataset, monkeypatch: pytest.MonkeyPatch) -> None:
    """A copy of the model per job is CPU the next job lacks: a site's first job is kept, the
    others only within VIEW_INTEREST_S of a view request; a request that finds an older
    snapshot than the site's last job waits for the next (VIEW_WAIT_S, then the older one)."""
    import services.recon.core as recon_core

    monkeypatch.setattr(recon_core, "VIEW_WAIT_S", 0.2)
    pool = Dispatcher()
    core = make_core(dataset, pool)
    pool.joined("w", 0.0)
    recon = ReconCore(worker_id="w", device="cpu", configs=CONFIGS)
    settings = RenderSettings("grid", "stream", 3, 3, cold_steps=7, warm_max_gap_ms=1e6)
    view = pb.ViewRequest(site="north", pose=pb.Pose(c2w=np.asarray(
        dataset.cameras[dataset.heldout_id].c2w, dtype=np.float64).reshape(-1).tolist()),
        intrinsics=pb.Intrinsics(fx=20.0, fy=20.0, cx=8.0, cy=6.0, width=16, height=12))

    done = []

    def job_at(i: int) -> pb.Job:
        for cam in (1, 2):
            core.on_frame(frame_payload(dataset, cam, 100.0 * i), now_ms=100.0 * i)
        core.on_decision(decision_payload(i, 100.0 * i, [(1, 100.0 * i), (2, 100.0 * i)]),
                         now_ms=100.0 * i, now_s=float(i))
        last = done[-1] if done else None
        assignment = pool.request(Report("w", done=last, rendered=last is not None,
                                         max_wait_s=1.0), float(i))
        job = pb.WorkReply.FromString(core.job(assignment, float(i), settings)).job
        recon.run(job)
        recon.keep_latest(job)
        done.append(assignment.decision.key)
        return job

    job_at(1)
    job_at(2)
    assert recon.snapshots == 1  # nobody asked: the first job's only
    stale = recon.view(view)
    assert not stale.error and stale.decision_id == 1  # the older one, after the wait
    job_at(3)  # views were asked for: this job's model is kept
    assert recon.snapshots == 2
    fresh = recon.view(view)
    assert not fresh.error and fresh.decision_id == 3 and len(fresh.data) > 0
