"""The suite's own layout: no test module imports another test module. What tests share lives
in tests/support/ (helpers) or in a conftest.py (fixtures); a test module imported by another
runs its module-level code twice and hands its fixtures over by name (the ``# noqa: F811``
this replaced). And every unit test lives in one of tests/unit's five folders, by what it
tests (tests/README.md): none directly in tests/unit, each folder a package with a test."""

from __future__ import annotations

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parents[2]
UNIT_FOLDERS = ("domain", "cores", "cli", "bench", "rules")
"""tests/unit's folders: the domain (aoi3d), the services' pure cores, the CLI, the benches and
the house rules."""


def _package(rel: Path) -> list[str]:
    """``services/test_x.py`` (under tests/) → ``["tests", "services"]``."""
    return ["tests", *rel.parent.parts]


def _resolve(rel: Path, node: ast.ImportFrom) -> str:
    """The absolute module an ``from … import`` names (a relative one resolved)."""
    if not node.level:
        return node.module or ""
    base = _package(rel)[: len(_package(rel)) - node.level + 1]
    return ".".join([*base, *([node.module] if node.module else [])])


def cross_imports(root: Path = TESTS) -> list[str]:
    """Each import of a test module other than tests.support (and conftest) by a test file,
    as ``file:line module``."""
    found = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root)
        if rel.parts[0] == "support":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                modules = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                module = _resolve(rel, node)
                # ``from tests import x`` / ``from . import x``: the modules are the names
                modules = ([f"{module}.{a.name}" for a in node.names]
                           if module == ".".join(_package(rel)) or module == "tests"
                           else [module])
            else:
                continue
            for module in modules:
                parts = module.split(".")
                if parts[0] != "tests" or parts[1:2] == ["support"]:
                    continue
                found.append(f"tests/{rel}:{node.lineno} {module}")
    return found


def test_no_test_module_imports_another() -> None:
    assert cross_imports() == [], (
        "a test module imports another: move what they share to tests/support/ (a helper) "
        "or a conftest.py (a fixture)")


def test_the_check_catches_absolute_and_relative_imports(tmp_path: Path) -> None:
    (tmp_path / "support").mkdir()
    (tmp_path / "support" / "helpers.py").write_text("from tests.unit.test_a import x\n")
    (tmp_path / "unit").mkdir()
    (tmp_path / "unit" / "test_ok.py").write_text(
        "from tests.support.waits import wait_for\nimport tests.support.metrics\n"
        "from tests.support import tiny\nimport os\n")
    (tmp_path / "unit" / "test_bad.py").write_text(
        "from tests.services.test_trainer import KEYS\n"
        "import tests.unit.test_ok\n"
        "from .test_ok import x\n"
        "from . import test_ok\n"
        "from tests import timeouts\n"
        "def f():\n    from ..services.test_x import y\n")
    assert cross_imports(tmp_path) == [
        "tests/unit/test_bad.py:1 tests.services.test_trainer",
        "tests/unit/test_bad.py:2 tests.unit.test_ok",
        "tests/unit/test_bad.py:3 tests.unit.test_ok",
        "tests/unit/test_bad.py:4 tests.unit.test_ok",
        "tests/unit/test_bad.py:5 tests.timeouts",
        "tests/unit/test_bad.py:7 tests.services.test_x",
    ]


def unsplit_unit_tests(unit: Path = TESTS / "unit") -> list[str]:
    """Each way tests/unit breaks its split, one line each: a test module outside the five
    folders (directly in tests/unit or in another folder), a folder missing, not a package or
    without a test."""
    found = [f"{path.relative_to(unit).as_posix()}: not in one of {', '.join(UNIT_FOLDERS)}"
             for path in sorted(unit.rglob("test_*.py"))
             if path.relative_to(unit).parts[0] not in UNIT_FOLDERS]
    for folder in UNIT_FOLDERS:
        if not (unit / folder).is_dir():
            found.append(f"{folder}/: missing")
            continue
        if not (unit / folder / "__init__.py").is_file():
            found.append(f"{folder}/: no __init__.py")
        if not any((unit / folder).rglob("test_*.py")):
            found.append(f"{folder}/: no test")
    return found


def test_every_unit_test_lives_in_one_of_the_five_folders() -> None:
    assert unsplit_unit_tests() == [], (
        "tests/unit holds its tests in domain/, cores/, cli/, bench/ and rules/ "
        "(tests/README.md says which is which)")


def test_the_split_check_catches_a_stray_test_and_a_missing_or_empty_folder(
        tmp_path: Path) -> None:
    for folder in UNIT_FOLDERS:
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "__init__.py").write_text("")
        (tmp_path / folder / "test_a.py").write_text("")
    (tmp_path / "conftest.py").write_text("")
    assert unsplit_unit_tests(tmp_path) == []
    (tmp_path / "test_loose.py").write_text("")
    (tmp_path / "misc").mkdir()
    (tmp_path / "misc" / "test_b.py").write_text("")
    (tmp_path / "cli" / "test_a.py").unlink()
    (tmp_path / "bench" / "__init__.py").unlink()
    for path in (tmp_path / "rules").iterdir():
        path.unlink()
    (tmp_path / "rules").rmdir()
    assert unsplit_unit_tests(tmp_path) == [
        "misc/test_b.py: not in one of domain, cores, cli, bench, rules",
        "test_loose.py: not in one of domain, cores, cli, bench, rules",
        "cli/: no test",
        "bench/: no __init__.py",
        "rules/: missing",
    ]
