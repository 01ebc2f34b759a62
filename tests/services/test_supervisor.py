"""The supervisor behind `aoi3d up`: a log folder per run, start-up that fails loudly.

The children are stand-ins (a few lines of stdlib Python each: a TCP listener for the router,
an HTTP server answering /healthz for a service), so the supervisor's own logic — log folders,
health checks against its own pids, a crash during start-up — is tested with real processes
without starting Zenoh, FastAPI or torch. They take ports of their own (from this process's
pid). Every wait scales with AOI3D_TEST_TIMEOUT_SCALE.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from services.supervisor import (
    DEFAULT_PORTS,
    LATEST,
    SERVICES,
    Supervisor,
    UpConfig,
    port_in_use,
    run_log_dir,
    taken_ports,
)
from tests.support.ports import block
from tests.support.timeouts import timeout_scale

SCALE = timeout_scale()
_PORTS = block("supervisor")
PORT_OFFSET = _PORTS.rest_offset
ZENOH_PORT = _PORTS.zenoh

ROUTER = """
import os, socket, time
port = int(os.environ["AOI3D_ROUTER_LISTEN"].rsplit(":", 1)[1])
s = socket.socket(); s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.bind(("127.0.0.1", port)); s.listen()
print("router listening", flush=True)
while True:
    s.accept()
"""

SERVICE = """
import json, os, sys
from http.server import BaseHTTPRequestHandler, HTTPServer
name = sys.argv[1]
if os.environ.get("STANDIN_CRASH") == name:
    print("something before", flush=True)
    print(f"{name}: /data/x/frames/cam03/0007.png: frame file is missing", flush=True)
    sys.exit(2)
port = int(os.environ[f"AOI3D_{name.upper()}_PORT"])
class H(BaseHTTPRequestHandler):
    def do_GET(self):
        body = json.dumps({"status": "ok", "pid": os.getpid()}).encode()
        self.send_response(200); self.end_headers(); self.wfile.write(body)
    def log_message(self, *args):
        pass
