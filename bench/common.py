"""What the benches share: where the results go and how a result document is written or
printed (``--json``); and, for the benches that start a live pipeline (bench/pipeline.py,
scale.py, soak.py, chaos.py, online_live.py, live_channel.py, realtime.py, live_default.py),
``aoi3d up`` started from the repository root on a bench's own ports as the one pipeline
handle (:class:`aoi3d_cli.pipeline.Pipeline`: URLs, REST, ``/metrics``, waits, the stop) and
one Zenoh tap of a run.

The ports come from :data:`bench.ports.BENCH_BLOCKS` (a :class:`services.kit.ports.PortBlock` per
bench: its URLs and its ``aoi3d up`` options). A bench is run from the repository root as
``python -m bench.NAME`` and imports this module as ``bench.common``; benches import nothing
from tests/.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import threading
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

from aoi3d_cli.pipeline import wait_until
from services.kit.ports import PortBlock

__all__ = ["RESULTS", "ROOT", "Tap", "add_json_option", "print_json", "progress_to_stderr",
           "wait_until", "write_json"]

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
