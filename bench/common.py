"""What the benches share: where the results go and how a result document is written or
printed (``--json``); and, for the benches that start a live pipeline (bench/pipeline.py,
scale.py, soak.py, chaos.py, online_live.py, live_channel.py), a service's URL on a bench's
own ports, starting ``aoi3d up`` there and stopping it, one wait loop, one ``/metrics``
scrape and one Zenoh tap of a run.

The ports come from :data:`aoi3d.ports.BENCH_BLOCKS` (a :class:`aoi3d.ports.PortBlock` per
bench: its URLs and its ``aoi3d up`` options). A bench is run from the repository root as
``python -m bench.NAME`` and imports this module as ``bench.common``; benches import nothing
from tests/.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from aoi3d.ports import PortBlock

__all__ = ["RESULTS", "ROOT", "Tap", "add_json_option", "print_json", "progress_to_stderr",
           "scrape", "start_up", "stop_up", "url", "wait_until", "write_json"]

ROOT = Path(__file__).resolve().parents[1]
"""The repository root (the benches read data/, models/ and write runs/ under it)."""
RESULTS = ROOT / "results"
"""Where the benches write their result documents (docs/measurements.md is rendered from it)."""


def write_json(path: Path, doc: Any, *, indent: int = 2, default: Any = None) -> Path:
    """``doc`` as JSON (``indent``, a final newline) at ``path``, its folder made first."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=indent, default=default) + "\n")
    return path


def add_json_option(parser: argparse.ArgumentParser,
                    help: str = "print the result document as JSON") -> None:
    """The ``--json`` flag every bench offers."""
    parser.add_argument("--json", action="store_true", help=help)


def print_json(doc: Any, *, indent: int | None = 2, default: Any = None) -> None:
    """The result document on stdout (``--json``)."""
    print(json.dumps(doc, indent=indent, default=default))


@contextlib.contextmanager
def progress_to_stderr(enabled: bool = True) -> Iterator[None]:
    """While a bench runs under ``--json``, what it prints on the way goes to stderr, so that
    stdout is the result document alone."""
    if not enabled:
        yield
        return
    with contextlib.redirect_stdout(sys.stderr):
        yield


def url(block: PortBlock, service: str, path: str = "/", *, site: str | None = None) -> str:
    """``service``'s URL for ``path`` on ``block``'s ports (under ``/sites/<site>`` when
    ``site`` is given)."""
    return block.url(service, path if site is None else f"/sites/{site}{path}")


def start_up(block: PortBlock, run_id: str, log_dir: Path, args: Sequence[str] = (),
             *, env: Mapping[str, str] | None = None,
             stdout: int = subprocess.DEVNULL) -> subprocess.Popen:
    """``python -m aoi3d_cli up --quiet`` on ``block``'s ports with ``args``, in its own process
    group (stop it with :func:`stop_up`)."""
    cmd = [sys.executable, "-m", "aoi3d_cli", "up", "--run-id", run_id, *block.up_args(),
           "--log-dir", str(log_dir), "--quiet", *args]
    return subprocess.Popen(cmd, cwd=ROOT, env=None if env is None else dict(env),
                            stdout=stdout, stderr=subprocess.STDOUT, start_new_session=True)


def stop_up(proc: subprocess.Popen, timeout_s: float = 90.0) -> None:
    """SIGTERM to ``aoi3d up`` (it stops its children), SIGKILL to the group after
    ``timeout_s``."""
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def wait_until(what: str, cond: Callable[[], Any], timeout_s: float, *,
               every_s: float = 0.5, proc: subprocess.Popen | None = None) -> None:
    """Poll ``cond`` until it is true; ``SystemExit`` naming ``what`` when ``timeout_s``
    passes or ``proc`` (the pipeline) exits. A poll that raises (the service is not up yet:
    an HTTP error, a missing key, a half-written file) counts as not yet."""
    import httpx

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            if cond():
                return
        except (OSError, ValueError, KeyError, httpx.HTTPError):
            pass
        if proc is not None and proc.poll() is not None:
            raise SystemExit(f"{what}: the pipeline exited (exit status {proc.returncode})")
        if time.monotonic() > deadline:
            raise SystemExit(f"{what}: not within {timeout_s:.0f} s")
        time.sleep(every_s)


def get_json(client: Any, block: PortBlock, service: str, path: str, **params: int) -> Any:
    """``GET`` a service of ``block``'s pipeline as JSON (an HTTP error raises)."""
    response = client.get(block.url(service, path), params=params or None)
    response.raise_for_status()
    return response.json()


def bench_main(parser: argparse.ArgumentParser, run: Callable[[argparse.Namespace], Any],
               argv: list[str] | None = None) -> None:
    """A bench's ``main``: ``run`` on the parsed options (progress to stderr with ``--json``,
    whose stdout is the document alone, printed), else the file written."""
    args = parser.parse_args(argv)
    with progress_to_stderr(args.json):
        doc = run(args)
    if args.json:
        print_json(doc)
    else:
        print(f"written: {args.out}")


def scrape(client: Any, url: str) -> dict[str, float]:
    """A service's ``/metrics`` as ``{series: value}``: each labelled sample under its full
    name, plus its metric's sum over labels under the bare name."""
    out: dict[str, float] = {}
    for line in client.get(url).text.splitlines():
        if line.startswith("#") or not line.strip():
            continue
        name, value = line.rsplit(" ", 1)
        out[name] = float(value)
        base = name.split("{")[0]
        if base != name:
            out[base] = out.get(base, 0.0) + float(value)
    return out


class Tap:
    """A Zenoh client session on ``block``'s router with one subscriber per key expression of
    ``subscriptions`` (its callback gets each sample); the callbacks share :attr:`lock`."""

    def __init__(self, block: PortBlock, subscriptions: Mapping[str, Callable[[Any], None]],
                 common: Any = None) -> None:
        """``common``: the session's :class:`services.kit.settings.CommonSettings` (a TLS
        router's, say); by default a plain client of ``block``'s router on 127.0.0.1."""
        import zenoh

        from services.kit.settings import CommonSettings, zenoh_config

        self.lock = threading.Lock()
        self.session = zenoh.open(zenoh_config(common or CommonSettings(
            zenoh_connect=[f"tcp/127.0.0.1:{block.zenoh}"])))
        self.subs = [self.session.declare_subscriber(key, callback)
                     for key, callback in subscriptions.items()]

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()
        self.session.close()