print(f"{name} serving", flush=True)
HTTPServer(("127.0.0.1", port), H).serve_forever()
"""


def standins() -> dict[str, list[str]]:
    commands = {"router": [sys.executable, "-c", ROUTER]}
    for name in SERVICES:
        commands[name] = [sys.executable, "-c", SERVICE, name]
    return commands


def config(tmp_path: Path, **changes) -> UpConfig:
    base = {"dataset": tmp_path, "run_id": "sup", "zenoh_port": ZENOH_PORT,
            "port_offset": PORT_OFFSET, "log_dir": tmp_path / "logs", "duration_s": 0.5,
            "ready_timeout_s": 30 * SCALE, "grace_s": 5 * SCALE, "echo": False,
            "commands": standins(), "workers": 0}
    return UpConfig(**{**base, **changes})


def assert_all_gone(sup: Supervisor) -> None:
    for child in sup.children:
        assert child.proc is None or child.proc.poll() is not None, f"{child.name} left running"


def test_ports_come_from_the_service_list() -> None:
    cfg = UpConfig(port_offset=7, zenoh_port=9000)
    assert cfg.ports() == {"router": 9000, **{s: DEFAULT_PORTS[s] + 7 for s in SERVICES}}


def test_taken_ports_sees_a_listening_socket() -> None:
    cfg = UpConfig(port_offset=PORT_OFFSET, zenoh_port=ZENOH_PORT)
    assert taken_ports(cfg) == []
    with socket.socket() as s:
        s.bind(("127.0.0.1", cfg.port("dispatcher")))
        s.listen()
        assert port_in_use(cfg.port("dispatcher"))
        assert taken_ports(cfg) == [("dispatcher", cfg.port("dispatcher"))]
    with socket.socket() as s:  # a server on all interfaces blocks 127.0.0.1 too
        s.bind(("0.0.0.0", ZENOH_PORT))
        s.listen()
        assert taken_ports(cfg) == [("router", ZENOH_PORT)]


def test_each_run_logs_to_its_own_folder_and_latest_points_at_the_newest(tmp_path: Path) -> None:
    ready = []
    first = Supervisor(config(tmp_path), on_ready=ready.append)
    assert first.run() == 0 and ready == [first] and first.failure is None
    second = Supervisor(config(tmp_path))
    assert second.run() == 0
    assert_all_gone(first)
    assert_all_gone(second)
    logs = tmp_path / "logs"
    assert first.log_dir != second.log_dir
    assert first.log_dir.parent == second.log_dir.parent == logs
    for sup in (first, second):
        assert sup.log_dir.name.startswith("sup-") and sup.log_dir.name[4:12].isdigit()
        state = json.loads((sup.log_dir / "up.json").read_text())
        assert state["stopped"] and state["run_id"] == "sup"
        assert set(state["children"]) == {"router", *SERVICES}
        for name in SERVICES:  # each run's own log, not overwritten by the other
            assert "serving" in (sup.log_dir / f"{name}.log").read_text()
        assert "router listening" in (sup.log_dir / "router.log").read_text()
    assert (logs / LATEST).is_symlink() and (logs / LATEST).resolve() == second.log_dir.resolve()
    assert sorted(p.name for p in logs.iterdir()) == sorted(
        [LATEST, first.log_dir.name, second.log_dir.name])


def test_run_log_dir_never_reuses_a_folder(tmp_path: Path) -> None:
    from datetime import UTC, datetime

    when = datetime(2026, 11, 23, 21, 0, 5, tzinfo=UTC)
    a = run_log_dir(tmp_path, "a/b c", when)
    b = run_log_dir(tmp_path, "a/b c", when)
    assert a.name == "a_b_c-20261123T210005Z" and b.name == "a_b_c-20261123T210005Z-2"
    assert (tmp_path / LATEST).resolve() == b.resolve()


def test_a_service_that_crashes_during_start_up_fails_it(tmp_path: Path) -> None:
    ready = []
    cfg = config(tmp_path, duration_s=1.0, extra_env={"STANDIN_CRASH": "camera"})
    sup = Supervisor(cfg, on_ready=ready.append)
    started = time.monotonic()
    assert sup.run() == 1
    assert time.monotonic() - started < cfg.ready_timeout_s  # not the timeout: the crash
    assert ready == []  # no "pipeline up" table
    assert sup.failure is not None and "camera exited (code 2, 2)" in sup.failure
    assert "frame file is missing" in sup.failure  # its last log line
    assert str(sup.log_dir / "camera.log") in sup.failure
    assert "\n" not in sup.failure
    assert_all_gone(sup)
    state = json.loads((sup.log_dir / "up.json").read_text())
    assert state["failure"] == sup.failure and state["children"]["camera"]["restarts"] == 1


class _Healthz(BaseHTTPRequestHandler):
    def do_GET(self) -> None:  # another process's healthy answer
        body = json.dumps({"status": "ok", "pid": os.getpid()}).encode()
        self.send_response(200)
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args) -> None:
        pass


def test_another_process_answering_healthz_is_not_this_pipeline(tmp_path: Path) -> None:
    """The old failure: another pipeline on the ports answered /healthz and `up` said "up"."""
    name = "metrics"
    commands = standins()
    commands[name] = [sys.executable, "-c", "import time; time.sleep(600)"]  # never serves
    cfg = config(tmp_path, duration_s=1.0, commands=commands, ready_timeout_s=3 * SCALE)
    server = ThreadingHTTPServer(("127.0.0.1", cfg.port(name)), _Healthz)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        ready = []
        sup = Supervisor(cfg, on_ready=ready.append)
        assert sup.run() == 1 and ready == []
        assert sup.failure is not None
        assert f"not healthy after {cfg.ready_timeout_s:g} s: {name}" in sup.failure
        assert_all_gone(sup)
    finally:
        server.shutdown()
        server.server_close()


def test_a_router_that_exits_fails_the_start_up(tmp_path: Path) -> None:
    commands = standins()
    commands["router"] = [sys.executable, "-c", "print('cannot listen: address in use'); "
                                                "raise SystemExit(3)"]
    sup = Supervisor(config(tmp_path, duration_s=1.0, commands=commands))
    assert sup.run() == 1
    assert "Zenoh router exited with code 3" in sup.failure
    assert "cannot listen: address in use" in sup.failure
    assert_all_gone(sup)


def test_the_restart_backoff_doubles_only_while_a_child_keeps_dying_young(tmp_path: Path,
                                                                        monkeypatch) -> None:
    """1 s after a child that ran for a while; 1, 2, 4 s … while it exits within STEADY_S of
    its start (a chaos run kills the same process many times: each waits 1 s, not 30)."""
    import services.supervisor as sv

    sup = Supervisor(config(tmp_path))
    child = sup.children[1]
    sup.children = [child]  # the others are never started
    child.start = lambda echo: None  # restarts are not the point here
    done = subprocess.Popen([sys.executable, "-c", "pass"])
    done.wait()
    child.proc = done
    now = [1000.0]
    monkeypatch.setattr(sv.time, "monotonic", lambda: now[0])
    waits = []
    for ran_s in (500.0, 5.0, 5.0, 5.0, 500.0):
        child.started_s = now[0] - ran_s
        sup._restart_dead()  # sees the exit: schedules the restart
        waits.append(child.next_start - now[0])
        now[0] = child.next_start
        sup._restart_dead()  # restarts it (start is a no-op; proc stays exited)
    assert waits == [1.0, 1.0, 2.0, 4.0, 1.0]
    assert child.restarts == 5 and len(child.exits) == 5


def test_auto_workers_takes_every_core_up_to_two_then_leaves_one() -> None:
    from services.supervisor import auto_workers

    assert [auto_workers(c) for c in (1, 2, 3, 4, 16)] == [1, 2, 2, 3, 15]
    assert auto_workers() >= 1  # this machine's


def test_up_refuses_a_worker_count_that_is_not_auto_or_0_to_64() -> None:
    from typer.testing import CliRunner

    from aoi3d_cli import app

    for bad in ("-1", "65", "many"):
        out = CliRunner().invoke(app, ["up", "--workers", bad])
        assert out.exit_code == 2 and "--workers" in out.output, out.output


def test_with_record_the_recorder_is_up_before_anything_else_starts(tmp_path: Path) -> None:
    """`aoi3d up --record` (the recorder's AOI3D_RECORDER_PATH): the recorder starts first and
    the other services only once it answers, so the recording holds the run from its first
    message (a stream replay needs each worker's first job)."""
    commands = standins()
    commands["recorder"] = [sys.executable, "-c", "import time; time.sleep(1.0)\n" + SERVICE,
                            "recorder"]
    cfg = config(tmp_path, commands=commands,
                 extra_env={"AOI3D_RECORDER_PATH": str(tmp_path / "run.mcap")})
    sup = Supervisor(cfg)
    assert sup.run() == 0, sup.failure
    started = {c.name: c.started_s for c in sup.children}
    assert min(t for name, t in started.items() if name not in ("router", "recorder")) \
        >= started["recorder"] + 1.0
    assert_all_gone(sup)
