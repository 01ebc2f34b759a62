"""``aoi3d live``'s side of the wire: the REST client of a running pipeline
(:class:`Pipeline`), one policy's measurement window (:func:`measure_policy`), and a
sweep's hold on the pipeline (:class:`LiveSession`: the whole sweep's windows, the channel put
back, a pipeline of its own started and stopped with ``--up``). What the windows mean is
:mod:`aoi3d.live`'s.

:mod:`aoi3d_cli.live` imports this module inside its command (httpx stays out of
``aoi3d --help``).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import httpx
import typer
from rich.console import Console
from rich.markup import escape

from aoi3d.live import Measurement, render_latency_s
from aoi3d_cli.common import control_headers
from services.kit.ports import SERVICE_PORTS, rest_port


class LiveError(RuntimeError):
    """The pipeline did not answer as expected; the message says what and where."""


@dataclass
class Pipeline:
    """The REST endpoints of a running pipeline."""

    url_base: str = "http://127.0.0.1"
    port_offset: int = 0
    timeout_s: float = 30.0
    site: str | None = None
    """The site measured (``/sites/<site>/…``); None: the run's first site (today's paths)."""
    client: Any = field(default=None, repr=False)

    RUN_LEVEL = frozenset({("dispatcher", "/reset"), ("dispatcher", "/backend"),
                           ("dispatcher", "/carry"), ("dispatcher", "/workers")})
    """Paths that are the run's, not a site's (the pool and its settings)."""

    def __post_init__(self) -> None:
        self.client = httpx.Client(timeout=self.timeout_s, headers=control_headers())

    def url(self, service: str, path: str) -> str:
        if self.site and (service, path) not in self.RUN_LEVEL and not path.startswith("/ready"):
            path = f"/sites/{self.site}{path}"
        return f"{self.url_base.rstrip('/')}:{rest_port(service, self.port_offset)}{path}"

    def call(self, method: str, service: str, path: str, **kw: Any) -> Any:
        url = self.url(service, path)
        try:
            resp = self.client.request(method, url, **kw)
        except httpx.HTTPError as err:
            raise LiveError(f"{method} {url}: {err!r} (is the pipeline up? `aoi3d up`, or "
                            f"pass --up)") from None
        if resp.status_code >= 400:
            raise LiveError(f"{method} {url} answered {resp.status_code}: {resp.text[:300]}")
        return resp.json()

    def ready(self) -> bool:
        try:
            return all(self.client.get(self.url(s, "/readyz")).status_code == 200
                       for s in SERVICE_PORTS)
        except httpx.HTTPError:
            return False

    def latest_render(self) -> tuple[bytes, int | None]:
        """The dispatcher's latest render (PNG) and the decision it represents."""
        try:
            resp = self.client.get(self.url("dispatcher", "/render.png"))
        except httpx.HTTPError:
            return b"", None
        if resp.status_code != 200:
            return b"", None
        return resp.content, int(resp.headers.get("x-decision-id", "0"))

    def close(self) -> None:
        self.client.close()


