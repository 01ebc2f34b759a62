"""docs/measurements.md is generated from results/ by bench/docs.py (`make docs`), never
edited by hand: the committed page equals its regeneration, every result file is reported
somewhere, a changed result changes the page, and every command it prints names a bench
script or make target that exists."""

from __future__ import annotations

import importlib
import json
import re
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def docs():
    return importlib.import_module("bench.docs")


def test_committed_pages_equal_their_regeneration(docs, tmp_path: Path) -> None:
    assert docs.main(["--out", str(tmp_path)]) == 0
    for name in docs.pages():
        committed = (ROOT / "docs" / name).read_text()
        assert (tmp_path / name).read_text() == committed, (
            f"docs/{name} differs from what results/ gives: run `make docs` "
            "(and do not edit the page by hand)")
    assert docs.main(["--check"]) == 0


def test_check_fails_on_a_hand_edit(docs, tmp_path: Path) -> None:
    docs.main(["--out", str(tmp_path)])
    page = tmp_path / docs.PAGE
    page.write_text(page.read_text().replace("| 17 |", "| 16 |", 1))
    assert docs.main(["--out", str(tmp_path), "--check"]) == 1


def test_every_result_file_is_reported(docs) -> None:
    assert docs.unaccounted() == [], "render these in bench/docs.py or list them in ELSEWHERE"


def test_a_new_or_changed_result_shows(docs, tmp_path: Path) -> None:
    results = tmp_path / "results"
    shutil.copytree(docs.RESULTS, results)
    before = docs.render(results)
    channel = json.loads((results / "channel.json").read_text())
    channel["cases"]["trace"]["camera_slots_per_s_best"] = 3.14e7
    (results / "channel.json").write_text(json.dumps(channel))
    after = docs.render(results)
    assert after != before and "3.14e+07" in after and "3.14e+07" not in before
    (results / "new-bench.json").write_text("{}")
    assert docs.unaccounted(results) == ["new-bench.json"]
    assert docs.main(["--results", str(results), "--out", str(tmp_path), "--check"]) == 1


def test_every_command_names_what_exists(docs) -> None:
    page = docs.render()
    makefile = (ROOT / "Makefile").read_text()
    scripts = set(re.findall(r"python (bench/\w+\.py)", page))
    assert {"bench/scale.py", "bench/chaos.py", "bench/recon.py"} <= scripts
    for script in scripts - {"bench/trainer_restart.py"}:  # historical: the page says so
        assert (ROOT / script).exists(), script
    for target in set(re.findall(r"make ([a-z][\w-]*)", page)):
        assert re.search(rf"^{target}:", makefile, re.M), f"make {target}"
    assert "--out bench/results/" not in page, "the results moved to results/"
    for results in re.findall(r"--out (results/[\w./-]+)", page):
        assert (ROOT / results).exists(), results
