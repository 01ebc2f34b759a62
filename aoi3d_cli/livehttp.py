"""``aoi3d live``'s side of the wire, on the one pipeline handle
(:class:`aoi3d_cli.pipeline.Pipeline`): one policy's measurement window
(:func:`measure_policy`), and a sweep's hold on the pipeline (:class:`LiveSession`: the whole
sweep's windows, the channel put back, a pipeline of its own started and stopped with
``--up``). What the windows mean is :mod:`aoi3d.live`'s.

:mod:`aoi3d_cli.live` imports this module inside its command (httpx stays out of
``aoi3d --help``).
"""

from __future__ import annotations

import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import typer
from rich.console import Console
from rich.markup import escape

from aoi3d.live import Measurement, render_latency_s
from aoi3d_cli.pipeline import Pipeline, PipelineError, wait_until
from services.kit.ports import PortBlock

LiveError = PipelineError
"""The pipeline did not answer as expected (:class:`aoi3d_cli.pipeline.PipelineError`)."""
wait = wait_until


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

    @classmethod
    def on(cls, console: Console, host: str, port_offset: int, zenoh_port: int,
           site: str | None, timeout_s: float) -> LiveSession:
        """A session on the pipeline at ``host`` on these ports (``site``: the one measured)."""
        return cls(Pipeline(PortBlock(port_offset, zenoh_port), host=host, site=site,
                            timeout_s=timeout_s), console)

    def __enter__(self) -> LiveSession:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.previous_delay is not None and self.proc is None:
            try:
                self.pipe.call("PUT", "network", "/channel", json={"delay": self.previous_delay})
            except LiveError as err:
                self.console.print(f"[yellow]could not put the channel back:[/] "
                                   f"{escape(str(err))}")
        self.pipe.stop()  # the pipeline it started, if any
        self.pipe.close()

    def start_pipeline(self, time_scale: float, run_id: str, extra: Sequence[str]) -> None:
        """``aoi3d up`` in a session of its own, quiet, on the client's ports; wait until every
        service is ready."""
        args = ["--time-scale", str(time_scale), *extra]
        self.console.print(f"starting the pipeline: aoi3d up "
                           f"{escape(' '.join([*self.pipe.block.up_args(), *args]))}")
        self.pipe.start(args, run_id=run_id)
        self.proc = self.pipe.proc
        self.pipe.wait_ready(10 * self.pipe.timeout_s)

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