def wait(what: str, check: Callable[[], Any], timeout_s: float, every_s: float = 0.25) -> Any:
    """``check()``'s first true answer (a :class:`LiveError` counts as not yet), polled every
    ``every_s``; :class:`LiveError` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    last: Any = None
    while time.monotonic() < deadline:
        try:
            last = check()
        except LiveError as err:
            last = err
        if last and not isinstance(last, Exception):
            return last
        time.sleep(every_s)
    raise LiveError(f"timed out after {timeout_s:g} s waiting for {what} (last: {last!r})")


def measure_policy(pipe: Pipeline, policy: dict[str, Any], spec: str, *, settle_s: float,
                   measure_s: float, reset: bool, repeat: int, sample_every_s: float = 0.5
                   ) -> Measurement:
    """Set ``policy``, (reset,) settle, and collect one measurement window."""
    pipe.call("PUT", "scheduler", "/policy", json=policy)
    wait(f"a decision under {spec}",
         lambda: pipe.call("GET", "scheduler", "/decision").get("policy") == spec,
         pipe.timeout_s)
    if reset:
        pipe.call("POST", "dispatcher", "/reset")
    time.sleep(settle_s)
    first = pipe.call("GET", "scheduler", "/decision")
    if first["policy"] != spec:
        raise LiveError(f"the scheduler's policy changed under the sweep: {first['policy']!r} "
                        f"while measuring {spec!r}")
    decisions = [first]
    started = time.monotonic()
    while time.monotonic() - started < measure_s:
        time.sleep(sample_every_s)
        decisions.append(pipe.call("GET", "scheduler", "/decision"))
    last = decisions[-1]
    if last["policy"] != spec:
        raise LiveError(f"the scheduler's policy changed under the sweep: {last['policy']!r} "
                        f"while measuring {spec!r}")
    # the renders of the window's decisions come a render's compute later: wait for them
    lo, hi = first["decision_id"], last["decision_id"]
    png, png_decision = pipe.latest_render()
    time.sleep(render_latency_s(pipe.call("GET", "dispatcher", "/status")))
    history = pipe.call("GET", "metrics", "/quality", params={"limit": 1000})["history"]
    qualities = [q for q in history if lo <= q["decision_id"] <= hi]
    return Measurement(policy=spec, repeat=repeat, first_decision=lo, last_decision=hi,
                       wall_s=time.monotonic() - started, qualities=qualities,
                       decisions=[d for d in decisions if d["policy"] == spec],
                       render_png=png, render_decision=png_decision)


@dataclass
class SweepWindows:
    """What :meth:`LiveSession.measure` collected: the windows, the dispatcher's status before
    and after, and the channel (as the network service reported it, with its changes)."""

    measurements: list[Measurement]
    status0: dict[str, Any]
    status1: dict[str, Any]
    channel: dict[str, Any]


class LiveSession:
    """A sweep's hold on a pipeline: on leaving the ``with`` block the channel it set is put
    back (unless it started the pipeline itself), the client closed, and a pipeline it
    started (:meth:`start_pipeline`) stopped."""

    def __init__(self, pipe: Pipeline, console: Console) -> None:
        self.pipe = pipe
        self.console = console
        self.proc: subprocess.Popen | None = None
        self.previous_delay: str | None = None

    def __enter__(self) -> LiveSession:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.previous_delay is not None and self.proc is None:
            try:
                self.pipe.call("PUT", "network", "/channel", json={"delay": self.previous_delay})
            except LiveError as err:
                self.console.print(f"[yellow]could not put the channel back:[/] "
                                   f"{escape(str(err))}")
        self.pipe.close()
        if self.proc is not None:
            stop_pipeline(self.proc)

    def start_pipeline(self, zenoh_port: int, time_scale: float, run_id: str,
                       extra: Sequence[str]) -> None:
        """``aoi3d up`` in a session of its own, quiet, on the client's ports; wait until every
        service is ready."""
        cmd = [sys.executable, "-c", "from aoi3d_cli import main; main()", "up", "--quiet",
               "--port-offset", str(self.pipe.port_offset), "--zenoh-port", str(zenoh_port),
               "--time-scale", str(time_scale), "--run-id", run_id, *extra]
        self.console.print(f"starting the pipeline: aoi3d {escape(' '.join(cmd[3:]))}")
        self.proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                     start_new_session=True)
        wait("every service to be ready", self.pipe.ready, 10 * self.pipe.timeout_s,
             every_s=1.0)

    def measure(self, specs: Sequence[str], bodies: dict[str, dict[str, Any]],
                canon: dict[str, str], *, delay: str | None, settle_s: float, measure_s: float,
                repeats: int, reset_each: bool) -> SweepWindows:
        """Set the channel (``delay``, when it differs from the one in force), then measure
        each policy of ``specs`` in turn, ``repeats`` passes, printing progress; a pipeline
        that does not answer ends the command (exit status 1)."""
        pipe, console = self.pipe, self.console
        try:
            status0 = pipe.call("GET", "dispatcher", "/status")
            channel = pipe.call("GET", "network", "/channel")
            if delay is not None and delay != channel["delay"]:
                self.previous_delay = channel["delay"]
                channel = pipe.call("PUT", "network", "/channel", json={"delay": delay})
                console.print(f"channel: {escape(delay)} (was {escape(self.previous_delay)})")
        except LiveError as err:
            console.print(f"[red]error:[/] {escape(str(err))}")
            raise typer.Exit(1) from None
        measurements: list[Measurement] = []
        total = repeats * len(specs)
        for rep in range(repeats):
            for i, spec in enumerate(specs):
                console.print(f"\\[{rep * len(specs) + i + 1}/{total}] {escape(canon[spec])}: "
                              f"settle {settle_s:g} s, measure {measure_s:g} s")
                try:
                    m = measure_policy(pipe, bodies[spec], canon[spec], settle_s=settle_s,
                                       measure_s=measure_s, reset=reset_each, repeat=rep)
                except LiveError as err:
                    console.print(f"[red]error:[/] {escape(str(err))}")
                    raise typer.Exit(1) from None
                measurements.append(m)
                console.print(f"    {len(m.qualities)} renders scored, decisions "
                              f"{m.first_decision}..{m.last_decision}")
        status1 = pipe.call("GET", "dispatcher", "/status")
        channel_end = pipe.call("GET", "network", "/channel")
        channel["changes"] = channel_end.get("changes", [])
        return SweepWindows(measurements, status0, status1, channel)


def stop_pipeline(proc: subprocess.Popen) -> None:
    """SIGTERM, then after a minute SIGKILL to the whole session."""
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
