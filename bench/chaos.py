"""Chaos: faults at random on a live pipeline while Quality is collected; the ledger at the end.

Starts ``aoi3d up`` (its own ports and run id; ``--sites``, ``--workers``), then every 20–40 s
(``--every``) injects one fault, chosen at random:

- ``kill``: SIGKILL of any process — the router, a service or a reconstruction worker
  (``aoi3d up`` restarts it);
- ``stop``: SIGSTOP of any process for ``--stop-s`` (10 s), then SIGCONT;
- ``router_restart``: SIGTERM of the Zenoh router (a clean restart; every session reconnects).

A Zenoh session of its own records every Quality (per site) and every Decision (the highest id
of each scheduler incarnation of each site: the decisions made). After ``--minutes`` the
faults stop; the scheduler is frozen (SIGSTOP) so no decision is made while the books are
read, the decision ledgers (the metrics service's ``GET /sites/<site>/ledger``) are given
until every open decision has ended (a decision held by a killed dispatcher ends ``expired``
after ``AOI3D_METRICS_LEDGER_OPEN_S``, 30 s here), and the run is judged:

- per fault, ``recovery_s``: from the fault's end (the kill, or the SIGCONT) to the next
  Quality of every site;
- ``stalls_over_15s``: gaps between consecutive Qualities of a site (from the first fault to
  the end of the faults) longer than 15 s;
- ``unaccounted``: decisions made minus decisions the ledgers counted (scored, skipped, lost
  with a reason, or open): 0 when every decision is accounted for;
- ``all_up_at_end``: every service answers /healthz and every worker is in the pool.

    python -m bench.chaos --minutes 10 --json     # docs/measurements.md's run
    python -m bench.chaos --minutes 2             # a quick look

``--target multihost`` runs the same judge on compose.multihost.yaml (three "hosts" on one
Docker engine: the edge, and worker hosts a and b, joined router to router over mutual TLS; a
project and ports of its own, secrets made in a temporary folder). Its faults, every 20–40 s:

- ``cut``: ``docker network disconnect`` of a worker host's router from the mesh for
  ``--cut-s`` (15 s: past Zenoh's 10 s lease, so the host's workers leave the pool), then
  ``connect`` (they rejoin by themselves);
- ``router_restart``: ``docker restart`` of the edge router or a worker host's router;
- ``edge_restart``: ``docker restart`` of an edge service (camera, network, scheduler,
  trainer, metrics);
- ``worker_kill``: SIGKILL of a worker's process inside its container (a crash: Docker's
  restart policy brings it back; ``docker kill`` would count as a stop by hand).

An override file (``multihost_override``) gives the metrics service a state folder on a volume,
so a restarted one keeps its ledger (as ``aoi3d up`` does), and the ledger's open timeout.
The books are read with the scheduler's container paused; "all up" is every container running
and healthy and both worker hosts in the pool, judged once the paused scheduler has had its
health checks again (up to 90 s: they fail while it is paused). Needs the images (``make
images``) and an engine (``eval "$(deploy/engine.sh start)"``):

    python -m bench.chaos --target multihost --minutes 10 --json

Exit status 1 when ``unaccounted`` or ``stalls_over_15s`` is not 0 or a process is down.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import random
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import httpx

from aoi3d_cli.pipeline import Pipeline
from bench import common
from bench.ports import BENCH_BLOCKS
from services.kit.keys import Keys
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.ports import SERVICE_PORTS
from services.kit.settings import CommonSettings

ROOT = common.ROOT
PORTS = BENCH_BLOCKS["chaos"]  # apart from make up, soak and the tests (bench/ports.py)
PIPE = Pipeline(PORTS, timeout_s=60.0)
"""This bench's pipeline (:class:`aoi3d_cli.pipeline.Pipeline`): its URLs."""
ZENOH = PORTS.zenoh
LEDGER_OPEN_S = 30.0
JOB_TIMEOUT_S = 20.0
STALL_S = 15.0


