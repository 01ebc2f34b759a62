"""Run the whole pipeline locally: a Zenoh router plus the services as supervised processes.

Used by ``aoi3d up`` (and so ``make up``). :data:`SERVICES` and :data:`DEFAULT_PORTS` are the
one list of services: the ports checked before start, the processes started, the table shown;
after them, ``workers`` reconstruction workers (:data:`WORKER`), which have no port.

Before anything starts, :func:`taken_ports` finds the REST and Zenoh ports already in use
(``aoi3d up`` then stops with one line naming the port and the option that moves it). Each
run writes its logs to a folder of its own, ``<log_dir>/<run id>-<UTC start time>/``
(``<name>.log`` per process and ``up.json``), and points ``<log_dir>/latest`` at it, so no run
overwrites another's logs. Each child runs in its own process group with the run's shared
environment (run id, clock epoch and scale, endpoints, ports); child output goes to its log
and, prefixed, to the console.

Start-up: the router must accept TCP connections (with ``--record``, then the recorder must
answer, so that the recording begins before any frame flows), then every service must answer
``/healthz`` *from its own process* (the answer carries the pid, so another pipeline on the
same ports never passes for this one) within ``ready_timeout_s``. A service that exits before
it is healthy is restarted once; a second exit, or the timeout, ends the start-up with one
error naming the service and the last line of its log, and :meth:`Supervisor.run` returns 1.
After start-up, a child that exits unexpectedly is restarted with a back-off (1 s; doubling
up to 30 s only while it keeps exiting within :data:`STEADY_S` of its start) and the restart
is logged. On SIGINT/SIGTERM (or after ``duration_s``) every child gets SIGTERM, then SIGKILL
after a grace period, so no process is left behind.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

from aoi3d.atomic import write_atomic  # stdlib only, as this module
from services.processes import (  # the run's processes; re-exported for the CLI and tests
    DEFAULT_PORTS,
    LATEST,
    SERVICES,
    STARTUP_RESTARTS,
    STEADY_S,
    WORKER,
    Child,
    UpConfig,
    auto_workers,
    last_line,
    port_in_use,
    run_log_dir,
    site_names,
    taken_ports,
)

log = logging.getLogger("aoi3d.up")

__all__ = ["DEFAULT_PORTS", "LATEST", "SERVICES", "STARTUP_RESTARTS", "STEADY_S", "WORKER",
           "Child", "Supervisor", "UpConfig", "auto_workers", "last_line", "port_in_use",
           "run_log_dir", "site_names", "taken_ports"]


class Supervisor:
    def __init__(self, cfg: UpConfig, on_ready: Callable[[Supervisor], None] | None = None):
        self.cfg = cfg
        self.on_ready = on_ready
        self.stopping = threading.Event()
        self.started = datetime.now(UTC)
        self.log_dir: Path | None = None
        """This run's own log folder (made when :meth:`run` starts)."""
        self.failure: str | None = None
        """Why the start-up failed (one line), else None."""
        self.children = self._plan()

    def _plan(self) -> list[Child]:
        cfg = self.cfg
        endpoint = f"tcp/127.0.0.1:{cfg.zenoh_port}"
        base = dict(os.environ)
        base.update({
            "PYTHONUNBUFFERED": "1",
            "AOI3D_RUN_ID": cfg.run_id,
            "AOI3D_EPOCH_S": repr(time.time()),
            "AOI3D_TIME_SCALE": repr(cfg.time_scale),
            "AOI3D_CAMERAS": str(cfg.cameras),
            "AOI3D_SITES": ",".join(site_names(cfg.sites)),
            "AOI3D_DATASET": str(Path(cfg.dataset).resolve()),
            "AOI3D_ZENOH_MODE": "client",
            "AOI3D_ZENOH_CONNECT": endpoint,
            "AOI3D_ROUTER_LISTEN": endpoint,
        })
        for name in SERVICES:
            base[f"AOI3D_{name.upper()}_PORT"] = str(cfg.port(name))
            base[f"AOI3D_{name.upper()}_HOST"] = "127.0.0.1"
        if cfg.rig is not None:  # real cameras: the ingest service in the camera's slot
            base.update({"AOI3D_RIG": str(Path(cfg.rig).resolve()),
                         "AOI3D_INGEST_PORT": str(cfg.port("camera")),
                         "AOI3D_INGEST_HOST": "127.0.0.1",
                         "AOI3D_INGEST_THROUGH_NETWORK": "true" if cfg.delay else "false"})
        if cfg.delay:
            base["AOI3D_NETWORK_DELAY"] = cfg.delay
        base.update(cfg.extra_env)
        children = [Child("router", cfg.commands.get("router", [sys.executable, "-m",
                                                                "services.router"]),
                          base, Path("router.log"))]
        children += [Child(name, cfg.commands.get(name, [sys.executable, "-m",
                                                         cfg.module(name)]),
                           base, Path(f"{name}.log")) for name in SERVICES]
        argv = cfg.commands.get(WORKER, [sys.executable, "-m", f"services.{WORKER}"])
        children += [Child(f"{WORKER}-{i}", argv, base, Path(f"{WORKER}-{i}.log"))
                     for i in range(1, cfg.workers + 1)]
        return children

    # ------------------------------------------------------------ lifecycle
    def run(self) -> int:
        """Start everything, supervise until stopped; returns the exit code (1: the start-up
        failed, :attr:`failure` says why)."""
        previous = {sig: signal.signal(sig, self._on_signal)
                    for sig in (signal.SIGINT, signal.SIGTERM)}
        try:
            self.log_dir = run_log_dir(self.cfg.log_dir, self.cfg.run_id, self.started)
            for child in self.children:
                child.log_path = self.log_dir / child.log_path.name
            log.info("logs of this run: %s", self.log_dir)
            for child in self.children:  # the decision ledger outlives a metrics restart
                child.env.setdefault("AOI3D_METRICS_STATE_DIR", str(self.log_dir))
            self._write_state()
            router, services = self.children[0], self.children[1:]
            router.start(self.cfg.echo)
            if not self._wait_tcp(self.cfg.zenoh_port, router):
                return 0 if self.stopping.is_set() else 1
            # --record: the recorder first, so the file holds the run from its first message
            # (a replay of the stream carry runs each worker's chain from its first job)
            first = [c for c in services if c.name == "recorder"
                     and c.env.get("AOI3D_RECORDER_PATH")]
            for child in first:
                child.start(self.cfg.echo)
            if first and not self._wait_ready(first):
                return 0 if self.stopping.is_set() else 1
            for child in services:
                if all(child is not c for c in first):
                    child.start(self.cfg.echo)
            self._write_state()
            if not self._wait_ready():
                return 0 if self.stopping.is_set() else 1
            if self.on_ready:
                self.on_ready(self)
            deadline = (time.monotonic() + self.cfg.duration_s
                        if self.cfg.duration_s is not None else None)
            while not self.stopping.is_set():
                if deadline is not None and time.monotonic() >= deadline:
                    log.info("duration reached; stopping")
                    break
                self._restart_dead()
                self.stopping.wait(0.5)
            return 0
        finally:
            self.shutdown()
            for sig, handler in previous.items():
                signal.signal(sig, handler)

    def _on_signal(self, signum, _frame) -> None:
        log.info("received %s; stopping the pipeline", signal.Signals(signum).name)
        self.stopping.set()

    def _fail(self, child: Child, what: str) -> None:
        """Record and log why the start-up failed: one line with the child's last log line."""
        self._settle_output(child)
        said = last_line(child.log_path)
        self.failure = (f"{what}" + (f"; its last log line: {said}" if said else "")
                        + f" (log: {child.log_path})")
        log.error("%s", self.failure)

    @staticmethod
    def _settle_output(child: Child) -> None:
        """Let the log pump copy what an exited child wrote."""
        if child._pump is not None and not child.alive():
            child._pump.join(timeout=2)

    def _restart_dead(self) -> None:
        now = time.monotonic()
        for child in self.children:
            if child.alive() or self.stopping.is_set() or child.proc is None:
                continue  # (None: not started yet)
            if child.next_start == 0.0:
                code = child.proc.returncode if child.proc else None
                child.exits.append(code)
                child.quick_exits = child.quick_exits + 1 if now - child.started_s < STEADY_S \
                    else 0
                backoff = min(30.0, 1.0 * 2 ** min(max(child.quick_exits - 1, 0), 5))
                child.next_start = now + backoff
                log.warning("service %s exited with code %s; restarting in %.0f s "
                            "(restart #%d, log: %s)", child.name, code, backoff,
                            child.restarts + 1, child.log_path)
            elif now >= child.next_start:
                child.restarts += 1
                child.next_start = 0.0
                child.start(self.cfg.echo)
                self._write_state()
                assert child.proc is not None  # start() set it
                log.warning("service %s restarted (pid %d)", child.name, child.proc.pid)

    def shutdown(self) -> None:
        """SIGTERM every child's process group, wait, SIGKILL what is left."""
        # services first, the router last, so services can leave the bus cleanly
        for child in reversed(self.children[1:]):
            child.signal_group(signal.SIGTERM)
        self._wait_exit(self.children[1:], self.cfg.grace_s)
        self.children[0].signal_group(signal.SIGTERM)
        self._wait_exit(self.children[:1], self.cfg.grace_s)
        for child in self.children:
            if child.alive():
                log.warning("%s did not stop in %.0f s; killing it", child.name,
                            self.cfg.grace_s)
            child.signal_group(signal.SIGKILL)
            if child.proc is not None:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    child.proc.wait(timeout=5)
            if child._pump is not None:
                child._pump.join(timeout=2)
        self._write_state(stopped=True)
        log.info("pipeline stopped")

    @staticmethod
    def _wait_exit(children: list[Child], timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and any(c.alive() for c in children):
            time.sleep(0.05)

    # ------------------------------------------------------------ readiness
    def _wait_tcp(self, port: int, child: Child) -> bool:
        """Wait until ``child`` (the router) accepts TCP connections on ``port``; False (and
        :attr:`failure` set, unless stopping) if it exits or the start-up timeout passes."""
        deadline = time.monotonic() + self.cfg.ready_timeout_s
        while time.monotonic() < deadline and not self.stopping.is_set():
            if not child.alive():
                code = child.proc.returncode if child.proc else None
                self._fail(child, f"the Zenoh router exited with code {code} "
                           f"before it accepted connections on port {port}")
                return False
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port),
                                                                        timeout=0.5):
                return True
            time.sleep(0.1)
        if not self.stopping.is_set():
            self._fail(child, f"the Zenoh router did not accept connections on port {port} "
                       f"within {self.cfg.ready_timeout_s:g} s")
        return False

    def _healthy(self, child: Child) -> bool:
        """Whether ``child`` itself answers ``/healthz`` (the body's pid is the child's); a
        reconstruction worker: whether the dispatcher's ``GET /workers`` lists its pid."""
        import urllib.request  # here: `aoi3d --help` imports this module

        if child.proc is None or not child.alive():  # alive() is False without a process
            return False
        worker = child.name not in DEFAULT_PORTS
        port = self.cfg.port("dispatcher" if worker else child.name)
        url = f"http://127.0.0.1:{port}/{'workers' if worker else 'healthz'}"
        try:
            with urllib.request.urlopen(url, timeout=1) as resp:
                body = json.loads(resp.read() or b"{}")
                if worker:
                    pids = {w.get("pid") for w in body.get("workers", [])}
                    return resp.status == 200 and child.proc.pid in pids
                return resp.status == 200 and body.get("pid") == child.proc.pid
        except (OSError, ValueError, AttributeError):
            return False

    def _wait_ready(self, children: list[Child] | None = None) -> bool:
        """Wait until every service (of ``children``) answers /healthz from its own process;
        False (and :attr:`failure` set, unless stopping) when one exits more than
        :data:`STARTUP_RESTARTS` times first, or the start-up timeout passes."""
        pending = {c.name: c for c in (children or self.children[1:])}
        router = self.children[0]
        deadline = time.monotonic() + self.cfg.ready_timeout_s
        while pending and time.monotonic() < deadline and not self.stopping.is_set():
            for name, child in sorted(pending.items()):
                if self._healthy(child):
                    assert child.proc is not None  # _healthy() is False without a process
                    del pending[name]
                    log.info("%s is up (pid %d)", name, child.proc.pid)
            self._restart_dead()
            for child in (router, *pending.values()):
                if len(child.exits) > (0 if child is router else STARTUP_RESTARTS):
                    codes = ", ".join(str(c) for c in child.exits)
                    self._fail(child, f"{child.name} exited (code {codes}) before it was "
                               "healthy")
                    return False
            if pending:
                self.stopping.wait(0.2)
        if pending and not self.stopping.is_set():
            names = ", ".join(sorted(pending))
            self._fail(next(iter(sorted(pending.items())))[1],
                       f"not healthy after {self.cfg.ready_timeout_s:g} s: {names}")
            return False
        return not self.stopping.is_set()

    def _write_state(self, stopped: bool = False) -> None:
        """``<run log folder>/up.json``: the pids and ports of this run (for operators and
        tests)."""
        if self.log_dir is None:
            return
        state = {
            "run_id": self.cfg.run_id,
            "started_utc": self.started.isoformat(),
            "stopped": stopped,
            "failure": self.failure,
            "children": {c.name: {"pid": c.proc.pid if c.proc else None,
                                  "restarts": c.restarts,
                                  "port": (self.cfg.zenoh_port if c.name == "router"
                                           else self.cfg.port(c.name)
                                           if c.name in DEFAULT_PORTS else None),
                                  "log": str(c.log_path)}
                         for c in self.children},
        }
        write_atomic(self.log_dir / "up.json", json.dumps(state, indent=2))
