"""results/README.md names the command behind each entry of results/: every file and folder
directly under results/ has its row (a folder written with its final ``/``), and no row names
an entry that is not there."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
RESULTS = ROOT / "results"
#: A table row's first cell: one entry in backticks.
ROW = re.compile(r"^\| `([^`]+)` \|", re.M)


def entries(folder: Path) -> set[str]:
    """What lies directly under ``folder`` (its README aside), folders ending in ``/``."""
    return {p.name + "/" if p.is_dir() else p.name
            for p in folder.iterdir() if p.name != "README.md"}


def mismatch(folder: Path) -> tuple[list[str], list[str]]:
    """(entries without a row, rows without an entry) of ``folder``'s README."""
    listed = set(ROW.findall((folder / "README.md").read_text()))
    present = entries(folder)
    return sorted(present - listed), sorted(listed - present)


def test_every_entry_has_its_row_and_every_row_its_entry() -> None:
    assert len(entries(RESULTS)) > 40, "results/ looks empty: the test would check nothing"
    missing, absent = mismatch(RESULTS)
    assert not missing, f"results/README.md has no row for {missing}"
    assert not absent, f"results/README.md lists what results/ does not hold: {absent}"


def test_the_check_names_a_missing_and_an_absent_entry(tmp_path: Path) -> None:
    (tmp_path / "run").mkdir()
    (tmp_path / "a.json").write_text("{}")
    (tmp_path / "b.json").write_text("{}")
    (tmp_path / "README.md").write_text(
        "| entry | command |\n|---|---|\n| `run/` | x |\n| `a.json` | y |\n"
        "| `gone.json` | z |\n")
    assert mismatch(tmp_path) == (["b.json"], ["gone.json"])
    (tmp_path / "README.md").write_text("| `run` | x |\n| `a.json` | y |\n| `b.json` | z |\n")
    assert mismatch(tmp_path) == (["run/"], ["run"]), "a folder's row ends in /"
