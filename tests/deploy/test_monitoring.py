"""The dashboard and the Prometheus rules are generated from one source (deploy/monitoring.py):
the committed files are what it makes, a stale one is caught, and the dashboard's queries,
variables and empty-at-rest reasons are what the source says. That every query returns data
on a live pipeline is tests/monitoring/test_prometheus_live.py's job."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from tests.support.deploy_modules import load

mon = load("monitoring")


def walk(panels: list[dict]):
    for p in panels:
        yield p
        yield from walk(p.get("panels", []))


@pytest.fixture(scope="module")
def board() -> dict:
    return json.loads(mon.DASHBOARD_FILE.read_text(encoding="utf-8"))


def test_committed_files_are_what_the_source_makes() -> None:
    assert mon.main(["--check"]) == 0, "run `make monitoring` and commit the result"


def test_a_hand_edited_dashboard_is_caught(tmp_path: Path, monkeypatch) -> None:
    edited = tmp_path / "aoi3d.json"
    edited.write_text(mon.DASHBOARD_FILE.read_text().replace("aoi3d_render_ssim",
                                                             "aoi3d_render_sim"))
    monkeypatch.setattr(mon, "DASHBOARD_FILE", edited)
    assert mon.main(["--check"]) == 1


def test_every_panel_query_comes_from_the_source(board: dict) -> None:
    panels = [p for p in walk(board["panels"]) if p["type"] != "row"]
    source = [p for p in mon.PANELS if isinstance(p, mon.Panel)]
    assert [p["title"] for p in panels] == [p.title for p in source]
    for got, want in zip(panels, source, strict=True):
        assert [t["expr"] for t in got["targets"]] == [q.expr for q in want.targets]
        assert [t["refId"] for t in got["targets"]] == [chr(65 + i)
                                                        for i in range(len(want.targets))]
        assert all(t["datasource"]["uid"] == mon.DATASOURCE_UID for t in got["targets"])
    ids = [p["id"] for p in walk(board["panels"])]
    assert len(ids) == len(set(ids)), "duplicate panel ids"
    assert all(p["gridPos"]["x"] + p["gridPos"]["w"] <= 24 for p in walk(board["panels"]))


def test_an_empty_at_rest_query_says_why_in_its_panel(board: dict) -> None:
    by_title = {p["title"]: p for p in walk(board["panels"])}
    declared = 0
    for panel in (p for p in mon.PANELS if isinstance(p, mon.Panel)):
        for q in panel.targets:
            if q.empty_at_rest:
                declared += 1
                assert "Empty at rest" in by_title[panel.title]["description"]
                assert q.empty_at_rest in by_title[panel.title]["description"]
    assert declared >= 1


def test_variables_site_worker_camera_and_their_use(board: dict) -> None:
    variables = {v["name"]: v for v in board["templating"]["list"]}
    assert set(variables) == {"site", "worker", "camera"}
    for v in variables.values():
        assert re.fullmatch(r"label_values\((aoi3d_\w+(\{[^}]*\})?), (\w+)\)", v["query"])
        assert v["datasource"]["uid"] == mon.DATASOURCE_UID
        assert v["includeAll"] and v["allValue"] == ".*"
    exprs = [t["expr"] for p in walk(board["panels"]) for t in p.get("targets", [])]
    for name in variables:
        assert any(f"${name}" in e for e in exprs), f"${name} is used by no panel"


def test_alerts_and_panels_share_their_expressions() -> None:
    """The PSNR-drop alert and the mean-PSNR panel are one function at two windows; the
    lost-decision alert and the lost-share recording rule one function too."""
    alerts = {a["alert"]: a["expr"] for a in mon.ALERTS}
    assert mon.mean_of("aoi3d_quality_psnr_db", "1m") in alerts["AoI3DPSNRDrop"]
    panel = next(p for p in mon.PANELS if isinstance(p, mon.Panel)
                 and p.title == "Mean PSNR over every render")
    assert panel.targets[0].expr == mon.mean_of("aoi3d_quality_psnr_db", mon.RATE, mon.S)
    lost = mon.ledger_ended("5m", "lost")
    assert lost in alerts["AoI3DDecisionsLost"]
    assert lost in mon.RECORDED["aoi3d:ledger_lost_share:5m"].expr
    rules = mon.rules()
    assert [r["record"] for r in rules["groups"][0]["rules"]] == list(mon.RECORDED)
    assert [r["alert"] for r in rules["groups"][1]["rules"]] == list(alerts)
