"""One handle on a running pipeline from outside it: ``aoi3d live``, the benches and the live
tests drive ``aoi3d up`` through :class:`Pipeline` and nothing else.

- where: a service's URL on a block of ports (:class:`services.kit.ports.PortBlock`; the
  ingest answers on the camera emulator's port), under ``/sites/<site>`` for a site's paths;
- what: :meth:`Pipeline.get` / :meth:`~Pipeline.put` / :meth:`~Pipeline.post` (JSON, a
  :class:`PipelineError` that names the request when it fails), :meth:`~Pipeline.metrics`
  (a service's ``/metrics`` as numbers), :meth:`~Pipeline.ready` / :meth:`~Pipeline.wait_ready`;
- its process: :meth:`Pipeline.start` runs ``aoi3d up`` on the block's ports in a session of
  its own, :meth:`~Pipeline.stop` sends SIGTERM (``aoi3d up`` stops its children) and SIGKILL
  to the session after a timeout.

The client sends the control token the services expect when this shell has one
(:func:`aoi3d_cli.common.control_headers`) and never uses httpx's 5 s default timeout. Not
imported by ``aoi3d --help`` (httpx stays out of it).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import httpx

from aoi3d_cli.common import control_headers
from services.kit.ports import LOCALHOST, SERVICE_PORTS, UP, PortBlock

__all__ = ["RUN_LEVEL", "Pipeline", "PipelineError", "parse_metrics", "wait_until"]

RUN_LEVEL = frozenset({("dispatcher", "/reset"), ("dispatcher", "/backend"),
                       ("dispatcher", "/carry"), ("dispatcher", "/workers")})
"""Paths that are the run's, not a site's (the pool and its settings): never under
``/sites/<site>``; nor is a probe (``/healthz``, ``/readyz``) or ``/metrics``."""


class PipelineError(RuntimeError):
    """The pipeline did not answer as expected; the message says what and where."""


def parse_metrics(text: str) -> dict[str, float]:
    """A ``/metrics`` page as ``{series: value}``: each labelled sample under its full name,
    plus its metric's sum over labels under the bare name."""
    out: dict[str, float] = {}
    for line in text.splitlines():
        if line.startswith("#") or not line.strip():
            continue
        name, value = line.rsplit(" ", 1)
        out[name] = float(value)
        base = name.split("{")[0]
        if base != name:
            out[base] = out.get(base, 0.0) + float(value)
    return out


def wait_until(what: str, check: Callable[[], Any], timeout_s: float, every_s: float = 0.25,
               *, proc: subprocess.Popen | None = None) -> Any:
    """``check()``'s first true answer, polled every ``every_s`` (a :class:`PipelineError`, an
    HTTP error, a missing key, a bad value or a half-written file counts as not yet);
    :class:`PipelineError` after ``timeout_s``, or as soon as ``proc`` has exited."""
    deadline = time.monotonic() + timeout_s
    last: Any = None
    while True:
        try:
            last = check()
        except (PipelineError, httpx.HTTPError, KeyError, ValueError, OSError) as err:
            last = err
        if last and not isinstance(last, Exception):
            return last
        if proc is not None and proc.poll() is not None:
            raise PipelineError(f"{what}: the pipeline exited (exit status {proc.returncode})")
        if time.monotonic() > deadline:
            raise PipelineError(f"timed out after {timeout_s:g} s waiting for {what} "
                                f"(last: {last!r})")
        time.sleep(every_s)