class Tap(common.Tap):
    """Every Quality (site, monotonic time) and the highest decision id per (site,
    incarnation) of the run, from a Zenoh session of its own."""

    def __init__(self, run_id: str, common: CommonSettings | None = None) -> None:
        keys = Keys(run_id, "*")
        self.qualities: list[tuple[str, float]] = []
        self.made: dict[tuple[str, int], int] = {}
        super().__init__(PORTS, {keys.quality: self._on_quality,
                                 keys.decision: self._on_decision}, common)

    def _on_quality(self, sample) -> None:
        msg = pb.Quality.FromString(sample.payload.to_bytes())
        with self.lock:
            self.qualities.append((msg.site, time.monotonic()))

    def _on_decision(self, sample) -> None:
        msg = pb.Decision.FromString(sample.payload.to_bytes())
        key = (Keys.site_of(str(sample.key_expr)), msg.incarnation)
        with self.lock:
            self.made[key] = max(self.made.get(key, 0), msg.decision_id)

    def quality_times(self, site: str) -> list[float]:
        with self.lock:
            return [t for s, t in self.qualities if s == site]


def children(log_dir: Path) -> dict[str, int]:
    state = json.loads((log_dir / "latest" / "up.json").read_text())
    return {name: c["pid"] for name, c in state["children"].items() if c["pid"]}


def wait(what: str, cond, timeout_s: float) -> None:
    common.wait_until(f"chaos: {what}", cond, timeout_s)


def settle(state: Callable[[], dict[str, bool]], timeout_s: float) -> dict[str, bool]:
    """``state()`` once all of it is true, or as it is after ``timeout_s``."""
    end = time.monotonic() + timeout_s
    while True:
        now = state()
        if all(now.values()) or time.monotonic() >= end:
            return now
        time.sleep(1.0)


def all_up(http: httpx.Client, log_dir: Path, workers: int) -> dict[str, bool]:
    up = {}
    for service in SERVICE_PORTS:
        try:
            up[service] = http.get(PIPE.url(service, "/healthz")).status_code == 200
        except httpx.HTTPError:
            up[service] = False
    try:
        with socket.create_connection(("127.0.0.1", ZENOH), timeout=2):
            up["router"] = True
    except OSError:
        up["router"] = False
    try:
        pool = http.get(PIPE.url("dispatcher", "/workers")).json()["workers"]
        up["workers"] = len(pool) == workers
    except (httpx.HTTPError, ValueError, KeyError):
        up["workers"] = False
    pids = children(log_dir)
    up["processes"] = all(Path(f"/proc/{pid}").exists() for pid in pids.values())
    return up


def judge(tap: Tap, sites: list[str], faults: list[dict], t_start: float,
          t_faults_end: float) -> tuple[int, float]:
    """Each fault's ``recovery_s`` (from its end, popped from the fault, to the next Quality of
    every site), and the stalls: (gaps over STALL_S, the longest gap)."""
    for f in faults:
        end_t = f.pop("end")
        nexts = [next((t for t in tap.quality_times(s) if t > end_t), None) for s in sites]
        found = [t for t in nexts if t is not None]
        f["recovery_s"] = None if len(found) < len(nexts) else round(max(found) - end_t, 1)
    stalls, max_gap = 0, 0.0
    for s in sites:
        times = [t_start] + [t for t in tap.quality_times(s) if t_start < t < t_faults_end]
        times.append(t_faults_end)
        gaps = [b - a for a, b in itertools.pairwise(times)]
        stalls += sum(g > STALL_S for g in gaps)
        max_gap = max([max_gap, *gaps])
    return stalls, max_gap


