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
until every open decision has ended (a decision held by a killed trainer ends ``expired``
after ``AOI3D_METRICS_LEDGER_OPEN_S``, 30 s here), and the run is judged:

- per fault, ``recovery_s``: from the fault's end (the kill, or the SIGCONT) to the next
  Quality of every site;
- ``stalls_over_15s``: gaps between consecutive Qualities of a site (from the first fault to
  the end of the faults) longer than 15 s;
- ``unaccounted``: decisions made minus decisions the ledgers counted (scored, skipped, lost
  with a reason, or open): 0 when every decision is accounted for;
- ``all_up_at_end``: every service answers /healthz and every worker is in the pool.

    python bench/chaos.py --minutes 10 --json     # docs/measurements.md's run
    python bench/chaos.py --minutes 2             # a quick look

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
import threading
import time
import uuid
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services.kit.keys import Keys  # noqa: E402
from services.kit.pb import aoi3d_pb2 as pb  # noqa: E402
from services.kit.settings import CommonSettings, zenoh_config  # noqa: E402
from services.supervisor import DEFAULT_PORTS  # noqa: E402

OFFSET, ZENOH = 5000, 9567  # REST 13101…13106: apart from make up, soak and the tests
LEDGER_OPEN_S = 30.0
JOB_TIMEOUT_S = 20.0
STALL_S = 15.0


class Tap:
    """Every Quality (site, monotonic time) and the highest decision id per (site,
    incarnation) of the run, from a Zenoh session of its own."""

    def __init__(self, run_id: str) -> None:
        import zenoh

        keys = Keys(run_id, "*")
        self.session = zenoh.open(zenoh_config(CommonSettings(
            zenoh_connect=[f"tcp/127.0.0.1:{ZENOH}"])))
        self.lock = threading.Lock()
        self.qualities: list[tuple[str, float]] = []
        self.made: dict[tuple[str, int], int] = {}
        self.subs = [self.session.declare_subscriber(keys.quality, self._on_quality),
                     self.session.declare_subscriber(keys.decision, self._on_decision)]

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

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()
        self.session.close()


def url(service: str, path: str) -> str:
    return f"http://127.0.0.1:{DEFAULT_PORTS[service] + OFFSET}{path}"


def children(log_dir: Path) -> dict[str, int]:
    state = json.loads((log_dir / "latest" / "up.json").read_text())
    return {name: c["pid"] for name, c in state["children"].items() if c["pid"]}


