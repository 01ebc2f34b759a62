"""The README stays current with the code: configuration table and REST routes."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

from services import configdoc
from services.kit.membus import MemoryBus

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()
PORTS = {8101: "camera", 8102: "network", 8103: "scheduler", 8104: "trainer", 8105: "metrics"}


def test_configuration_table_is_current() -> None:
    assert configdoc.readme_section(README) == configdoc.markdown().strip(), (
        "README configuration table is stale: run `python -m services.configdoc --update`")


@pytest.fixture(scope="module")
def openapi_paths() -> dict[str, dict]:
    out = {}
    for name in PORTS.values():
        app = importlib.import_module(f"services.{name}.app").create_app(bus=MemoryBus())
        out[name] = app.openapi()["paths"]
    return out


def test_readme_curl_calls_exist(openapi_paths: dict[str, dict]) -> None:
    calls = re.findall(r"curl(?: -X (\w+))?[^\n]*?localhost:(\d+)(/[\w./]*)", README)
    assert len(calls) >= 6
    for method, port, path in calls:
        service = PORTS[int(port)]
        path = path.split("?")[0]
        # a path of a site (/sites/site2/policy) is the template /sites/{site}/policy
        template = re.sub(r"^/sites/[^/]+/", "/sites/{site}/", path)
        assert template in openapi_paths[service], f"README calls {path} on {service}"
        assert (method or "GET").lower() in openapi_paths[service][template], (method, path)


def test_readme_route_table_exists(openapi_paths: dict[str, dict]) -> None:
    for line in README.splitlines():
        m = re.match(r"\| (camera|network|scheduler|trainer|metrics) \| 81\d\d \|.*\| (.+) \|$",
                     line)
        if not m:
            continue
        for method, path in re.findall(r"`(GET/PUT|GET|PUT|POST) (/[\w./]*)`", m.group(2)):
            for one in method.split("/"):
                assert one.lower() in openapi_paths[m.group(1)].get(path, {}), (m.group(1),
                                                                                 one, path)


def test_api_docs_load_nothing_from_outside() -> None:
    """/docs and /redoc of every service (one service_app for all) reference only assets the
    service serves itself, and those load: the pages work on a machine with no internet."""
    from fastapi.testclient import TestClient

    from services.network.app import create_app
    from services.network.settings import Settings

    with TestClient(create_app(Settings(), bus=MemoryBus())) as client:
        for page in ("/docs", "/redoc"):
            html = client.get(page).text
            urls = re.findall(r'(?:src|href)\s*=\s*["\']([^"\']+)["\']', html)
            urls += re.findall(r'url:\s*["\']([^"\']+)["\']', html)
            assert urls, html[:500]
            for u in urls:
                assert u.startswith("/"), f"{page} loads {u} from outside the service"
                assert client.get(u).status_code == 200, u
