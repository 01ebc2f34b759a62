"""The one pipeline handle (aoi3d_cli/pipeline.py): where a service is, a site's paths, the
/metrics reading, the waits and the stop of a real child process. Its live use is the
integration tests' (they start every pipeline through it)."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from aoi3d_cli.pipeline import Pipeline, PipelineError, parse_metrics, wait_until
from services.kit.ports import PortBlock


def test_urls_follow_the_block_the_site_and_the_published_ports() -> None:
    pipe = Pipeline(PortBlock(1000, 7547))
    assert pipe.url("dispatcher", "/status") == "http://127.0.0.1:9104/status"
    assert pipe.url("ingest", "/status") == "http://127.0.0.1:9101/status"  # the camera's
    assert pipe.url("scheduler", "/policy", site="site2") == \
        "http://127.0.0.1:9103/sites/site2/policy"
    site = Pipeline(PortBlock(), host="https://edge", site="site2")
    assert site.url("metrics", "/quality") == "https://edge:8105/sites/site2/quality"
    # the run's paths, the probes and /metrics are never a site's
    for service, path in (("dispatcher", "/workers"), ("metrics", "/readyz"),
                          ("metrics", "/metrics"), ("camera", "/healthz")):
        assert "/sites/" not in site.url(service, path), (service, path)
    stack = Pipeline(ports={"camera": 18101, "prometheus": 19090})
    assert stack.url("prometheus", "/-/ready") == "http://127.0.0.1:19090/-/ready"
    with pytest.raises(KeyError):
        stack.url("grafana")
    for p in (pipe, site, stack):
        p.close()


def test_metrics_are_read_per_series_and_summed_per_family() -> None:
    text = ('# HELP x_total x\n# TYPE x_total counter\nx_total{site="a"} 2.0\n'
            'x_total{site="b"} 3.0\ny 7\n\n')
    assert parse_metrics(text) == {'x_total{site="a"}': 2.0, 'x_total{site="b"}': 3.0,
                                   "x_total": 5.0, "y": 7.0}


def test_nothing_listening_is_a_pipeline_error_that_names_the_request() -> None:
    pipe = Pipeline(PortBlock(-8000, 1), timeout_s=2.0)  # REST ports 101…108: nothing there
    with pytest.raises(PipelineError, match=r"GET http://127\.0\.0\.1:104/status"):
        pipe.get("dispatcher", "/status")
    assert not pipe.ready()
    pipe.close()


def test_a_wait_tolerates_not_yet_and_times_out_naming_what() -> None:
    answers = iter([KeyError("x"), None, 0, {"ok": 1}])

    def check() -> object:
        a = next(answers)
        if isinstance(a, Exception):
            raise a
        return a

    assert wait_until("it", check, 5.0, every_s=0.0) == {"ok": 1}
    with pytest.raises(PipelineError, match="waiting for the impossible"):
        wait_until("the impossible", lambda: False, 0.2, every_s=0.05)


def test_stop_ends_a_child_and_returns_its_output() -> None:
    pipe = Pipeline(PortBlock())
    pipe.proc = subprocess.Popen(
        [sys.executable, "-c", "import signal, sys, time\n"
         "signal.signal(signal.SIGTERM, lambda *a: (print('bye', flush=True), sys.exit(0)))\n"
         "print('up', flush=True)\ntime.sleep(60)"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    time.sleep(0.5)
    with pytest.raises(PipelineError, match="exited"):  # a wait notices a dead pipeline
        dead = Pipeline(PortBlock())
        dead.proc = subprocess.Popen([sys.executable, "-c", "pass"])
        dead.proc.wait()
        dead.wait("never", lambda: False, 30.0)
    assert pipe.pid == pipe.proc.pid
    out = pipe.stop(30.0)
    assert "up" in out and pipe.proc.returncode == 0
    stubborn = Pipeline(PortBlock())
    stubborn.proc = subprocess.Popen(
        [sys.executable, "-c", "import signal, time\n"
         "signal.signal(signal.SIGTERM, signal.SIG_IGN)\nprint('x', flush=True)\n"
         "time.sleep(60)"], stdout=subprocess.PIPE, text=True, start_new_session=True)
    time.sleep(0.5)
    stubborn.stop(0.5)  # SIGTERM ignored: SIGKILL to its session
    assert stubborn.proc.returncode == -9
    with pytest.raises(PipelineError):
        _ = Pipeline(PortBlock()).pid
