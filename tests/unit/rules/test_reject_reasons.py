"""The reasons a message is dropped for: one enum (``RejectReason``, services/kit/rejected.py),
the table of docs/operations.md (and the ingest's of docs/real-cameras.md) equal to it, every
``Rejected`` raised with a member, and the Prometheus label values the same strings."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest
from prometheus_client import CollectorRegistry, generate_latest

from services.kit.observe import Rejections
from services.kit.rejected import Rejected, RejectReason

ROOT = Path(__file__).resolve().parents[3]
CODE = ("services", "aoi3d_cli", "aoi3d", "bench", "tests")


def _table(page: str, after: str) -> list[list[str]]:
    """The labels of each row of the first table after the line holding ``after``: the
    backquoted words of its first cell."""
    lines = (ROOT / "docs" / page).read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if after in line)
    rows, seen = [], False
    for line in lines[start:]:
        if line.startswith("|"):
            seen = True
            first = line.split("|")[1]
            if not set(first.strip()) <= {"-"} and first.strip() != "reason":
                rows.append(re.findall(r"`([a-z_]+)`", first))
        elif seen:
            break
    return rows


def test_the_documented_reasons_are_the_enums() -> None:
    rows = _table("operations.md", "with one of these reasons")
    documented = [label for row in rows for label in row]
    assert len(documented) == len(set(documented)), "a reason documented twice"
    assert set(documented) == {str(r) for r in RejectReason}
    # the ingest's reasons, one row here, are docs/real-cameras.md's table, which says what each is
    ingest = [label for row in _table("real-cameras.md", "## Bad input") for label in row]
    ros_row = next(row for row in rows if "bad_cdr" in row)
    assert set(ingest) - {"too_large", "bad_image", "bad_pose", "bad_intrinsics"} == set(ros_row)
    assert set(ingest) <= set(documented)


def test_every_reason_is_raised_somewhere() -> None:
    code = "\n".join(p.read_text() for p in sorted((ROOT / "services").rglob("*.py")))
    unused = [r.name for r in RejectReason if f"RejectReason.{r.name}" not in code]
    assert not unused, f"documented but never raised: {unused}"


def _bare(tree: ast.AST) -> list[int]:
    """Lines of ``Rejected(...)`` calls whose reason is not a ``RejectReason`` member."""
    out = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and (
                (isinstance(node.func, ast.Name) and node.func.id == "Rejected")
                or (isinstance(node.func, ast.Attribute) and node.func.attr == "Rejected"))):
            continue
        reason = node.args[0] if node.args else next(
            (k.value for k in node.keywords if k.arg == "reason"), None)
        if not (isinstance(reason, ast.Attribute) and isinstance(reason.value, ast.Name)
                and reason.value.id == "RejectReason"):
            out.append(node.lineno)
    return out


def test_the_finder_finds_a_bare_reason() -> None:
    tree = ast.parse('raise Rejected("malformed", "x")\nraise kit.Rejected(reason=r, detail="")\n'
                     'raise Rejected(RejectReason.MALFORMED, "x")\n')
    assert _bare(tree) == [1, 2]


@pytest.mark.parametrize("package", CODE)
def test_no_rejected_is_raised_with_a_bare_string(package: str) -> None:
    found = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel == "tests/unit/rules/test_reject_reasons.py" or path.name.endswith("_pb2.py"):
            continue
        lines = _bare(ast.parse(path.read_text(), rel))
        if lines:
            found[rel] = lines
    assert not found, f"raise Rejected with a RejectReason member: {found}"


def test_a_reason_is_its_label_in_prometheus_and_in_words() -> None:
    err = Rejected(RejectReason.CLOCK_SKEW, "ahead")
    assert err.reason == "clock_skew" and str(err) == "clock_skew: ahead"
    registry = CollectorRegistry()
    rejections = Rejections(registry)
    rejections.reject(err, "k")
    rejections.reject(Rejected(RejectReason.CLOCK_SKEW, "again"), "k")
    text = generate_latest(registry).decode()
    assert 'aoi3d_messages_rejected_total{reason="clock_skew"} 2.0' in text
    assert rejections.total("clock_skew") == 2.0
