"""The README and docs/ stay current with the code: the configuration table, the REST calls
and routes they show, their links, the front page's length, and the numbers they quote."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

from services import configdoc
from services.kit.membus import MemoryBus

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()
DOCS = {p.name: p.read_text() for p in sorted((ROOT / "docs").glob("*.md"))}
#: Every page a user reads: the front page and docs/.
PAGES = {"README.md": README, **{f"docs/{k}": v for k, v in DOCS.items()}}
PORTS = {8101: "camera", 8102: "network", 8103: "scheduler", 8104: "dispatcher", 8105: "metrics"}
CURL = re.compile(r"curl(?: -X (\w+))?[^\n]*?localhost:(\d+)(/[\w./]*)")
#: Pages whose numbers come from result files: measurements.md (bench/docs.py, from
#: results/) and science.md (bench/science.py, `make science`); and the hand-written
#: pages that report the runs kept outside results/ (development seeds, the oracle, the
#: replay of a 39 MB recording).
NUMBER_SOURCES = ("measurements.md", "science.md", "ppo.md", "experiments.md", "recording.md")
#: Overview pages, which quote numbers and must quote them as their source pages have them.
OVERVIEWS = ("README.md", "docs/operations.md", "docs/performance.md", "docs/research.md",
             "docs/cli.md")


def test_configuration_table_is_current() -> None:
    assert configdoc.embedded(DOCS["configuration.md"]) == configdoc.markdown().strip(), (
        "docs/configuration.md's table is stale: run `python -m services.configdoc --update`")


@pytest.fixture(scope="module")
def openapi_paths() -> dict[str, dict]:
    out = {}
    for name in PORTS.values():
        app = importlib.import_module(f"services.{name}.app").create_app(bus=MemoryBus())
        out[name] = app.openapi()["paths"]
    return out


@pytest.mark.parametrize("page", sorted(PAGES))
def test_curl_calls_exist(page: str, openapi_paths: dict[str, dict]) -> None:
    for method, port, path in CURL.findall(PAGES[page]):
        service = PORTS[int(port)]
        path = path.split("?")[0]
        # a path of a site (/sites/site2/policy) is the template /sites/{site}/policy
        template = re.sub(r"^/sites/[^/]+/", "/sites/{site}/", path)
        assert template in openapi_paths[service], f"{page} calls {path} on {service}"
        assert (method or "GET").lower() in openapi_paths[service][template], (method, path)


def test_the_pages_that_teach_control_show_it() -> None:
    """The front page shows how to change MAT and the policy; operations.md every control."""
    readme = {(m or "GET", path) for m, _, path in CURL.findall(README)}
    assert {("PUT", "/policy"), ("GET", "/aoi")} <= readme, readme
    assert len(CURL.findall(DOCS["operations.md"])) >= 12


def test_route_table_exists(openapi_paths: dict[str, dict]) -> None:
    rows = 0
    for line in DOCS["operations.md"].splitlines():
        m = re.match(r"\| (camera|network|scheduler|dispatcher|metrics) \| 81\d\d \|.*\| (.+) \|$",
                     line)
        if not m:
            continue
        rows += 1
        for method, path in re.findall(r"`(GET/PUT|GET|PUT|POST) (/[\w./]*)`", m.group(2)):
            for one in method.split("/"):
                assert one.lower() in openapi_paths[m.group(1)].get(path, {}), (m.group(1),
                                                                                 one, path)
    assert rows == 5, "docs/operations.md's service table lost a service"


def test_front_page_is_a_front_page() -> None:
    lines = README.splitlines()
    assert len(lines) <= 250, f"README.md has {len(lines)} lines; the rest belongs in docs/"
    first_command = next(i for i, line in enumerate(lines) if line.startswith("```"))
    assert "aoi3d" in " ".join(lines[:first_command]).lower() and first_command > 3, (
        "say what aoi3d is before the commands")
    assert "make up" in README and "make test" in README
    linked = set(re.findall(r"\]\(docs/([\w-]+\.md)", README))
    assert set(DOCS) <= linked, f"pages the front page does not link: {set(DOCS) - linked}"


@pytest.mark.parametrize("page", sorted(PAGES))
def test_relative_links_resolve(page: str) -> None:
    base = (ROOT / page).parent
    for target in re.findall(r"\]\(([^)\s]+)\)", PAGES[page]):
        if re.match(r"[a-z]+://|mailto:|#", target):
            continue
        path, _, anchor = target.partition("#")
        assert (base / path).exists(), f"{page} links {target}, which does not exist"
        if anchor and path.endswith(".md"):
            text = (base / path).read_text()
            anchors = {_anchor(h) for h in re.findall(r"^#+ (.+)$", text, re.M)}
            assert anchor in anchors, f"{page} links {target}: no such heading"


def _anchor(title: str) -> str:
    keep = "".join(c for c in title.lower() if c.isalnum() or c in " -_")
    return keep.replace(" ", "-")


def _pairs(text: str) -> list[tuple[str, str]]:
    return re.findall(r"(\d+\.\d+) ± (\d+\.\d+)", text)


@pytest.mark.parametrize("page", OVERVIEWS)
def test_quoted_numbers_match_their_source(page: str) -> None:
    """Every `mean ± interval` an overview page quotes is on a page generated from result
    files (or on the page that reports the run), to the digits quoted: a re-run that moves a
    number makes the overview fail here instead of going stale."""
    known = [(float(a), float(b)) for name in NUMBER_SOURCES for a, b in _pairs(DOCS[name])]
    for a, b in _pairs(PAGES[page]):
        digits = len(a.split(".")[1])
        assert any(round(x, digits) == float(a) and round(y, len(b.split(".")[1])) == float(b)
                   for x, y in known), f"{page} quotes {a} ± {b}, which no source page has"


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