def fault_loop(args: argparse.Namespace, rng: random.Random, inject: Callable[[], dict]
               ) -> tuple[list[dict], float, float]:
    """For ``--minutes``: a pause drawn from ``--every``, then one fault (``inject`` does it and
    says what it did). Returns the faults (each with its start ``t_s`` and its ``end``), the
    start and the end of the faults, after 5 s for the last one's recovery."""
    faults: list[dict] = []
    t_start = time.monotonic()
    end = t_start + args.minutes * 60.0
    while True:
        pause = rng.uniform(*args.every)
        if time.monotonic() + pause >= end:
            time.sleep(max(0.0, end - time.monotonic()))
            break
        time.sleep(pause)
        t0 = time.monotonic()
        fault = inject()
        faults.append({"t_s": round(t0 - t_start, 1), **fault, "end": time.monotonic()})
    t_faults_end = time.monotonic()
    time.sleep(5.0)  # the last fault's recovery, if it has one
    return faults, t_start, t_faults_end


def run_up(args: argparse.Namespace, rng: random.Random) -> dict:
    """The faults on `aoi3d up` (its processes on this machine)."""
    run_id = f"chaos{uuid.uuid4().hex[:6]}"
    log_dir = ROOT / "runs" / "bench-chaos"
    env = {**os.environ, "AOI3D_METRICS_LEDGER_OPEN_S": str(LEDGER_OPEN_S),
           "AOI3D_DISPATCHER_JOB_TIMEOUT_S": str(JOB_TIMEOUT_S)}
    up = PIPE.start([
        "--sites", str(args.sites), "--workers", str(args.workers),
        "--time-scale", str(args.time_scale)], run_id=run_id, log_dir=log_dir, env=env,
        cwd=ROOT)
    http = httpx.Client(timeout=30.0)
    tap = None
    try:
        wait("the metrics service", lambda: http.get(PIPE.url("metrics", "/healthz")).is_success,
             300)
        sites = http.get(PIPE.url("metrics", "/sites")).json()["sites"]
        tap = Tap(run_id)
        wait("a Quality of every site", lambda: all(tap.quality_times(s) for s in sites), 300)

        def inject() -> dict:
            pids = children(log_dir)
            kind = rng.choice(["kill", "kill", "stop", "router_restart"])
            target = "router" if kind == "router_restart" else rng.choice(sorted(pids))
            pid = pids[target]
            try:
                if kind == "stop":
                    os.kill(pid, signal.SIGSTOP)
                    time.sleep(args.stop_s)
                    os.kill(pid, signal.SIGCONT)
                else:
                    os.kill(pid, signal.SIGKILL if kind == "kill" else signal.SIGTERM)
            except ProcessLookupError:
                kind += " (already gone)"
            return {"kind": kind, "target": target, "pid": pid}

        faults, t_start, t_faults_end = fault_loop(args, rng, inject)
        stalls, max_gap = judge(tap, sites, faults, t_start, t_faults_end)

        # the books: no new decision while they are read, every open one given its end
        sched = children(log_dir)["scheduler"]
        os.kill(sched, signal.SIGSTOP)
        try:
            time.sleep(3.0)
            ledgers = read_ledgers(http, lambda s, path: PIPE.url("metrics", path), sites)
            with tap.lock:
                made = dict(tap.made)
        finally:
            os.kill(sched, signal.SIGCONT)
        wait("every process up", lambda: all(all_up(http, log_dir, args.workers).values()), 90)
        up_state = all_up(http, log_dir, args.workers)
    finally:
        if tap is not None:
            tap.close()
        up.stop(90)
    return outcome(args, faults, made, ledgers, stalls, max_gap, up_state)


def read_ledgers(http: httpx.Client, ledger_url, sites: list[str]) -> dict[str, dict]:
    """Every site's ledger once no decision is open (the caller has frozen the scheduler)."""
    wait("every open decision ended", lambda: all(
        http.get(ledger_url(s, f"/sites/{s}/ledger")).json()["open"] == 0
        for s in sites), LEDGER_OPEN_S * 3 + 30)
    return {s: http.get(ledger_url(s, f"/sites/{s}/ledger")).json() for s in sites}