def wait(what: str, cond, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            if cond():
                return
        except (OSError, ValueError, KeyError, httpx.HTTPError):
            pass
        time.sleep(0.5)
    raise SystemExit(f"chaos: {what} not within {timeout_s:.0f} s")


def all_up(http: httpx.Client, log_dir: Path, workers: int) -> dict[str, bool]:
    up = {}
    for service in DEFAULT_PORTS:
        try:
            up[service] = http.get(url(service, "/healthz")).status_code == 200
        except httpx.HTTPError:
            up[service] = False
    try:
        with socket.create_connection(("127.0.0.1", ZENOH), timeout=2):
            up["router"] = True
    except OSError:
        up["router"] = False
    try:
        pool = http.get(url("trainer", "/workers")).json()["workers"]
        up["workers"] = len(pool) == workers
    except (httpx.HTTPError, ValueError, KeyError):
        up["workers"] = False
    pids = children(log_dir)
    up["processes"] = all(Path(f"/proc/{pid}").exists() for pid in pids.values())
    return up


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--sites", type=int, default=1)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--every", type=float, nargs=2, default=(20.0, 40.0),
                        metavar=("MIN_S", "MAX_S"), help="seconds between faults (uniform)")
    parser.add_argument("--stop-s", type=float, default=10.0)
    parser.add_argument("--time-scale", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--out", type=Path, default=ROOT / "bench/results/chaos.json")
    args = parser.parse_args()
    rng = random.Random(args.seed)
    run_id = f"chaos{uuid.uuid4().hex[:6]}"
    log_dir = ROOT / "runs" / "bench-chaos"
    env = {**os.environ, "AOI3D_METRICS_LEDGER_OPEN_S": str(LEDGER_OPEN_S),
           "AOI3D_TRAINER_JOB_TIMEOUT_S": str(JOB_TIMEOUT_S)}
    up = subprocess.Popen(
        [sys.executable, "-m", "aoi3d", "up", "--run-id", run_id, "--port-offset", str(OFFSET),
         "--zenoh-port", str(ZENOH), "--log-dir", str(log_dir), "--quiet", "--sites",
         str(args.sites), "--workers", str(args.workers), "--time-scale",
         str(args.time_scale)], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
        stderr=subprocess.STDOUT, start_new_session=True)
    http = httpx.Client(timeout=30.0)
    tap = None
    try:
        wait("the metrics service", lambda: http.get(url("metrics", "/healthz")).is_success,
             300)
        sites = http.get(url("metrics", "/sites")).json()["sites"]
        tap = Tap(run_id)
        wait("a Quality of every site", lambda: all(tap.quality_times(s) for s in sites), 300)
        faults: list[dict] = []
        t_start = time.monotonic()
        end = t_start + args.minutes * 60.0
        while True:
            pause = rng.uniform(*args.every)
            if time.monotonic() + pause >= end:
                time.sleep(max(0.0, end - time.monotonic()))
                break
            time.sleep(pause)
            pids = children(log_dir)
            kind = rng.choice(["kill", "kill", "stop", "router_restart"])
            target = "router" if kind == "router_restart" else rng.choice(sorted(pids))
            pid = pids[target]
            t0 = time.monotonic()
            try:
                if kind == "stop":
                    os.kill(pid, signal.SIGSTOP)
                    time.sleep(args.stop_s)
                    os.kill(pid, signal.SIGCONT)
                else:
                    os.kill(pid, signal.SIGKILL if kind == "kill" else signal.SIGTERM)
            except ProcessLookupError:
                kind += " (already gone)"
            faults.append({"t_s": round(t0 - t_start, 1), "kind": kind, "target": target,
                           "pid": pid, "end": time.monotonic()})
        t_faults_end = time.monotonic()
        time.sleep(5.0)  # the last fault's recovery, if it has one
        for f in faults:
            end_t = f.pop("end")
            nexts = [next((t for t in tap.quality_times(s) if t > end_t), None) for s in sites]
            f["recovery_s"] = None if None in nexts else round(max(nexts) - end_t, 1)
        stalls, max_gap = 0, 0.0
        for s in sites:
            times = [t_start] + [t for t in tap.quality_times(s) if t_start < t < t_faults_end]
            times.append(t_faults_end)
            gaps = [b - a for a, b in itertools.pairwise(times)]
            stalls += sum(g > STALL_S for g in gaps)
            max_gap = max([max_gap, *gaps])

        # the books: no new decision while they are read, every open one given its end
        sched = children(log_dir)["scheduler"]
        os.kill(sched, signal.SIGSTOP)
        try:
            time.sleep(3.0)
            wait("every open decision ended", lambda: all(
                http.get(url("metrics", f"/sites/{s}/ledger")).json()["open"] == 0
                for s in sites), LEDGER_OPEN_S * 3 + 30)
            ledgers = {s: http.get(url("metrics", f"/sites/{s}/ledger")).json() for s in sites}
            with tap.lock:
                made = dict(tap.made)
        finally:
            os.kill(sched, signal.SIGCONT)
        decisions = sum(made.values())
        counted = sum(led["decisions"] for led in ledgers.values())
        wait("every process up", lambda: all(all_up(http, log_dir, args.workers).values()), 90)
        up_state = all_up(http, log_dir, args.workers)
    finally:
        if tap is not None:
            tap.close()
        up.send_signal(signal.SIGTERM)
        try:
            up.wait(timeout=90)
        except subprocess.TimeoutExpired:
            os.killpg(up.pid, signal.SIGKILL)
    recoveries = [f["recovery_s"] for f in faults if f["recovery_s"] is not None]
    result = {
        "command": "python bench/chaos.py " + " ".join(sys.argv[1:]),
        "minutes": args.minutes, "sites": args.sites, "workers": args.workers,
        "faults": faults, "max_recovery_s": max(recoveries, default=None),
        "decisions": decisions, "ledger_decisions": counted, "unaccounted": decisions - counted,
        "stalls_over_15s": stalls, "max_quality_gap_s": round(max_gap, 1),
        "ledger": {s: {k: led[k] for k in ("decisions", "scored", "skipped", "lost",
                                           "lost_total", "open", "after_close")}
                   for s, led in ledgers.items()},
        "all_up_at_end": all(up_state.values()), "up": up_state,
        "load_1min_at_end": round(os.getloadavg()[0], 2),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        for f in faults:
            print(f"{f['t_s']:7.1f} s  {f['kind']:24s} {f['target']:10s} "
                  f"next Quality after {f['recovery_s']} s")
        print(f"decisions {decisions}, counted {counted}, unaccounted {decisions - counted}; "
              f"stalls over {STALL_S:g} s: {stalls} (longest gap {max_gap:.1f} s); "
              f"all up at the end: {result['all_up_at_end']}")
    ok = result["unaccounted"] == 0 and stalls == 0 and result["all_up_at_end"]
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
