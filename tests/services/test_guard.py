"""Hostile REST input and open control (issue 11, failures 3, 4 and 5), on the five real
service apps (MemoryBus; the REST layer is the real one): every case here answered 500,
was half-applied, echoed megabytes back or was accepted from anyone before."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from aoi3d.scene import SceneDataset
from tests.support.guard import SERVICES, build

TOKEN = "s3cret-token"

# a state-changing request each service accepts when it is well-formed
VALID = {"camera": ("PUT", "/config", {"paused": False}),
         "network": ("PUT", "/channel", {"delay": "exp:60"}),
         "scheduler": ("PUT", "/policy", {"kind": "mat", "mat_ms": 70}),
         "dispatcher": ("POST", "/reset", None),
         "metrics": None}  # nothing to change there: GETs only
NUMERIC = {"camera": ("PUT", "/config", "period_ms"),
           "network": ("PUT", "/channel", "seed"),
           "scheduler": ("PUT", "/policy", "mat_ms"),
           "dispatcher": ("PUT", "/carry", "render_steps")}






@pytest.fixture
def open_app(dataset: SceneDataset) -> Iterator[Callable[[str], TestClient]]:
    clients: list[TestClient] = []

    def make(service: str, **kw) -> TestClient:
        client = TestClient(build(service, dataset, **kw))
        client.__enter__()
        clients.append(client)
        return client

    yield make
    for c in clients:
        c.__exit__(None, None, None)




def _route(service: str) -> tuple[str, str]:
    method, path, _ = NUMERIC.get(service, ("GET", "/quality", None))
    return method, path


@pytest.mark.parametrize("service", SERVICES)
@pytest.mark.parametrize("raw", [b"NaN", b"Infinity", b"-Infinity", b"1e999"])
def test_nan_and_infinity_are_422_not_500(open_app, service: str, raw: bytes) -> None:
    client = open_app(service)
    if service == "metrics":
        r = client.get("/quality", params={"limit": raw.decode()})
        assert r.status_code == 422, r.text
        return
    method, path, field = NUMERIC[service]
    before = client.get(path).json() if method == "PUT" else None
    r = client.request(method, path, content=b'{"%s": %s}' % (field.encode(), raw),
                       headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    assert "not a valid JSON number" in r.text or "finite number" in r.text
    if before is not None:
        assert client.get(path).json() == before  # nothing changed


@pytest.mark.parametrize("service", SERVICES)
def test_bodies_are_bounded_and_errors_do_not_echo_them(open_app, service: str) -> None:
    client = open_app(service)
    method, path = _route(service)
    if method == "GET":
        method, path = "PUT", "/quality"  # no such route: the guard answers first anyway
    big = b'{"x": "' + b"A" * (70 * 1024) + b'"}'
    r = client.request(method, path, content=big, headers={"content-type": "application/json"})
    assert r.status_code == 413 and len(r.content) < 300, r.text[:300]

    def chunks() -> Iterator[bytes]:  # no Content-Length: bounded while read
        for _ in range(80):
            yield b"A" * 1024

    r = client.request(method, path, content=chunks(),
                       headers={"content-type": "application/json"})
    assert r.status_code == 413, r.text[:300]
    # an invalid body under the limit: 422 with a short message, never the body back
    r = client.request(method, path, content=b'{"' + b"B" * 60_000 + b'": [1, 2',
                       headers={"content-type": "application/json"})
    assert r.status_code in (404, 405, 422) and len(r.content) < 2000, len(r.content)


def test_delay_specs_that_would_block_links_are_refused_and_change_nothing(open_app) -> None:
    client = open_app("network")
    before = client.get("/channel").json()
    for spec in ("const:1e300", "lognormal:1000:1000", "exp:1e9"):
        r = client.put("/channel", json={"delay": spec, "seed": 99})
        assert r.status_code == 422, r.text
        assert "exceeds the maximum" in r.json()["detail"]
        got = client.get("/channel")
        assert got.status_code == 200 and got.json() == before  # not half-applied
    r = client.put("/channel", json={"per_camera": {"1": "const:1e300"}})
    assert r.status_code == 422 and client.get("/channel").json() == before


def test_a_camera_period_below_one_slot_is_refused(open_app) -> None:
    client = open_app("camera")
    before = client.get("/config").json()
    for period in (1e-9, 0.5, 0):
        r = client.put("/config", json={"period_ms": period})
        assert r.status_code == 422, r.text
    assert client.get("/config").json() == before


@pytest.mark.parametrize("service", [s for s in SERVICES if VALID[s]])
def test_the_control_token_guards_every_change_and_leaves_gets_open(open_app,
                                                                    service: str) -> None:
    client = open_app(service, control_token=TOKEN)
    method, path, body = VALID[service]
    kw = {"json": body} if body is not None else {}
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": TOKEN}):
        r = client.request(method, path, headers=headers, **kw)
        assert r.status_code == 401, (headers, r.text)
        assert r.headers["www-authenticate"] == "Bearer"
    assert client.get("/healthz").status_code == 200
    assert client.get(path if method == "PUT" else "/status").status_code == 200
    r = client.request(method, path, headers={"Authorization": f"Bearer {TOKEN}"}, **kw)
    assert r.status_code == 200, r.text


def test_the_token_can_come_from_a_file(open_app, tmp_path: Path) -> None:
    secret = tmp_path / "token"
    secret.write_text(TOKEN + "\n")
    client = open_app("scheduler", control_token_file=secret)
    assert client.put("/policy", json={"kind": "all"}).status_code == 401
    r = client.put("/policy", json={"kind": "all"},
                   headers={"Authorization": f"Bearer {TOKEN}"})
    assert r.status_code == 200, r.text


def test_cross_site_requests_are_refused(open_app) -> None:
    """A page of another site posting a form, or fetching with its Origin; and a rebound DNS
    name pointing at 127.0.0.1 (the Host header names it)."""
    client = open_app("dispatcher")
    steps = client.get("/status").json()["steps"]
    r = client.post("/reset", content=b"a=1",
                    headers={"content-type": "application/x-www-form-urlencoded"})
    assert r.status_code == 415, r.text
    r = client.post("/reset", headers={"Origin": "http://evil.example"})
    assert r.status_code == 403, r.text
    r = client.post("/reset", headers={"Origin": "null"})
    assert r.status_code == 403, r.text
    r = client.post("/reset", headers={"Host": "evil.example:8104"})
    assert r.status_code == 400, r.text
    r = client.get("/status", headers={"Host": "rebound.evil.example"})
    assert r.status_code == 400, r.text
    assert client.get("/status").json()["resets"] == 0 and steps >= 0
    # the console's own origin (loopback) may
    r = client.post("/reset", headers={"Origin": "http://127.0.0.1:8106"})
    assert r.status_code == 200, r.text
