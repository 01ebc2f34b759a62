"""Run the whole pipeline locally: a Zenoh router plus the five services as supervised processes.

Used by ``aoi3d up`` (and so ``make up``). Each child runs in its own process group with
the run's shared environment (run id, clock epoch and scale, endpoints, ports). A child that
exits unexpectedly is restarted with a back-off and the restart is logged. On SIGINT/SIGTERM
(or after ``duration_s``) every child gets SIGTERM, then SIGKILL after a grace period, so no
process is left behind. Child output goes to ``<log_dir>/<name>.log`` and, prefixed, to the
console.
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
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

log = logging.getLogger("aoi3d.up")

SERVICES = ("camera", "network", "scheduler", "trainer", "metrics")
DEFAULT_PORTS = {"camera": 8101, "network": 8102, "scheduler": 8103, "trainer": 8104,
                 "metrics": 8105}


@dataclass
class UpConfig:
    dataset: Path = Path("data/turbine")
    run_id: str = "default"
    time_scale: float = 0.1
    cameras: int = 18
    zenoh_port: int = 7447
    port_offset: int = 0
    log_dir: Path = Path("runs/logs")
    duration_s: float | None = None
    ready_timeout_s: float = 60.0
    grace_s: float = 10.0
    echo: bool = True
    extra_env: dict[str, str] = field(default_factory=dict)

    def port(self, service: str) -> int:
        return DEFAULT_PORTS[service] + self.port_offset


@dataclass
class Child:
    name: str
    argv: list[str]
    env: dict[str, str]
    log_path: Path
    proc: subprocess.Popen | None = None
    restarts: int = 0
    next_start: float = 0.0
    _pump: threading.Thread | None = None

    def start(self, echo: bool) -> None:
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self.proc = subprocess.Popen(
            self.argv, env=self.env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL, start_new_session=True, bufsize=1, text=True,
            errors="replace")
        self._pump = threading.Thread(target=self._copy_output, args=(self.proc, echo),
                                      name=f"log-{self.name}", daemon=True)
        self._pump.start()

    def _copy_output(self, proc: subprocess.Popen, echo: bool) -> None:
        with open(self.log_path, "a", encoding="utf-8") as out:
            for line in proc.stdout:  # type: ignore[union-attr]
                out.write(line)
                out.flush()
                if echo:
                    sys.stdout.write(f"[{self.name:9s}] {line}")
                    sys.stdout.flush()

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def signal_group(self, sig: int) -> None:
        if self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, sig)


class Supervisor:
    def __init__(self, cfg: UpConfig, on_ready: Callable[[Supervisor], None] | None = None):
        self.cfg = cfg
        self.on_ready = on_ready
        self.stopping = threading.Event()
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
            "AOI3D_DATASET": str(Path(cfg.dataset).resolve()),
            "AOI3D_ZENOH_MODE": "client",
            "AOI3D_ZENOH_CONNECT": endpoint,
            "AOI3D_ROUTER_LISTEN": endpoint,
        })
        for name in SERVICES:
            base[f"AOI3D_{name.upper()}_PORT"] = str(cfg.port(name))
            base[f"AOI3D_{name.upper()}_HOST"] = "127.0.0.1"
        base.update(cfg.extra_env)
        names = ("router", *SERVICES)
        return [Child(name, [sys.executable, "-m", f"services.{name}"], base,
                      cfg.log_dir / f"{name}.log") for name in names]

    # ------------------------------------------------------------ lifecycle
    def run(self) -> int:
        """Start everything, supervise until stopped; returns the exit code."""
        previous = {sig: signal.signal(sig, self._on_signal)
                    for sig in (signal.SIGINT, signal.SIGTERM)}
        try:
            self._write_state()
            router, services = self.children[0], self.children[1:]
            router.start(self.cfg.echo)
            if not self._wait_tcp(self.cfg.zenoh_port, router):
                log.error("the Zenoh router did not come up; see %s", router.log_path)
                return 1
            for child in services:
                child.start(self.cfg.echo)
            self._write_state()
            if not self._wait_ready():
                return 1
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

    def _restart_dead(self) -> None:
        now = time.monotonic()
        for child in self.children:
            if child.alive() or self.stopping.is_set():
                continue
            if child.next_start == 0.0:
                code = child.proc.returncode if child.proc else None
                backoff = min(30.0, 1.0 * 2 ** min(child.restarts, 5))
                child.next_start = now + backoff
                log.warning("service %s exited with code %s; restarting in %.0f s "
                            "(restart #%d, log: %s)", child.name, code, backoff,
                            child.restarts + 1, child.log_path)
            elif now >= child.next_start:
                child.restarts += 1
                child.next_start = 0.0
                child.start(self.cfg.echo)
                self._write_state()
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
        deadline = time.monotonic() + self.cfg.ready_timeout_s
        while time.monotonic() < deadline and not self.stopping.is_set():
            if not child.alive():
                return False
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port),
                                                                        timeout=0.5):
                return True
            time.sleep(0.1)
        return False

    def _wait_ready(self) -> bool:
        """Wait until every service answers /healthz."""
        pending = {c.name for c in self.children[1:]}
        deadline = time.monotonic() + self.cfg.ready_timeout_s
        while pending and time.monotonic() < deadline and not self.stopping.is_set():
            for name in sorted(pending):
                with contextlib.suppress(OSError):
                    url = f"http://127.0.0.1:{self.cfg.port(name)}/healthz"
                    with urllib.request.urlopen(url, timeout=1) as resp:
                        if resp.status == 200:
                            pending.discard(name)
            self._restart_dead()
            time.sleep(0.2)
        if pending and not self.stopping.is_set():
            log.error("services not healthy after %.0f s: %s (logs in %s)",
                      self.cfg.ready_timeout_s, ", ".join(sorted(pending)), self.cfg.log_dir)
            return False
        return not self.stopping.is_set()

    def _write_state(self, stopped: bool = False) -> None:
        """``<log_dir>/up.json``: the pids and ports of this run (for operators and tests)."""
        state = {
            "run_id": self.cfg.run_id,
            "stopped": stopped,
            "children": {c.name: {"pid": c.proc.pid if c.proc else None,
                                  "restarts": c.restarts,
                                  "port": (self.cfg.zenoh_port if c.name == "router"
                                           else self.cfg.port(c.name)),
                                  "log": str(c.log_path)}
                         for c in self.children},
        }
        self.cfg.log_dir.mkdir(parents=True, exist_ok=True)
        tmp = self.cfg.log_dir / "up.json.tmp"
        tmp.write_text(json.dumps(state, indent=2))
        tmp.replace(self.cfg.log_dir / "up.json")
