"""Two sites, one pool (issue 22, part 2): `aoi3d up --sites 2 --workers 2` on real processes
and real Zenoh on 127.0.0.1. Quality flows for both sites, each site's policy changes on its
own, and the console shows both."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import uuid
from pathlib import Path

import pytest

from services.kit.keys import Keys
from services.kit.pb import aoi3d_pb2 as pb
from tests.support.pipeline import HTTP, SCALE, assert_clean_exit, handle, stop_pipeline, wait_for
from tests.support.ports import block

pytestmark = [pytest.mark.integration, pytest.mark.slow]

PIPE = handle("sites")
_PORTS = block("sites")
PORT_OFFSET = _PORTS.rest_offset
ZENOH_PORT = _PORTS.zenoh
SITES = ("site1", "site2")



class SiteTap:
    """Decisions and Quality of every site, by site (a Zenoh client on the run's keys)."""

    def __init__(self, run_id: str) -> None:
        import zenoh

        from services.kit.settings import CommonSettings, zenoh_config

        self.session = zenoh.open(zenoh_config(CommonSettings(
            zenoh_connect=[f"tcp/127.0.0.1:{ZENOH_PORT}"])))
        self.lock = threading.Lock()
        self.decisions: dict[str, list[pb.Decision]] = {s: [] for s in SITES}
        self.quality: dict[str, list[pb.Quality]] = {s: [] for s in SITES}
        every = Keys(run_id, "*")
        self.subs = [self.session.declare_subscriber(every.decision, self._on_decision),
                     self.session.declare_subscriber(every.quality, self._on_quality)]

    def _on_decision(self, sample) -> None:
        with self.lock:
            self.decisions[Keys.site_of(str(sample.key_expr))].append(
                pb.Decision.FromString(sample.payload.to_bytes()))

    def _on_quality(self, sample) -> None:
        with self.lock:
            self.quality[Keys.site_of(str(sample.key_expr))].append(
                pb.Quality.FromString(sample.payload.to_bytes()))

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()
        self.session.close()


def test_two_sites_share_the_pool_and_change_policy_on_their_own(
        small_dataset: Path, tmp_path: Path) -> None:
    run_id = f"sites{uuid.uuid4().hex[:8]}"
    cmd = ["--dataset", str(small_dataset), "--run-id", run_id, "--log-dir",
           str(tmp_path / "logs"), "--time-scale", "0.1", "--sites", "2", "--workers", "2"]
    env = dict(os.environ, AOI3D_DISPATCHER_RENDER_STEPS="30")
    up = PIPE.start(cmd, env=env, output=subprocess.PIPE)
    tap = None
    try:
        wait_for("two workers", lambda: len(
            HTTP.get(PIPE.url("dispatcher", "/workers")).json()["workers"]) == 2, timeout_s=120)
        tap = SiteTap(run_id)
        for site in SITES:
            wait_for(f"Quality of {site}", lambda s=site: len(tap.quality[s]) >= 2,
                     timeout_s=120)
        with tap.lock:
            assert all(q.site == site for site in SITES for q in tap.quality[site])
        assert HTTP.get(PIPE.url("scheduler", "/sites")).json() == {"sites": list(SITES)}

        # site2 selects nothing from now on; site1 keeps its policy
        r = HTTP.put(PIPE.url("scheduler", "/sites/site2/policy"),
                     json={"kind": "mat", "mat_ms": 0})
        assert r.status_code == 200, r.text
        spec2 = r.json()["spec"]
        spec1 = HTTP.get(PIPE.url("scheduler", "/policy")).json()["spec"]
        assert spec1 != spec2
        with tap.lock:
            n1, n2 = len(tap.decisions["site1"]), len(tap.decisions["site2"])
        wait_for("decisions of both after the change", lambda: len(
            tap.decisions["site1"]) > n1 + 5 and len(tap.decisions["site2"]) > n2 + 5)
        with tap.lock:
            after1, after2 = tap.decisions["site1"][n1 + 1:], tap.decisions["site2"][n2 + 1:]
        assert {d.policy for d in after2} == {spec2} and all(not d.selected for d in after2)
        assert {d.policy for d in after1} == {spec1} and any(d.selected for d in after1)
        assert HTTP.get(PIPE.url("scheduler", "/sites/site1/policy")).json()["spec"] == spec1
        assert HTTP.get(PIPE.url("scheduler", "/sites/nowhere/policy")).status_code == 404

        # per-site REST and series, one pool
        for site in SITES:
            assert HTTP.get(PIPE.url("metrics", f"/sites/{site}/quality")).json()["history"]
            assert HTTP.get(PIPE.url("dispatcher", f"/sites/{site}/status")).json()["site"] == site
        by_site = HTTP.get(PIPE.url("dispatcher", "/workers")).json()["by_site"]
        assert all(by_site[s].get("rendered", 0) >= 1 for s in SITES), by_site
        text = HTTP.get(PIPE.url("metrics", "/metrics")).text
        assert all(f'site="{s}"' in text for s in SITES)

        # the console shows both sites: the list, and each site's own state
        assert HTTP.get(PIPE.url("console", "/config")).json()["sites"] == list(SITES)
        for site in SITES:
            state = wait_for(f"the console's {site}", lambda s=site: (st := HTTP.get(
                PIPE.url("console", f"/sites/{s}/state")).json())["quality"] and st, timeout_s=60)
            assert state["policy"]["spec"] == (spec1 if site == "site1" else spec2)

        # `aoi3d live sweep --site site2` measures site2 while site1 goes on
        sweep = subprocess.run(
            [sys.executable, "-m", "aoi3d_cli", "live", "sweep", "--site", "site2", "--policies",
             "mat:70,all", "--settle-s", "1", "--measure-s", str(8 * SCALE), "--repeats", "1",
             "--port-offset", str(PORT_OFFSET), "--no-sim", "--json",
             "--out", str(tmp_path / "sweep"), "--dataset", str(small_dataset),
             "--timeout-s", str(30 * SCALE)],
            capture_output=True, text=True, timeout=300 * SCALE)
        assert sweep.returncode == 0, sweep.stderr[-3000:]
        doc = json.loads(sweep.stdout)
        assert doc["settings"]["site"] == "site2"
        assert [r["policy"] for r in doc["results"]] == ["mat:70", "all"]
        assert all(r["n"] >= 1 for r in doc["results"]), doc["results"]
        assert HTTP.get(PIPE.url("scheduler", "/policy")).json()["spec"] == spec1  # untouched
    finally:
        if tap is not None:
            tap.close()
        out = stop_pipeline(up)
    assert_clean_exit(up, out, run_id)