def outcome(args: argparse.Namespace, faults: list[dict], made: dict, ledgers: dict,
            stalls: int, max_gap: float, up_state: dict[str, bool]) -> dict:
    decisions = sum(made.values())
    counted = sum(led["decisions"] for led in ledgers.values())
    recoveries = [f["recovery_s"] for f in faults if f["recovery_s"] is not None]
    return {
        "command": "python bench/chaos.py " + " ".join(sys.argv[1:]),
        "target": args.target, "minutes": args.minutes, "sites": args.sites,
        "workers": args.workers,
        "faults": faults, "max_recovery_s": max(recoveries, default=None),
        "decisions": decisions, "ledger_decisions": counted, "unaccounted": decisions - counted,
        "stalls_over_15s": stalls, "max_quality_gap_s": round(max_gap, 1),
        "ledger": {s: {k: led[k] for k in ("decisions", "scored", "skipped", "lost",
                                           "lost_total", "open", "after_close")}
                   for s, led in ledgers.items()},
        "all_up_at_end": all(up_state.values()), "up": up_state,
        "load_1min_at_end": round(os.getloadavg()[0], 2),
    }


# ------------------------------------------------------------------ the multi-host target
MH_FILE = ROOT / "compose.multihost.yaml"
_MH = BENCH_BLOCKS["chaos_multihost"]
MH_PORTS = {"ZENOH": _MH.zenoh, **{s.upper(): _MH.rest(s) for s in ("scheduler", "dispatcher",
                                                                      "metrics")}}
"""The multi-host stack's published ports (compose.multihost.yaml's AOI3D_PORT_<NAME>), from the
one table: apart from `aoi3d up` above, compose-test and soak."""
MH_HOSTS = {"worker-a": ("router-a", "recon-a"), "worker-b": ("router-b", "recon-b")}
MH_EDGE = ("camera", "network", "scheduler", "dispatcher", "metrics")
MH_ROUTERS = ("router-edge", "router-a", "router-b")
MH_FAULTS = ("cut", "cut", "router_restart", "edge_restart", "worker_kill", "worker_kill")
"""The draw: a worker host cut off twice as often as a restart, as often as a worker crash."""

KILL_WORKER = (
    "import os, signal\n"
    "for pid in os.listdir('/proc'):\n"
    "    if pid.isdigit() and int(pid) != os.getpid():\n"
    "        try:\n"
    "            cmd = open(f'/proc/{pid}/cmdline', 'rb').read()\n"
    "        except OSError:\n"
    "            continue\n"
    "        if b'services.recon' in cmd:\n"
    "            os.kill(int(pid), signal.SIGKILL)\n")
"""Run in a worker's container: SIGKILL of its worker process (not of the init, docker-init,
which then exits with it, and the restart policy starts the container again)."""


def multihost_override() -> dict:
    """The compose override the chaos run adds: the metrics service keeps its ledger on a
    volume across restarts (AOI3D_METRICS_STATE_DIR, as `aoi3d up` sets it) and gives an open
    decision LEDGER_OPEN_S to end."""
    return {
        "services": {"metrics": {
            "environment": {"AOI3D_METRICS_STATE_DIR": "/app/runs/state",
                            "AOI3D_METRICS_LEDGER_OPEN_S": str(LEDGER_OPEN_S)},
            "volumes": ["chaos-state:/app/runs"]}},
        "volumes": {"chaos-state": {}},
    }


def fault_plan(rng: random.Random) -> tuple[str, str]:
    """One fault: (kind, the compose service it hits)."""
    kind = rng.choice(MH_FAULTS)
    if kind == "cut":
        return kind, rng.choice(sorted(h[0] for h in MH_HOSTS.values()))
    if kind == "router_restart":
        return kind, rng.choice(MH_ROUTERS)
    if kind == "edge_restart":
        return kind, rng.choice(MH_EDGE)
    return kind, rng.choice(sorted(h[1] for h in MH_HOSTS.values()))


