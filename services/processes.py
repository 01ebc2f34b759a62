"""The processes of an ``aoi3d up`` run: the service list and ports, the run's configuration
(:class:`UpConfig`), one supervised child process (:class:`Child`) and the helpers the
supervisor (:mod:`services.supervisor`) uses — ports in use, the run's log folder, a log's
last line. Standard library only, like the supervisor (``aoi3d --help`` imports it)."""

from __future__ import annotations

import contextlib
import os
import re
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from aoi3d.atomic import atomic_path  # stdlib only, as this module
from aoi3d.sites import site_names as site_names  # re-exported (the supervisor, tests)
from services.kit.ports import SERVICE_PORTS, ZENOH_PORT  # the one table of ports

SERVICES = tuple(SERVICE_PORTS)
"""The services ``aoi3d up`` runs, in start order (``python -m services.<name>``)."""
DEFAULT_PORTS = SERVICE_PORTS
"""Each service's REST port before ``--port-offset`` (:data:`services.kit.ports.SERVICE_PORTS`)."""
WORKER = "recon"
"""The reconstruction workers (``python -m services.recon``): ``--workers`` of them, named
``recon-1`` … in the logs; no REST port each — a worker is ready when the dispatcher's ``GET
/workers`` lists its pid (it joined the pool by its Zenoh liveliness token)."""
LATEST = "latest"
"""The link in ``log_dir`` to the newest run's log folder."""
STARTUP_RESTARTS = 1
"""How often a service that exits before it is healthy is restarted before start-up fails."""
STEADY_S = 60.0
"""A child that ran this long before it exited is restarted after 1 s; one that keeps
exiting sooner waits 1, 2, 4 … 30 s (a crash loop does not spin, one crash does not wait)."""


@dataclass
class UpConfig:
    dataset: Path = Path("data/turbine-rotor")
    run_id: str = "default"
    time_scale: float = 0.1
    cameras: int = 18
    sites: int = 1
    """Sites of the run: ``site1`` … ``site<S>``, each with its own cameras (the scene at its
    own phase), channel, policy and quality; one shared pool of workers."""
    workers: int = 1
    """Reconstruction workers of the pool (``python -m services.recon``, 1 torch thread each
    unless ``AOI3D_RECON_TORCH_THREADS`` says otherwise)."""
    zenoh_port: int = ZENOH_PORT
    port_offset: int = 0
    log_dir: Path = Path("runs/logs")
    """The parent of the runs' log folders (each run writes to a folder of its own)."""
    duration_s: float | None = None
    ready_timeout_s: float = 120.0
    grace_s: float = 10.0
    echo: bool = True
    extra_env: dict[str, str] = field(default_factory=dict)
    rig: Path | None = None
    """A rig file of real cameras (ROS 2 over Zenoh): the camera slot runs the ingest service
    (``python -m services.ingest``, on the camera's port) instead of the emulator, and every
    process gets ``AOI3D_RIG``."""
    delay: str | None = None
    """The network emulator's delay spec (``AOI3D_NETWORK_DELAY``). With a rig: emulated
    delay on top of the real link (the ingest publishes through the network service); without
    it (None) the network steps aside."""
    commands: dict[str, list[str]] = field(default_factory=dict)
    """argv of a child by name (``router`` or a service) instead of ``python -m services.<name>``
    (tests run stand-ins)."""

    def module(self, service: str) -> str:
        """The module a service slot runs: the camera slot is the ingest service with a rig."""
        return "services.ingest" if service == "camera" and self.rig is not None \
            else f"services.{service}"

    def port(self, service: str) -> int:
        return DEFAULT_PORTS[service] + self.port_offset

    def ports(self) -> dict[str, int]:
        """Every port the run listens on: ``router`` (Zenoh) and each service's REST port."""
        return {"router": self.zenoh_port, **{name: self.port(name) for name in SERVICES}}


def auto_workers(cores: int | None = None) -> int:
    """The pool ``--workers auto`` starts on a machine of ``cores`` CPUs (default: this
    process's, ``os.sched_getaffinity``): every core up to 2, one core left to the rest of the
    pipeline beyond. A worker runs one torch thread and keeps its core busy while it has a
    job; the router, the five services and the console took 0.2 cores together at time scale
    0.1 (results/scale.json, ``cores_by_process``), about 3× that at 0.3. On 2 cores
    two workers beside them rendered 3.29 of 3.33 decisions/s where one rendered 2.01, so
    both cores go to workers there; from 3 cores on, a core is kept for the services, whose
    share grows with the renders they score and dispatch (docs/performance.md, "Streaming
    reconstruction")."""
    if cores is None:
        try:
            cores = len(os.sched_getaffinity(0))
        except (AttributeError, OSError):
            cores = os.cpu_count() or 1
    return max(1, cores if cores <= 2 else cores - 1)


def port_in_use(port: int, host: str = "127.0.0.1") -> bool:
    """Whether a server could not listen on ``host:port`` now. Binds with ``SO_REUSEADDR``, as
    uvicorn and Zenoh do, so a port held only by connections closing (TIME_WAIT) is free."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError:
            return True
    return False


def taken_ports(cfg: UpConfig) -> list[tuple[str, int]]:
    """``(name, port)`` of each port of the run (:meth:`UpConfig.ports`) already in use."""
    return [(name, port) for name, port in cfg.ports().items() if port_in_use(port)]


def run_log_dir(log_dir: Path, run_id: str, started: datetime) -> Path:
    """A new folder ``<log_dir>/<run id>-<YYYYmmddTHHMMSSZ>`` (``-2``, ``-3``… appended if a
    run of the same id started in the same second), and ``<log_dir>/latest`` pointing at it."""
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", run_id) or "run"
    stem = f"{safe}-{started.astimezone(UTC):%Y%m%dT%H%M%SZ}"
    log_dir.mkdir(parents=True, exist_ok=True)
    for n in range(1, 1000):
        folder = log_dir / (stem if n == 1 else f"{stem}-{n}")
        try:
            folder.mkdir()
            break
        except FileExistsError:
            continue
    else:
        raise FileExistsError(f"no free log folder name for {stem} in {log_dir}")
    with atomic_path(log_dir / LATEST) as tmp:
        os.symlink(folder.name, tmp)  # relative: the logs folder can move
    return folder


def last_line(path: Path, limit: int = 4096) -> str:
    """The last non-empty line of a log file (read from its last ``limit`` bytes)."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - limit))
            lines = f.read().decode("utf-8", "replace").splitlines()
    except OSError:
        return ""
    return next((line.strip() for line in reversed(lines) if line.strip()), "")


@dataclass
class Child:
    name: str
    argv: list[str]
    env: dict[str, str]
    log_path: Path
    proc: subprocess.Popen | None = None
    restarts: int = 0
    next_start: float = 0.0
    exits: list[int | None] = field(default_factory=list)
    """Exit codes of this child so far (the supervisor records each exit it sees)."""
    started_s: float = 0.0
    """Monotonic time of its latest start."""
    quick_exits: int = 0
    """Exits in a row that came within :data:`STEADY_S` of a start (the restart backoff
    doubles with each; a child that ran longer restarts after 1 s again)."""
    _pump: threading.Thread | None = None

    def start(self, echo: bool) -> None:
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self.started_s = time.monotonic()
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
