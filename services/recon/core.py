"""The reconstruction worker's core: a :class:`pb.Job` in, a :class:`pb.Render` out.

No bus and no threads. The job carries everything (the decision, its frames, backend, carry,
steps, seed, the camera to render and the scene box), so one worker serves any scene and any
site. The model is an :class:`aoi3d.field.carry.Reconstruction` — the experiments' code: with
the ``fresh`` carry each job is an independent reconstruction; ``stream`` (the live default),
``warm`` and ``fork`` carry this worker's own model from job to job (a new one when the job's
backend, seed, scene box or model epoch changes). Each Render says where in that chain it
stands (``job_index``: the jobs that reached this worker's model before it) and the settings
it was made with (model epoch, budgets, the stream carry's cold steps and gap), so a replay
can run the chain again (:mod:`services.recorder.chains`).

Free views and exports: after a job the worker keeps a snapshot of the model that rendered
it (:class:`aoi3d.field.snapshot.ModelSnapshot`, one per site: its latest) — after every job
while views are being asked for (one in the last :data:`VIEW_INTEREST_S`), else only the first
of each site (a copy of the model a job nobody views is CPU the next job lacks) — and
:meth:`ReconCore.view` answers a :class:`pb.ViewRequest` from it — a render from any pose
(checked by :func:`aoi3d.freeview.check_pose`), a point cloud or a mesh as PLY — without
touching the model the jobs train; a request that finds its site's snapshot older than the
site's last job waits for the next job's (at most :data:`VIEW_WAIT_S`, then the older one
answers). (With the ``fork`` carry the snapshot is the continuously
trained model the forks start from; with the others, the model that rendered the decision.)

Each frame is given its age at the decision (decision time − its generation time), which a
field that reads ages takes; a time-aware field (``flow``) is rendered at the display time:
the scene time ``now_ms()`` gives when the render is taken (the worker's clock), so that the
render shows the scene when it is shown (a static field shows the decision's time).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from aoi3d.field import FieldConfig, FieldTrainer, TrainView
from aoi3d.field import field_config as make_field_config
from aoi3d.field.carry import Reconstruction, RenderedDecision, WarmStart
from aoi3d.field.snapshot import ModelSnapshot, ply_bytes
from aoi3d.freeview import MAX_VIEW_SIDE, PoseError, check_pose, check_size
from services.kit.codec import camera_from_pb, encode_png, frame_data
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import Rejected, RejectReason

__all__ = ["JobFailed", "Latest", "Outcome", "ReconCore", "decode_reply"]

MAX_FRAMES = 256
"""Frames one job may carry (a rig of up to 256 cameras)."""


class JobFailed(Exception):
    """The job cannot be reconstructed; ``reason`` (free text) is the detail of the decision the
    pool counts lost, ``render_failed``."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


@dataclass(frozen=True)
class Outcome:
    render: pb.Render
    rendered: RenderedDecision
    rejected_frames: int


@dataclass(frozen=True)
class Latest:
    """A site's latest model at this worker: its snapshot and the decision it rendered."""

    snapshot: ModelSnapshot
    decision_id: int
    time_ms: float


VIEW_INTEREST_S = 60.0
"""Seconds after a view request during which every job's model is snapshot."""
VIEW_WAIT_S = 2.0
"""Longest a view request waits for a snapshot of its site's last job's model."""
EXPORT_RESOLUTION = 96
"""Lattice points a side of an export unless the request says (96³ ≈ 885 k queries)."""
EXPORT_ALPHA = 0.1
"""Opacity over one lattice step an exported point (or the mesh's surface) has at least."""


def decode_reply(payload: bytes) -> pb.WorkReply:
    try:
        reply: pb.WorkReply = pb.WorkReply.FromString(payload)
        return reply
    except Exception as err:
        raise Rejected(RejectReason.MALFORMED,
                       f"not a WorkReply ({err.__class__.__name__})") from None


