"""The recorder worker: the runtime of :class:`services.recorder.core.Recording`.

It subscribes the run's recorded keys of every site (deliveries, truth frames, decisions,
renders, quality, outcomes) while a recording is open, and only then: an idle recorder costs
the pipeline nothing (its subscriptions took 4 % of a core and a share of the router at time
scale 1). The handlers only enqueue (key, payload, receipt time) into a bounded inbox, and one
writing thread hands them to the core. A write that fails (a full
disk) ends the recording with its error — the recorder, and with it the pipeline, goes on;
the error is in ``GET /recording`` and ``GET /status``, ``/readyz``'s reason, the log, and
``aoi3d_recorder_failed`` (alert ``AoI3DRecordingFailed``).
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

from prometheus_client import CollectorRegistry, Counter, Gauge

from services.kit.bus import Bus, Inbox, Subscription
from services.kit.keys import Keys
from services.kit.observe import Rejected, Rejections
from services.kit.runtime import Loops
from services.recorder.core import Recording, RecordingStatus

log = logging.getLogger(__name__)

_POLL_S = 0.1
RECORDED = ("edge/*/frame", "truth/frame", "decision", "render", "quality", "outcome")
"""The keys recorded, under ``aoi3d/<run>/<site>/`` of every site."""


class RecordingError(ValueError):
    """A start or stop that cannot be done (already recording, nothing to stop)."""


class RecorderRuntime:
    def __init__(self, bus: Bus, registry: CollectorRegistry, *, run_id: str,
                 inbox_size: int = 4096, metadata: dict[str, str] | None = None,
                 chunk_bytes: int = 1 << 20, compression: str = "zstd") -> None:
        self._bus = bus
        self._root = Keys(run_id, "*").root
        self._metadata = dict(metadata or {})
        self._chunk_bytes = chunk_bytes
        self._compression = compression
        self._lock = threading.Lock()  # guards _recording and _last
        self._recording: Recording | None = None
        self._subs: list[Subscription] = []
        self._last: RecordingStatus | None = None
        self._on = False  # read by the bus handlers without the lock
        self._inbox = Inbox(inbox_size, on_drop=self._dropped)
        self._loops = Loops("recorder")
        self._loops.forever("writer", self._step)
        self.rejections = Rejections(registry)
        self._m_messages = Counter("aoi3d_recorder_messages", "Bus messages recorded.",
                                   registry=registry)
        self._m_dropped = Counter("aoi3d_recorder_dropped",
                                  "Bus messages not recorded while recording (inbox full).",
                                  registry=registry)
        self._m_bytes = Gauge("aoi3d_recorder_bytes", "Bytes written by the recording in force "
                                                      "(0 when idle).", registry=registry)
        self._m_state = Gauge("aoi3d_recorder_recording",
                              "1 while a recording is open, else 0.", registry=registry)
        self._m_failed = Gauge("aoi3d_recorder_failed",
                               "1 when the latest recording stopped on a write error (a full "
                               "disk), until a new one starts; else 0 (alert "
                               "AoI3DRecordingFailed).", registry=registry)
        self._m_failures = Counter("aoi3d_recorder_failures",
                                   "Recordings stopped by a write error, by reason (disk_full, "
                                   "io_error).", ["reason"], registry=registry)
        for reason in ("disk_full", "io_error"):
            self._m_failures.labels(reason=reason)

    # ------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self._loops.start()

    def _subscribe(self) -> None:
        """The recorded keys, subscribed (while a recording is open; under ``_lock``)."""
        self._subs = [self._bus.subscribe(f"{self._root}/{suffix}", self._on_message)
                      for suffix in RECORDED]

    def _unsubscribe(self) -> None:
        subs, self._subs = self._subs, []
        for sub in subs:
            sub.undeclare()

    def stop(self) -> None:
        """Stop the writing thread, write what was received before, finish the file."""
        self._on = False
        self._loops.stop()
        for item in self._inbox.drain():
            self._write(*item)
        with self._lock:
            self._close_locked()

    def readiness(self) -> tuple[bool, str]:
        why = self._loops.not_running()
        if why:
            return False, why
        status = self.status()
        if status is not None and status.state == "failed":
            return True, status.error or "the recording failed"
        return True, "recording" if self._on else "idle"

    # ------------------------------------------------------------ control
    def start_recording(self, path: Path, *, max_bytes: int = 0) -> RecordingStatus:
        with self._lock:
            if self._recording is not None:
                raise RecordingError(f"already recording into {self._recording.path}; "
                                     "POST /recording/stop first")
            meta = {**self._metadata, "started_unix_s": repr(time.time())}
            rec = Recording(path, max_bytes=max_bytes, chunk_bytes=self._chunk_bytes,
                            compression=self._compression, metadata=meta)
            self._last = rec.status
            if not rec.active:
                self._failed(rec)
                return rec.status
            self._m_failed.set(0)
            self._recording = rec
            self._on = True
            self._subscribe()
            self._m_state.set(1)
            log.info("recording into %s", path)
            return rec.status

    def stop_recording(self) -> RecordingStatus:
        self._on = False
        for item in self._inbox.drain():  # what was received before the stop is kept
            self._write(*item)
        with self._lock:
            if self._recording is None:
                if self._last is not None:
                    return self._last
                raise RecordingError("no recording was started")
            status = self._close_locked()
            assert status is not None, "a recording was open"
            return status

    def _close_locked(self) -> RecordingStatus | None:
        rec, self._recording = self._recording, None
        self._on = False
        self._unsubscribe()
        self._m_state.set(0)
        self._m_bytes.set(0)
        if rec is None:
            return None
        status = rec.close()
        log.info("recording %s: %s, %d messages, %d bytes in %d segment(s)", status.path,
                 status.state, status.messages, status.bytes_written, len(status.segments))
        return status

    def _failed(self, rec: Recording) -> None:
        """A recording that stopped on a write error: logged, counted, the gauge up."""
        log.error("%s", rec.status.error)
        error = rec.status.error or ""
        self._m_failures.labels(reason="disk_full" if "disk is full" in error
                                else "io_error").inc()
        self._m_failed.set(1)

    def status(self) -> RecordingStatus | None:
        with self._lock:
            return self._last

    # ------------------------------------------------------------ the bus and the writer
    def _on_message(self, key: str, payload: bytes) -> None:
        if self._on:
            self._inbox.put((key, payload, time.time_ns()))

    def _dropped(self) -> None:
        self._m_dropped.inc()

    def _step(self) -> None:
        item = self._inbox.get(timeout=_POLL_S)
        if item is not None:
            self._write(*item)

    def _write(self, key: str, payload: bytes, log_ns: int) -> None:
        with self._lock:
            rec = self._recording
            if rec is None:
                return
            try:
                rec.write(key, payload, log_ns)
            except Rejected as err:
                self.rejections.reject(err, key)
                return
            if not rec.active:  # the write failed: the recording ends, the recorder goes on
                self._failed(rec)
                self._recording = None
                self._on = False
                self._unsubscribe()
                self._m_state.set(0)
                return
            self._m_messages.inc()
            self._m_bytes.set(rec.status.bytes_written)