class MultiHost:
    """`docker compose` on compose.multihost.yaml plus the override, as a project of its own."""

    def __init__(self, project: str, secrets: Path, override: Path) -> None:
        self.project = project
        self.secrets = secrets
        self.override = override
        self.env = {**os.environ, "AOI3D_SECRETS_DIR": str(secrets), "AOI3D_RUN_ID": project,
                    **{f"AOI3D_PORT_{k}": str(v) for k, v in MH_PORTS.items()}}

    def with_time_scale(self, time_scale: float) -> MultiHost:
        self.env["AOI3D_TIME_SCALE"] = str(time_scale)
        return self

    def run(self, *argv: str, timeout_s: float = 180.0,
            check: bool = True) -> subprocess.CompletedProcess[str]:
        proc = subprocess.run(argv, env=self.env, capture_output=True, text=True,
                              timeout=timeout_s)
        if check and proc.returncode != 0:
            raise SystemExit(f"chaos: {' '.join(argv)} exited {proc.returncode}: "
                             f"{proc.stderr[-2000:]}")
        return proc

    def compose(self, *args: str, timeout_s: float = 180.0, check: bool = True):
        return self.run("docker", "compose", "-f", str(MH_FILE), "-f", str(self.override),
                        "-p", self.project, *args, timeout_s=timeout_s, check=check)

    def container(self, service: str) -> str:
        return self.compose("ps", "-aq", service).stdout.strip()

    def url(self, service: str, path: str) -> str:
        return f"http://127.0.0.1:{MH_PORTS[service.upper()]}{path}"

    def common(self) -> CommonSettings:
        s = self.secrets
        return CommonSettings(
            zenoh_connect=[f"tls/127.0.0.1:{MH_PORTS['ZENOH']}"], zenoh_mode="client",
            zenoh_user="aoi3d", zenoh_password_file=s / "zenoh_password",
            zenoh_tls_root_ca=s / "zenoh_tls_ca", zenoh_tls_cert=s / "zenoh_tls_client_cert",
            zenoh_tls_key=s / "zenoh_tls_client_key", zenoh_tls_mtls=True)

    def inject(self, kind: str, target: str, cut_s: float) -> None:
        if kind == "cut":
            router = self.container(target)
            self.run("docker", "network", "disconnect", f"{self.project}_mesh", router)
            try:
                time.sleep(cut_s)
            finally:
                self.run("docker", "network", "connect", f"{self.project}_mesh", router)
        elif kind in ("router_restart", "edge_restart"):
            self.run("docker", "restart", "-t", "10", self.container(target))
        else:
            self.run("docker", "exec", self.container(target), "python", "-c", KILL_WORKER)

    def all_up(self, http: httpx.Client) -> dict[str, bool]:
        up = {}
        rows = [json.loads(line) for line in
                self.compose("ps", "-a", "--format", "json").stdout.splitlines() if line]
        for row in rows:
            if row["Service"] == "dataset":
                continue
            up[row["Service"]] = row["State"] == "running" and row.get("Health") in (
                "", "healthy", None)
        try:
            hosts = {w["host"] for w in http.get(self.url("dispatcher", "/workers")).json()[
                "workers"]}
            up["workers"] = hosts == set(MH_HOSTS)
        except (httpx.HTTPError, ValueError, KeyError):
            up["workers"] = False
        return up