class Pipeline:
    """A pipeline's REST services on ``block``'s ports at ``host`` (and, once
    :meth:`start` ran it, its ``aoi3d up`` process)."""

    def __init__(self, block: PortBlock = UP, *, host: str = LOCALHOST,
                 site: str | None = None, timeout_s: float = 30.0,
                 ports: Mapping[str, int] | None = None) -> None:
        """``host``: a host, or a scheme and host (``https://edge``). ``site``: the site whose
        paths :meth:`url` addresses by default (None: the run's first, the paths without
        ``/sites/``). ``ports``: each service's port as published somewhere else (a compose
        stack's), instead of ``block``'s."""
        self.block = block
        self.base = (host if "://" in host else f"http://{host}").rstrip("/")
        self.site = site
        self.timeout_s = timeout_s
        self.ports = dict(ports) if ports is not None else None
        self.client = httpx.Client(timeout=timeout_s, headers=control_headers())
        self.proc: subprocess.Popen | None = None

    # -- where -----------------------------------------------------------------------------
    def port(self, service: str) -> int:
        """``service``'s REST port (``ingest``: the camera emulator's, which it replaces)."""
        name = "camera" if service == "ingest" else service
        if self.ports is not None:
            return self.ports[name]
        return self.block.rest(name)

    def url(self, service: str, path: str = "/", *, site: str | None = None) -> str:
        """``service``'s URL for ``path``; a site's path under ``/sites/<site>`` (``site``,
        else this handle's), a run-level path (:data:`RUN_LEVEL`), a probe or ``/metrics``
        never."""
        site = site or self.site
        if site and (service, path) not in RUN_LEVEL and not path.startswith(
                ("/healthz", "/readyz", "/metrics")):
            path = f"/sites/{site}{path}"
        return f"{self.base}:{self.port(service)}{path}"

    # -- what ------------------------------------------------------------------------------
    def request(self, method: str, service: str, path: str, **kw: Any) -> httpx.Response:
        """The raw response (any status); :class:`PipelineError` when nothing answers."""
        url = self.url(service, path)
        try:
            return self.client.request(method, url, **kw)
        except httpx.HTTPError as err:
            raise PipelineError(f"{method} {url}: {err!r} (is the pipeline up? `aoi3d up`, "
                                f"or pass --up)") from None

    def call(self, method: str, service: str, path: str, **kw: Any) -> Any:
        """The JSON answer; :class:`PipelineError` naming the request for a status ≥ 400."""
        resp = self.request(method, service, path, **kw)
        if resp.status_code >= 400:
            raise PipelineError(f"{method} {resp.request.url} answered {resp.status_code}: "
                                f"{resp.text[:300]}")
        return resp.json()

    def get(self, service: str, path: str, **params: Any) -> Any:
        return self.call("GET", service, path, params=params or None)

    def put(self, service: str, path: str, body: Any) -> Any:
        return self.call("PUT", service, path, json=body)

    def post(self, service: str, path: str, body: Any = None) -> Any:
        return self.call("POST", service, path, json=body)

    def metrics(self, service: str) -> dict[str, float]:
        """``service``'s ``/metrics`` (:func:`parse_metrics`)."""
        resp = self.request("GET", service, "/metrics")
        if resp.status_code != 200:
            raise PipelineError(f"GET {resp.request.url} answered {resp.status_code}")
        return parse_metrics(resp.text)

    def ready(self, services: Iterable[str] = SERVICE_PORTS) -> bool:
        """Every one of ``services`` answers ``/readyz`` with 200."""
        try:
            return all(self.client.get(self.url(s, "/readyz")).status_code == 200
                       for s in services)
        except httpx.HTTPError:
            return False

    def wait_ready(self, timeout_s: float, services: Iterable[str] = SERVICE_PORTS) -> None:
        """Until :meth:`ready`; :class:`PipelineError` after ``timeout_s`` or when the
        pipeline this handle started has exited."""
        names = tuple(services)
        self.wait("every service to be ready", lambda: self.ready(names), timeout_s,
                  every_s=1.0)

    def wait(self, what: str, check: Callable[[], Any], timeout_s: float,
             every_s: float = 0.25) -> Any:
        """:func:`wait_until`, failing at once when the pipeline this handle started exits."""
        return wait_until(what, check, timeout_s, every_s, proc=self.proc)

    def latest_render(self) -> tuple[bytes, int | None]:
        """The dispatcher's latest render (PNG) and the decision it shows; ``(b"", None)``
        while it has none."""
        try:
            resp = self.client.get(self.url("dispatcher", "/render.png"))
        except httpx.HTTPError:
            return b"", None
        if resp.status_code != 200:
            return b"", None
        return resp.content, int(resp.headers.get("x-decision-id", "0"))

    # -- its process -----------------------------------------------------------------------
    def start(self, args: Sequence[str] = (), *, run_id: str | None = None,
              log_dir: Path | None = None, env: Mapping[str, str] | None = None,
              output: int | None = subprocess.DEVNULL, cwd: Path | None = None) -> Pipeline:
        """Run ``aoi3d up --quiet`` on this handle's ports with ``args``, in a session of its
        own, and return at once (:meth:`wait_ready` waits). ``output``: where its output goes
        (``subprocess.PIPE``: read as text, :meth:`stop` returns it)."""
        cmd = [sys.executable, "-m", "aoi3d_cli", "up", *self.block.up_args(), "--quiet"]
        if run_id is not None:
            cmd += ["--run-id", run_id]
        if log_dir is not None:
            cmd += ["--log-dir", str(log_dir)]
        self.proc = subprocess.Popen(
            [*cmd, *args], cwd=cwd, env=None if env is None else dict(env), stdout=output,
            stderr=subprocess.STDOUT if output is not None else None,
            text=output == subprocess.PIPE, start_new_session=True)
        return self

    @property
    def pid(self) -> int:
        """The started ``aoi3d up``'s process id (:class:`PipelineError` before :meth:`start`)."""
        if self.proc is None:
            raise PipelineError("this pipeline handle started no `aoi3d up`")
        return self.proc.pid

    def stop(self, timeout_s: float = 60.0) -> str:
        """SIGTERM to the started ``aoi3d up``, SIGKILL to its session after ``timeout_s``;
        its output when it was piped, else ``""``. Asserts nothing (safe in a ``finally``);
        the handle can start the next one."""
        out = ""
        proc = self.proc
        if proc is not None and proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        if proc is not None:
            try:
                out = proc.communicate(timeout=timeout_s)[0] or ""
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                out = proc.communicate()[0] or ""
        return out

    def close(self) -> None:
        self.client.close()

    def __enter__(self) -> Pipeline:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
        self.close()