class ReconCore:
    """See the module docstring. ``configs``: field configs by backend name that replace the
    defaults (tests use small ones); ``num_threads``: torch threads of each model (0: torch's
    default)."""

    def __init__(self, *, worker_id: str, device: str, num_threads: int = 0,
                 configs: dict[str, FieldConfig] | None = None) -> None:
        self.worker_id = worker_id
        self.device = device
        self.num_threads = num_threads
        self._configs = dict(configs or {})
        self._rec: Reconstruction | None = None
        self._model_key: tuple[str, int, int, tuple[float, ...]] | None = None
        self.jobs = 0
        self.model_jobs = 0
        """Jobs that reached the model (trained it, or would have): a Render's ``job_index``."""
        self.max_view_side = MAX_VIEW_SIDE
        self._latest: dict[str, Latest] = {}
        self._latest_lock = threading.Lock()
        self._latest_cond = threading.Condition(self._latest_lock)
        self._last_job: dict[str, int] = {}
        """site → decision id of the last job rendered (its snapshot may be older)."""
        self._view_asked_s: float | None = None  # monotonic time of the last view request
        self.snapshots = 0
        self.views = 0

    def _config(self, name: str) -> FieldConfig:
        cfg = self._configs.get(name) or make_field_config(name)
        return replace(cfg, num_threads=self.num_threads) if self.num_threads else cfg

    def _reconstruction(self, job: pb.Job, aabb: np.ndarray) -> Reconstruction:
        key = (job.backend, int(job.seed), int(job.model_epoch), tuple(aabb.tolist()))
        if self._rec is None or key != self._model_key:
            try:
                trainer = FieldTrainer(self._config(job.backend), aabb.reshape(2, 3),
                                       device=self.device,
                                       seed=int(job.seed))
            except (KeyError, ValueError, TypeError) as err:
                raise JobFailed("backend", f"cannot build backend {job.backend!r}: "
                                           f"{err}") from None
            try:
                self._rec = Reconstruction(trainer, job.carry, int(job.render_steps),
                                           self._warm_start(job))
            except ValueError as err:
                raise JobFailed("carry", str(err)) from None
            self._model_key = key
        else:
            try:
                self._rec.set_carry(job.carry, int(job.render_steps))
                self._rec.warm_start = self._warm_start(job)
            except ValueError as err:
                raise JobFailed("carry", str(err)) from None
        return self._rec

    @staticmethod
    def _warm_start(job: pb.Job) -> WarmStart:
        """The stream carry's settings the job carries (0: the defaults)."""
        default = WarmStart()
        return WarmStart(cold_steps=int(job.cold_steps) or default.cold_steps,
                         max_gap_ms=float(job.warm_max_gap_ms) or default.max_gap_ms)

    def run(self, job: pb.Job, now_ms: Callable[[], float] | None = None) -> Outcome:
        """Reconstruct the job's decision and render its camera; :class:`JobFailed` when it
        cannot be done (bad scene box, camera, backend or selection). ``now_ms``: the scene
        clock, read once the model is trained (a time-aware field is rendered at that time)
        and once the Render is made: its ``ready_ms``, which the stream carry's gap to the
        next job leaves out (:meth:`aoi3d.field.carry.Reconstruction.ready`)."""
        aabb = np.asarray(job.aabb, dtype=np.float64)
        if aabb.shape != (6,) or not np.all(np.isfinite(aabb)) or np.any(aabb[3:] <= aabb[:3]):
            raise JobFailed("bad_job", "the scene box must be 6 finite values, min < max")
        if len(job.frames) > MAX_FRAMES:
            raise JobFailed("bad_job", f"{len(job.frames)} frames (at most {MAX_FRAMES})")
        try:
            camera = camera_from_pb(job.pose, job.intrinsics)
        except Rejected as err:
            raise JobFailed("bad_job", f"render camera: {err.detail}") from None
        views, gens, cams, rejected = [], [], [], 0
        for frame in job.frames:
            try:
                data = frame_data(frame)
                age = max(0.0, float(job.decision.time_ms) - float(data.generation_ms))
                views.append(TrainView(camera=data.camera, image=data.rgb(),
                                       age_ms=age if math.isfinite(age) else None))
                gens.append(float(data.generation_ms))
                cams.append(int(frame.camera_id))
            except (Rejected, ValueError):
                rejected += 1
        rec = self._reconstruction(job, aabb)
        try:
            rec.set_views(views, float(job.decision.time_ms))  # warm, fork: the model moves there
        except ValueError as err:
            raise JobFailed("bad_selection", str(err)) from None
        job_index, self.model_jobs = self.model_jobs, self.model_jobs + 1
        rendered = rec.render_decision(camera, time_ms=float(job.decision.time_ms))
        image = rendered.image
        if now_ms is not None and rec.trainer.cfg.time_aware:  # taken at the display time
            image = rec.render_at(camera, max(0.0, now_ms() - float(job.decision.time_ms)))
        self.jobs += 1
        d = job.decision
        render = pb.Render(
            decision_id=d.decision_id, decision_incarnation=d.incarnation, time_ms=d.time_ms,
            pose=job.pose, intrinsics=job.intrinsics, image=encode_png(image),
            training_step=rendered.steps, n_views=rendered.n_views, backend=job.backend,
            frame_generation_ms=gens, frame_camera_ids=cams, carry=rec.carry,
            render_steps=rendered.render_steps,
            worker_id=self.worker_id, site=job.site, seed=job.seed, aabb=list(job.aabb),
            warm_start=rendered.warm,
            loss=rendered.loss if math.isfinite(rendered.loss) else math.nan,
            job_index=job_index, model_epoch=job.model_epoch, job_steps=job.render_steps,
            cold_steps=rec.warm_start.cold_steps, warm_max_gap_ms=rec.warm_start.max_gap_ms)
        if now_ms is not None:  # ready: shown from now on; the stream gap leaves the job out
            render.ready_ms = now_ms()
            rec.ready(render.ready_ms)
        return Outcome(render, rendered, rejected)

    def keep_latest(self, job: pb.Job) -> None:
        """Snapshot the model that just rendered ``job`` as its site's latest, when views are
        being asked for or the site has none yet (call it after the render is published: the
        copy never delays a decision's render)."""
        if self._rec is None:
            return
        site, decision_id = job.site or "site1", int(job.decision.decision_id)
        with self._latest_cond:
            self._last_job[site] = decision_id
            asked = self._view_asked_s
            if site in self._latest and (asked is None
                                         or time.monotonic() - asked > VIEW_INTEREST_S):
                return
        latest = Latest(ModelSnapshot(self._rec.trainer), decision_id,
                        float(job.decision.time_ms))
        with self._latest_cond:
            self._latest[site] = latest
            self.snapshots += 1
            self._latest_cond.notify_all()

    def _latest_for_view(self, site: str) -> Latest | None:
        """The site's snapshot for a view: that of its last job, waited for (at most
        :data:`VIEW_WAIT_S`) when the one kept is older; marks views as asked for."""
        deadline = time.monotonic() + VIEW_WAIT_S
        with self._latest_cond:
            self._view_asked_s = time.monotonic()
            while True:
                latest = self._latest.get(site)
                left = deadline - time.monotonic()
                last = self._last_job.get(site)
                if left <= 0 or last is None or (latest is not None
                                                 and latest.decision_id == last):
                    return latest  # (no job of the site here yet: none to wait for)
                self._latest_cond.wait(left)

    def latest(self, site: str) -> Latest | None:
        with self._latest_lock:
            return self._latest.get(site)

    def view(self, req: pb.ViewRequest) -> pb.ViewReply:
        """A free view (PNG) or an export (PLY) of ``req.site``'s latest model; the reply's
        ``error``/``reason`` say why not (no model of that site yet, a bad pose or size, an
        unknown format)."""
        t0 = time.monotonic()
        latest = self._latest_for_view(req.site or "site1")
        if latest is None:
            return pb.ViewReply(error=f"worker {self.worker_id} has no model of site "
                                      f"{req.site!r} yet", reason="no_model",
                                worker_id=self.worker_id)
        snap = latest.snapshot
        try:
            if req.format in ("", "png"):
                check_pose(list(req.pose.c2w), snap.aabb)
                check_size(req.intrinsics.width, req.intrinsics.height, self.max_view_side)
                camera = camera_from_pb(req.pose, req.intrinsics)
                data = encode_png(snap.render(camera)).data
            elif req.format in ("ply", "mesh"):
                res = int(req.resolution) or EXPORT_RESOLUTION
                alpha = float(req.alpha) or EXPORT_ALPHA
                cloud = (snap.point_cloud(resolution=res, alpha=alpha) if req.format == "ply"
                         else snap.mesh(resolution=res, alpha=alpha))
                data = ply_bytes(cloud, comment=f"aoi3d {req.format} of site {req.site} "
                                                f"decision {latest.decision_id} step "
                                                f"{snap.steps}")
            else:
                return pb.ViewReply(error=f"unknown format {req.format!r}: png, ply or mesh",
                                    reason="bad_format", worker_id=self.worker_id)
        except (PoseError, Rejected, ValueError) as err:
            detail = err.detail if isinstance(err, Rejected) else str(err)
            return pb.ViewReply(error=detail, reason="bad_request", worker_id=self.worker_id)
        self.views += 1
        return pb.ViewReply(data=data, decision_id=latest.decision_id, time_ms=latest.time_ms,
                            training_step=snap.steps, worker_id=self.worker_id,
                            compute_s=time.monotonic() - t0)

    def train_between_jobs(self, n: int) -> float:
        """``n`` background steps of a warm or fork model on its last job's frames (no-op for
        fresh, or before the first job)."""
        return self._rec.train(n) if self._rec is not None else math.nan

    @property
    def trains_in_background(self) -> bool:
        return self._rec is not None and self._rec.trains_in_background