def run_multihost(args: argparse.Namespace, rng: random.Random) -> dict:
    """The faults on compose.multihost.yaml's three hosts."""
    import tempfile

    import yaml

    project = f"aoi3d-chaos-{uuid.uuid4().hex[:6]}"
    tmp = Path(tempfile.mkdtemp(prefix="aoi3d-chaos-"))
    subprocess.run([str(ROOT / "deploy" / "secrets.sh"), str(tmp / "secrets")], check=True,
                   capture_output=True)
    override = tmp / "chaos.override.yaml"
    override.write_text(yaml.safe_dump(multihost_override()))
    mh = MultiHost(project, tmp / "secrets", override).with_time_scale(args.time_scale)
    mh.run("docker", "info", timeout_s=30)
    http = httpx.Client(timeout=30.0)
    tap = None
    paused = False
    try:
        mh.compose("up", "-d", "--no-build", "--wait", "--wait-timeout", "600", timeout_s=660)
        wait("both worker hosts in the pool", lambda: {w["host"] for w in http.get(
            mh.url("dispatcher", "/workers")).json()["workers"]} == set(MH_HOSTS), 300)
        sites = http.get(mh.url("metrics", "/sites")).json()["sites"]
        tap = Tap(project, mh.common())
        wait("a Quality of every site", lambda: all(tap.quality_times(s) for s in sites), 300)

        def inject() -> dict:
            kind, target = fault_plan(rng)
            mh.inject(kind, target, args.cut_s)
            return {"kind": kind, "target": target}

        faults, t_start, t_faults_end = fault_loop(args, rng, inject)
        stalls, max_gap = judge(tap, sites, faults, t_start, t_faults_end)
        wait("every container up, both hosts in the pool",
             lambda: all(mh.all_up(http).values()), 180)
        mh.run("docker", "pause", mh.container("scheduler"))
        paused = True
        time.sleep(3.0)
        ledgers = read_ledgers(http, lambda s, path: mh.url("metrics", path), sites)
        with tap.lock:
            made = dict(tap.made)
        mh.run("docker", "unpause", mh.container("scheduler"))
        paused = False
        # Docker's health checks fail while the container is paused (three in a row mark it
        # unhealthy, and the pause lasts until every open decision has ended, up to
        # LEDGER_OPEN_S): it is judged once it has had its checks again, within 90 s.
        up_state = settle(lambda: mh.all_up(http), 90.0)
    finally:
        if tap is not None:
            tap.close()
        if paused:
            mh.run("docker", "unpause", mh.container("scheduler"), check=False)
        mh.compose("down", "-v", "--remove-orphans", timeout_s=300, check=False)
    return outcome(args, faults, made, ledgers, stalls, max_gap, up_state)


def parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--target", choices=("up", "multihost"), default="up",
                        help="aoi3d up on this machine, or compose.multihost.yaml on Docker")
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--sites", type=int, default=1)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--every", type=float, nargs=2, default=(20.0, 40.0),
                        metavar=("MIN_S", "MAX_S"), help="seconds between faults (uniform)")
    parser.add_argument("--stop-s", type=float, default=10.0)
    parser.add_argument("--cut-s", type=float, default=15.0,
                        help="multihost: seconds a worker host stays cut off the mesh")
    parser.add_argument("--time-scale", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    common.add_json_option(parser, help="print one JSON object")
    parser.add_argument("--out", type=Path, default=None,
                        help="default results/chaos.json (multihost: chaos-multihost.json)")
    return parser


def run(args: argparse.Namespace) -> dict:
    """The faults on ``args.target`` (``parser()``'s options); writes ``args.out`` (or the
    target's default under results/) and returns the result document."""
    out = args.out or common.RESULTS / (
        "chaos.json" if args.target == "up" else "chaos-multihost.json")
    rng = random.Random(args.seed)
    result = (run_up if args.target == "up" else run_multihost)(args, rng)
    common.write_json(out, result, indent=1)
    return result


def main(argv: list[str] | None = None) -> int:
    ap = parser()
    args = ap.parse_args(argv)
    if args.target == "multihost" and (args.sites, args.workers) != (1, 2):
        ap.error("the multi-host stack has one site and a worker on each of two hosts")
    result = run(args)
    if args.json:
        common.print_json(result, indent=1)
    else:
        for f in result["faults"]:
            print(f"{f['t_s']:7.1f} s  {f['kind']:24s} {f['target']:12s} "
                  f"next Quality after {f['recovery_s']} s")
        print(f"decisions {result['decisions']}, counted {result['ledger_decisions']}, "
              f"unaccounted {result['unaccounted']}; stalls over {STALL_S:g} s: "
              f"{result['stalls_over_15s']} (longest gap {result['max_quality_gap_s']} s); "
              f"longest recovery {result['max_recovery_s']} s; "
              f"all up at the end: {result['all_up_at_end']}")
    ok = result["unaccounted"] == 0 and result["stalls_over_15s"] == 0 and \
        result["all_up_at_end"]
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
