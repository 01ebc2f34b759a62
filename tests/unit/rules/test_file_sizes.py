"""File size limits (issue 39): no .py file under services/ over 330 lines (the generated
services/kit/pb/ aside), none under aoi3d/ over 500. A file past its limit is split along its
seams, not squeezed. Reads the files' bytes only: cheap."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
LIMITS: tuple[tuple[str, int, tuple[str, ...]], ...] = (
    ("services", 330, ("services/kit/pb",)),
    ("aoi3d", 500, ()),
)
"""(folder, most lines a .py file under it may have, folders under it left out)."""


def oversized(root: Path = ROOT,
              limits: tuple[tuple[str, int, tuple[str, ...]], ...] = LIMITS) -> list[str]:
    """Each .py file over its folder's limit, as ``path: N lines (limit L)``."""
    found = []
    for folder, limit, skip in limits:
        for path in sorted((root / folder).rglob("*.py")):
            rel = path.relative_to(root).as_posix()
            if any(rel.startswith(f"{s}/") for s in skip):
                continue
            lines = len(path.read_bytes().splitlines())
            if lines > limit:
                found.append(f"{rel}: {lines} lines (limit {limit})")
    return found


def test_no_file_is_over_its_limit() -> None:
    offenders = oversized()
    assert not offenders, "split these along their seams:\n" + "\n".join(offenders)


def test_the_check_names_every_offender_and_skips_the_generated(tmp_path: Path) -> None:
    def write(rel: str, lines: int) -> None:
        path = tmp_path / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("x = 1\n" * lines)

    write("services/a/worker.py", 331)
    write("services/a/core.py", 330)  # at the limit: allowed
    write("services/kit/pb/aoi3d_pb2.py", 2000)  # generated: left out
    write("services/kit/pbx.py", 10)
    write("aoi3d/field/big.py", 501)
    write("aoi3d/small.py", 500)
    write("aoi3d/notes.txt", 900)  # not Python
    assert oversized(tmp_path) == ["services/a/worker.py: 331 lines (limit 330)",
                                   "aoi3d/field/big.py: 501 lines (limit 500)"]


def test_the_architecture_page_stays_short() -> None:
    """docs/architecture.md is the layers, the flow of one decision, the contracts and where to
    start reading: at most 300 lines; history goes to docs/decisions/."""
    lines = len((ROOT / "docs" / "architecture.md").read_text().splitlines())
    assert lines <= 300, f"docs/architecture.md has {lines} lines (limit 300)"
