"""A refused change changes nothing (issue 44): for every PUT endpoint of every service (and
the recorder's start, a POST), a request answered with a 4xx leaves the resource's GET
exactly as it was — bad values, a valid field beside an invalid one, a trace whose times
overflow, paths outside the roots or that cannot be resolved.
The apps are the real ones on a MemoryBus (tests/support/guard.py)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from aoi3d.scene import SceneDataset
from tests.support.guard import build

Body = dict[str, Any] | str


def _traces(root: Path, write: bool) -> dict[str, Path]:
    """Trace files a PUT /channel can name, each refused for another reason."""
    files = {
        "overflow": "0\n100000000000000000000\n",  # int64 overflow of the phase draw
        "year": "0\n31536000000\n",  # a period of a year: over the cap
        "negative": "5\n-1\n",
        "text": "0\nten\n",
        "empty": "",
        "binary": "\x00\xff\xfe" * 10,
    }
    out = {}
    for name, text in files.items():
        out[name] = root / f"{name}.up"
        if write:
            out[name].write_text(text, encoding="latin-1")
    return out


def _bodies(tmp: Path, *, write: bool = True) -> dict[tuple[str, str, str], list[Body]]:
    """(service, PUT path, GET path) → bodies that must each be a 4xx."""
    t = _traces(tmp, write)
    return {
        ("camera", "/config", "/config"): [
            {"period_ms": -1}, {"period_ms": 0}, {"cameras": [999]},
            {"period_ms": 50, "cameras": [999]},  # a valid field beside a bad one
            {"paused": True, "cameras": [1, 1, 999]}, {"paused": "maybe"}, {"nope": 1},
            "not json", [1, 2]],
        ("network", "/channel", "/channel"): [
            {"delay": "nope"}, {"seed": -1},
            {"delay": "exp:60", "per_camera": {"99": "const:1"}},
            {"delay": "exp:10", "seed": 3, "per_camera": {"1": "cell:" + str(t["year"])}},
            *({"delay": f"trace:{p}", "seed": 9} for p in t.values()),
            *({"delay": "const:7", "per_camera": {"2": f"trace:{p}"}} for p in t.values()),
            {"delay": f"cell:{t['overflow']},spread=0"},
            {"delay": "trace:/etc/hostname"}, {"delay": "regimes:exp:20"},
            "not json"],
        ("scheduler", "/policy", "/policy"): [
            {"kind": "nope"}, {"kind": "mat", "mat_ms": -5}, {"kind": "freshest", "k": 999},
            {"kind": "mat", "mat_ms": 70, "save_to": "runs/x.pt"},
            {"kind": "ppo", "checkpoint": "/etc/passwd"},
            {"kind": "ppo", "checkpoint": "models/no-such.pt", "learn": True},
            "not json"],
        ("dispatcher", "/backend", "/status"): [{"backend": "nope"}, {"backend": 3}, "not json"],
        ("recorder", "/recording/start", "/recording"): [  # a POST: the one state change
            {"path": "/etc/aoi3d.mcap"}, {"path": ""}, {"path": "~nobody-here/x.mcap"},
            {"path": str(tmp / "x.mcap"), "max_bytes": -1}, {"path": "a\u0000b"},
            {"path": str(tmp / "x.mcap"), "extra": 1}, "not json"],
        ("dispatcher", "/carry", "/status"): [
            {"carry": "nope"}, {"carry": "stream", "render_steps": 0},
            {"carry": "fresh", "render_steps": 10**9}, "not json"],
    }


_VOLATILE = {"/status": {"pool", "steps_per_s", "decision"}, "/channel": {"in_force"}}
"""Fields that move with time, not with a PUT (the pool's windows, a regime in force)."""


def _state(client: TestClient, path: str) -> dict[str, Any]:
    r = client.get(path)
    assert r.status_code == 200, r.text
    return {k: v for k, v in r.json().items() if k not in _VOLATILE.get(path, set())}


CASES = list(_bodies(Path("/nonexistent"), write=False))
"""Every PUT endpoint: (service, PUT path, GET path)."""


@pytest.mark.parametrize("case", CASES,
                         ids=lambda c: f"{c[0]}-PUT{c[1]}")
def test_a_4xx_on_any_put_leaves_the_resource_as_it_was(
        case: tuple[str, str, str], dataset: SceneDataset, tmp_path: Path) -> None:
    service, put, get = case
    bodies = _bodies(tmp_path)[case]
    roots = [str(tmp_path), "runs", "models"] if service != "recorder" else [str(tmp_path)]
    app = build(service, dataset, files_roots=roots)
    with TestClient(app) as client:
        for prefix in ("", "/sites/site1"):  # the default site's routes and the per-site ones
            if client.get(prefix + get).status_code == 404:
                continue
            before = _state(client, prefix + get)
            for body in bodies:
                send: Callable[..., Any] = client.post if service == "recorder" \
                    else client.put
                r = (send(prefix + put, content=body, headers={"content-type":
                                                                "application/json"})
                     if isinstance(body, str) else send(prefix + put, json=body))
                assert 400 <= r.status_code < 500, (body, r.status_code, r.text)
                assert "Traceback" not in r.text
                assert _state(client, prefix + get) == before, body
