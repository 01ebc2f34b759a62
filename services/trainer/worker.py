"""The trainer worker: delivered frames + decisions in, renders of the novel view out.

Bus callbacks only put raw payloads into :class:`Inbox` queues. One training thread owns
the radiance field, driven by an :class:`aoi3d.field.carry.Reconstruction` (the experiments'
carry modes, the same code): between small chunks of ``steps_per_chunk`` background steps it
ingests the queued frames (kept per camera, still encoded), applies the newest decision
(resolves its selected FrameRefs to frames, decodes them and swaps the training set, model
kept), and ``render_period_s`` wall seconds after the previous render it renders the
decision in force — with the default ``fresh`` carry, a new model trained ``render_steps``
steps on exactly that decision's frames — and publishes a Render stamped
with that decision and the generation times of its frames. Control requests from the HTTP
threads — reset the model, switch the backend or the carry — are queued and carried out by
the training thread between two chunks, so no other thread ever touches the model.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, replace

import numpy as np
from prometheus_client import CollectorRegistry, Counter, Gauge

from aoi3d.clock import SimClock
from aoi3d.device import resolve_device
from aoi3d.field import FieldConfig, FieldTrainer, TrainView
from aoi3d.field import field_config as make_field_config
from aoi3d.field.carry import CARRY_MODES, Reconstruction, check_carry
from aoi3d.scene import SceneDataset
from aoi3d.scene.camera import Camera
from services.kit.bus import Bus, Inbox
from services.kit.codec import (
    camera_to_pb,
    decode_decision,
    decode_frame,
    encode_png,
)
from services.kit.keys import Keys
from services.kit.observe import Heartbeat, RateMeter, Rejected, Rejections
from services.kit.pb import aoi3d_pb2 as pb
from services.trainer.control import ControlQueue
from services.trainer.frames import FrameBuffer
from services.trainer.settings import Settings
from services.trainer.state import (
    BackendBuildError,
    CarryError,
    DecisionInForce,
    LatestRender,
    TrainerStatus,
    check_backend,
)

log = logging.getLogger(__name__)

RATE_WINDOW_S = 5.0
"""Wall seconds over which ``steps_per_s`` is measured."""

_IDLE_WAIT_S = 0.05
_STOP_JOIN_S = 2.0


@dataclass
class _BackendRequest:
    """A request to switch the backend; the training thread fills ``error`` if it fails."""

    name: str
    error: str | None = None


class TrainerWorker:
    """Owns the radiance field and its training thread; see the module docstring."""

    def __init__(self, settings: Settings, bus: Bus, registry: CollectorRegistry, *,
                 dataset: SceneDataset, clock: SimClock,
                 field_config: FieldConfig | None = None) -> None:
        self.settings = settings
        self.bus = bus
        self.clock = clock
        self.keys = Keys(settings.common.run_id)
        self.backend = check_backend(settings.backend)
        self.device = resolve_device(settings.device)
        # Configs given here are used whenever their backend is (re)built; others: defaults.
        self._configs: dict[str, FieldConfig] = (
            {} if field_config is None else {settings.backend: field_config})
        self._aabb = dataset.aabb
        self.heldout_camera: Camera = dataset.cameras[dataset.heldout_id]
        self._camera_ids = frozenset(range(1, settings.common.cameras + 1))
        # every frame must have the scene's image size (checked before anything is decoded)
        sizes = {(c.width, c.height) for c in dataset.cameras}
        self._size = sizes.pop() if len(sizes) == 1 else None
        self._skew_ms = settings.common.skew_ms
        self._scene_key = f"{dataset.root.resolve()}|{np.asarray(dataset.aabb).tolist()}"
        self._ckpt_path = settings.checkpoint_dir / f"{settings.common.run_id}.trainer.pt"
        self._ckpt_saved_steps: int | None = 0  # nothing trained: nothing to save
        self.resumed_steps = 0
        self._decisions_beat = Heartbeat(settings.common.stall_s)  # a decision accepted
        self._steps_beat = Heartbeat(settings.common.stall_s)  # a training step taken
        self.trainer = self._build_trainer(self.backend)
        self.rec = Reconstruction(self.trainer, settings.carry, settings.render_steps)

        self.rejections = Rejections(registry)
        self.m_steps = Counter("aoi3d_trainer_steps", "Training steps taken.",
                               registry=registry)
        self.m_rate = Gauge("aoi3d_trainer_steps_per_second",
                            f"Training steps per wall second over the last {RATE_WINDOW_S:g} s.",
                            registry=registry)
        self.m_loss = Gauge("aoi3d_trainer_loss", "Photometric loss of the last training step.",
                            registry=registry)
        self.m_views = Gauge("aoi3d_trainer_views", "Frames in the training set.",
                             registry=registry)
        self.m_renders = Counter("aoi3d_renders", "Novel-view renders published.",
                                 registry=registry)
        self.m_decisions = Counter("aoi3d_trainer_decisions", "Decisions applied.",
                                   registry=registry)
        self.m_received = Counter("aoi3d_trainer_frames_received",
                                  "Delivered frames accepted into the per-camera buffers.",
                                  registry=registry)
        self.m_missing = Counter(
            "aoi3d_trainer_frames_missing",
            "Selected frames skipped because the trainer never received them.",
            registry=registry)
        self.m_render_age = Gauge(
            "aoi3d_render_age_seconds",
            "Wall seconds from the rendered decision taking effect at the trainer to the "
            "render's publication (the compute lag a viewer sees).", registry=registry)
        self.m_render_lag = Gauge(
            "aoi3d_render_lag_sim_seconds",
            "Sim seconds from the time the latest render represents to its publication.",
            registry=registry)
        self.m_frames_age = Gauge(
            "aoi3d_render_frames_age_seconds",
            "Mean age (sim s) at the represented time of the frames the latest render's "
            "decision selected: how stale what it shows is.", registry=registry)
        self.m_render_steps = Gauge(
            "aoi3d_render_steps",
            "Training steps spent on the latest rendered decision's own frames (carry fork or "
            "fresh; 0 for warm).", registry=registry)
        self.m_overflow = Counter(
            "aoi3d_trainer_inbox_overflow",
            "Frames and decisions dropped unread because the training thread fell behind.",
            registry=registry)
        self.m_checkpoints = Counter("aoi3d_trainer_checkpoints", "Model checkpoints written.",
                                     registry=registry)
        self.m_loss.set(math.nan)
        for gauge in (self.m_render_age, self.m_render_lag, self.m_frames_age):
            gauge.set(math.nan)

        self._frames_in: Inbox = Inbox(maxsize=max(256, 4 * len(self._camera_ids)),
                                       on_drop=self.m_overflow.inc)
        self._decisions_in: Inbox = Inbox(maxsize=64, on_drop=self.m_overflow.inc)
        self._frames = FrameBuffer(settings.frames_per_camera)
        self._views: list[TrainView] = []

        self._stop = threading.Event()
        self._wake = threading.Event()
        self._control = ControlQueue(self._wake)
        self._thread: threading.Thread | None = None
        self._rate = RateMeter(RATE_WINDOW_S)

        # State shared with the HTTP threads, guarded by _state_lock.
        self._state_lock = threading.Lock()
        self._steps_total = 0
        self._steps_per_s = 0.0
        self._loss: float | None = None
        self._n_views = 0
        self._decision: DecisionInForce | None = None
        self._renders = 0
        self._latest: LatestRender | None = None
        self._frames_received = 0
        self._frames_buffered = 0
        self._frames_missing = 0
        self._resets = 0
        self._error: str | None = None

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self._resume()
        self.bus.subscribe(self.keys.edge_frames, self._on_frame)
        self.bus.subscribe(self.keys.decision, self._on_decision)
        self._thread = threading.Thread(target=self._run, name="trainer", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=_STOP_JOIN_S)
            if self._thread.is_alive():
                log.warning("training thread did not stop within %.1f s", _STOP_JOIN_S)

    def readiness(self) -> tuple[bool, str]:
        if self._thread is None or not self._thread.is_alive():
            return False, self._error or "training thread not running"
        if not self._decisions_beat.stalled() and self._steps_beat.stalled():
            return False, (f"decisions arrive but no training step for "
                           f"{self._steps_beat.idle_s():.0f} s")
        with self._state_lock:
            if self._decision is None:
                return True, "waiting for the first decision"
            return True, f"training on decision {self._decision.decision_id}"

    # ------------------------------------------------------------------ bus callbacks
    def _on_frame(self, key: str, payload: bytes) -> None:
        self._frames_in.put((key, payload))
        self._wake.set()

    def _on_decision(self, key: str, payload: bytes) -> None:
        self._decisions_in.put((key, payload))
        self._wake.set()

    # ------------------------------------------------------------------ control (any thread)
    def reset(self, timeout_s: float = 10.0) -> bool:
        """Re-initialise the model (training set and buffered frames kept).

        Done by the training thread between two chunks; returns False if it did not happen
        within ``timeout_s``.
        """
        return self._control.call(self._do_reset, thread_alive=self._running(),
                                  timeout_s=timeout_s)

    def set_backend(self, name: str, timeout_s: float = 30.0) -> bool:
        """Train a new model of backend ``name`` from now on (training set and buffered frames
        kept; counts as a reset).

        Raises :class:`UnknownBackendError` for a name not in ``aoi3d.field.BACKENDS`` and
        :class:`BackendBuildError` when its model cannot be built (the previous one is kept).
        Done by the training thread between two chunks; returns False if it did not happen
        within ``timeout_s``.
        """
        check_backend(name)
        request = _BackendRequest(name)
        if not self._control.call(lambda: self._do_backend(request),
                                  thread_alive=self._running(), timeout_s=timeout_s):
            return False
        if request.error is not None:
            raise BackendBuildError(request.error)
        return True

    def set_carry(self, carry: str, render_steps: int, timeout_s: float = 10.0) -> bool:
        """Make renders with ``carry`` and ``render_steps`` from the next render on (the model
        and the decision in force are kept). Raises :class:`CarryError` — nothing changed —
        for an unknown mode or budget. Done by the training thread between two chunks;
        returns False if it did not happen within ``timeout_s``."""
        try:
            check_carry(carry, render_steps)
        except ValueError as err:
            raise CarryError(f"{err}; accepted carry modes: {', '.join(CARRY_MODES)}") from None
        return self._control.call(lambda: self._do_carry(carry, int(render_steps)),
                                  thread_alive=self._running(), timeout_s=timeout_s)

    def _running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def status(self) -> TrainerStatus:
        with self._state_lock:
            decision = self._decision
            return TrainerStatus(
                steps=int(self.trainer.steps),
                steps_total=self._steps_total,
                steps_per_s=self._steps_per_s,
                loss=self._loss,
                n_views=self._n_views,
                decision=decision,
                decision_age_ms=None if decision is None
                else self.clock.now_ms() - decision.time_ms,
                backend=self.backend,
                device=self.device,
                carry=self.rec.carry,
                render_steps=self.rec.render_steps,
                renders=self._renders,
                frames_received=self._frames_received,
                frames_buffered=self._frames_buffered,
                frames_missing=self._frames_missing,
                resets=self._resets,
                running=self._thread is not None and self._thread.is_alive(),
            )

    def latest_render(self) -> LatestRender | None:
        with self._state_lock:
            return self._latest

    # ------------------------------------------------------------------ checkpoints
    def _resume(self) -> None:
        """Go on from this run's checkpoint when it is of the same backend and scene."""
        if not self.settings.checkpoint_period_s or not self._ckpt_path.is_file():
            return
        import torch

        try:
            doc = torch.load(self._ckpt_path, map_location=self.device, weights_only=False)
            if (doc.get("backend"), doc.get("scene")) != (self.backend, self._scene_key):
                log.info("checkpoint %s is of backend %s on another scene or backend: starting "
                         "fresh", self._ckpt_path, doc.get("backend"))
                return
            self.trainer.restore(doc["state"])
        except Exception as err:  # a torn or foreign file must not stop the trainer
            log.warning("could not resume from %s (%r): starting fresh", self._ckpt_path, err)
            self.trainer = self._build_trainer(self.backend)
            self.rec = Reconstruction(self.trainer, self.rec.carry, self.rec.render_steps)
            return
        self.resumed_steps = self._ckpt_saved_steps = self.trainer.steps
        log.info("resumed from %s at step %d", self._ckpt_path, self.trainer.steps)

    def _save_checkpoint(self) -> None:
        """Write the model atomically (a temporary file, then rename) if it trained since."""
        if self.trainer.steps == self._ckpt_saved_steps:
            return
        import torch

        self._ckpt_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self._ckpt_path.with_suffix(".tmp")
        torch.save({"backend": self.backend, "scene": self._scene_key,
                    "saved_unix_s": time.time(), "state": self.trainer.checkpoint()}, tmp)
        tmp.replace(self._ckpt_path)
        self._ckpt_saved_steps = self.trainer.steps
        self.m_checkpoints.inc()

    def _drop_checkpoint(self) -> None:
        """A reset or a new backend starts fresh, also after a restart."""
        self._ckpt_path.unlink(missing_ok=True)
        self._ckpt_saved_steps = None

    # ------------------------------------------------------------------ training thread
    def _run(self) -> None:
        next_render_s = time.monotonic() + self.settings.render_period_s
        period_s = self.settings.checkpoint_period_s
        next_ckpt_s = time.monotonic() + period_s
        try:
            while not self._stop.is_set():
                self._wake.clear()
                self._ingest()
                if self._stop.is_set():
                    break
                training = bool(self._views) and self.rec.trains_in_background
                if training:
                    self._train_chunk()
                else:
                    self._record_idle()
                now = time.monotonic()
                if now >= next_render_s:
                    self._render_and_publish()
                    # background training gets render_period_s between two renders, however
                    # long a render (with its own training) took
                    next_render_s = time.monotonic() + self.settings.render_period_s
                if period_s and now >= next_ckpt_s:
                    try:
                        self._save_checkpoint()
                    except OSError as err:
                        log.warning("could not write checkpoint %s: %r", self._ckpt_path, err)
                    next_ckpt_s = time.monotonic() + period_s
                if not training:
                    self._wake.wait(min(_IDLE_WAIT_S, max(0.0, next_render_s - now)))
        except Exception as err:  # keep the service up to report it on /readyz
            self._error = f"training thread failed: {err!r}"
            log.exception("training thread failed")

    def _ingest(self) -> None:
        # Decisions first, then frames: every frame sent before those decisions is then in.
        decisions = self._decisions_in.drain()
        for key, payload in self._frames_in.drain():
            self._store_frame(key, payload)
        newest: pb.Decision | None = None
        for key, payload in decisions:
            try:
                msg = decode_decision(payload)
                self._check_decision(msg, newest)
            except Rejected as err:
                self.rejections.reject(err, key)
                continue
            newest = msg
        if newest is not None:
            self._decisions_beat.beat()
            self._apply_decision(newest)
        self._control.run_pending()

    def _check_decision(self, msg: pb.Decision, newest: pb.Decision | None) -> None:
        """Raise :class:`Rejected` unless ``msg`` supersedes the decision in force (or the
        newer ``newest`` of this batch).

        Decisions are ordered by the sim time they are for, then by id, within one scheduler
        incarnation; a decision of another incarnation (a restarted scheduler, which numbers
        from 1 again) supersedes at once. Times further ahead of this clock than the skew
        are rejected, so no message — not even one with id 2^64−1 — can hold the trainer for
        longer than the skew.
        """
        now_ms = self.clock.now_ms()
        if msg.time_ms > now_ms + self._skew_ms:
            raise Rejected("clock_skew", f"decision for {msg.time_ms:g} ms but this clock says "
                                         f"{now_ms:g} ms")
        if newest is not None:
            current = (newest.incarnation, newest.time_ms, newest.decision_id)
        else:
            with self._state_lock:
                d = self._decision
            if d is None:
                return
            current = (d.incarnation, d.time_ms, d.decision_id)
        incarnation, time_ms, decision_id = current
        if msg.incarnation != incarnation:
            return
        if (msg.time_ms, msg.decision_id) <= (time_ms, decision_id):
            raise Rejected("stale_decision",
                           f"decision {msg.decision_id} for {msg.time_ms:g} ms is not newer "
                           f"than decision {decision_id} for {time_ms:g} ms")

    def _store_frame(self, key: str, payload: bytes) -> None:
        try:
            frame = decode_frame(payload, self._camera_ids, self._size)
            if frame.generation_ms > self.clock.now_ms() + self._skew_ms:
                raise Rejected("clock_skew", f"frame generated at {frame.generation_ms:g} ms, "
                                             f"ahead of this clock")
        except Rejected as err:
            self.rejections.reject(err, key)
            return
        self._frames.add(frame)
        self.m_received.inc()
        with self._state_lock:
            self._frames_received += 1
            self._frames_buffered = len(self._frames)

    def _apply_decision(self, decision: pb.Decision) -> None:
        views: list[TrainView] = []
        generation: list[float] = []
        missing = 0
        for ref in decision.selected:
            frame = self._frames.find(ref.camera_id, ref.generation_ms)
            if frame is None:
                missing += 1
                continue
            try:
                views.append(TrainView(camera=frame.camera, image=frame.rgb()))
                generation.append(float(frame.generation_ms))
            except Rejected as err:
                self.rejections.reject(err, self.keys.edge_frame(ref.camera_id))
        if missing:
            self.m_missing.inc(missing)
            log.debug("decision %d: %d selected frame(s) never received",
                      decision.decision_id, missing)
        try:
            self.rec.set_views(views)
        except ValueError as err:  # the field refuses the selection: keep the previous one
            self.rejections.reject(Rejected("bad_selection", str(err)), self.keys.decision)
            return
        self._views = views
        self.m_decisions.inc()
        self.m_views.set(len(views))
        with self._state_lock:
            self._n_views = len(views)
            self._frames_missing += missing
            self._decision = DecisionInForce(
                decision_id=decision.decision_id, incarnation=decision.incarnation,
                time_ms=decision.time_ms,
                policy=decision.policy, n_selected=len(decision.selected), n_missing=missing,
                applied_wall_s=time.time(), generation_ms=tuple(generation))

    def _train_chunk(self) -> None:
        n = self.settings.steps_per_chunk
        self._count_steps(n, float(self.rec.train(n)))

    def _count_steps(self, n: int, loss: float) -> None:
        """Account for ``n`` training steps (background or a render's own) ending at ``loss``."""
        now = time.monotonic()
        self._steps_beat.beat()
        self.m_steps.inc(n)
        if math.isfinite(loss):
            self.m_loss.set(loss)
        with self._state_lock:
            self._steps_total += n
            self._steps_per_s = self._rate.add(now, self._steps_total)
            self._loss = loss if math.isfinite(loss) else None
            rate = self._steps_per_s
        self.m_rate.set(rate)

    def _record_idle(self) -> None:
        with self._state_lock:
            self._steps_per_s = self._rate.idle(time.monotonic(), self._steps_total)
            rate = self._steps_per_s
        self.m_rate.set(rate)

    def _render_and_publish(self) -> None:
        with self._state_lock:
            decision = self._decision
        if decision is None:  # nothing to represent yet: no render before the first decision
            return
        camera = self.heldout_camera
        rendered = self.rec.render_decision(camera)
        if rendered.render_steps:
            self._count_steps(rendered.render_steps, rendered.loss)
        image = encode_png(rendered.image)
        pose, intrinsics = camera_to_pb(camera)
        gens = decision.generation_ms
        frames_age_ms = (decision.time_ms - float(np.mean(gens))) if gens else math.nan
        lag_ms = self.clock.now_ms() - decision.time_ms
        wall = time.time()
        age_s = wall - decision.applied_wall_s
        msg = pb.Render(decision_id=decision.decision_id,
                        decision_incarnation=decision.incarnation,
                        time_ms=decision.time_ms, pose=pose,
                        intrinsics=intrinsics, image=image, training_step=rendered.steps,
                        n_views=rendered.n_views, backend=self.backend,
                        frame_generation_ms=list(gens), carry=self.rec.carry,
                        render_steps=rendered.render_steps)
        self.bus.publish(self.keys.render, msg.SerializeToString())
        self.m_renders.inc()
        self.m_render_age.set(age_s)
        self.m_render_lag.set(lag_ms / 1000.0)
        self.m_frames_age.set(frames_age_ms / 1000.0)
        self.m_render_steps.set(rendered.render_steps)
        with self._state_lock:
            self._renders += 1
            self._latest = LatestRender(png=image.data, decision_id=decision.decision_id,
                                        time_ms=decision.time_ms, training_step=rendered.steps,
                                        n_views=rendered.n_views, wall_s=wall,
                                        carry=self.rec.carry,
                                        render_steps=rendered.render_steps,
                                        frames_age_ms=frames_age_ms, lag_ms=lag_ms, age_s=age_s)

    def _config(self, name: str) -> FieldConfig:
        cfg = self._configs.get(name) or make_field_config(name)
        if self.settings.torch_threads:
            cfg = replace(cfg, num_threads=self.settings.torch_threads)
        return cfg

    def _build_trainer(self, name: str) -> FieldTrainer:
        return FieldTrainer(self._config(name), self._aabb, device=self.device,
                            seed=self.settings.seed)

    def _do_backend(self, request: _BackendRequest) -> None:
        """Replace the model by a new one of ``request.name``, on the current views."""
        try:
            trainer = self._build_trainer(request.name)
            rec = Reconstruction(trainer, self.rec.carry, self.rec.render_steps)
            rec.set_views(self._views)
        except Exception as err:  # the caller hears of it; the old model trains on
            request.error = (f"could not build backend {request.name!r} ({err!r}); still "
                             f"training {self.backend!r}")
            log.warning("%s", request.error)
        else:
            previous = self.backend
            self._drop_checkpoint()
            with self._state_lock:
                self.trainer = trainer
                self.rec = rec
                self.backend = request.name
                self._resets += 1
                self._loss = None
            self.m_loss.set(math.nan)
            log.info("backend %s -> %s (%d views kept)", previous, request.name,
                     len(self._views))

    def _do_carry(self, carry: str, render_steps: int) -> None:
        """Render with ``carry`` and ``render_steps`` from now on (model and views kept)."""
        with self._state_lock:
            self.rec.set_carry(carry, render_steps)
        log.info("renders: carry %s, %d steps per rendered decision", carry, render_steps)

    def _do_reset(self) -> None:
        self.trainer.reset()  # keeps the views
        self._drop_checkpoint()
        with self._state_lock:
            self._resets += 1
            self._loss = None
        self.m_loss.set(math.nan)
        log.info("model reset (%d views kept)", len(self._views))
