"""The import layering of pyproject.toml's ``[tool.importlinter]`` holds (what `make lint`
checks, run here so that `make test` — CI — checks it too): the commands (``aoi3d_cli``, the
composition root) above ``services`` above the domain ``aoi3d``, with no exception;
``aoi3d.policy`` never imports ``aoi3d.rl``; and no package has an import cycle between its
modules."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]


def test_import_contracts_are_kept() -> None:
    lint_imports = Path(sys.executable).parent / "lint-imports"
    assert lint_imports.exists(), "import-linter is missing: make install (dev extras)"
    proc = subprocess.run([str(lint_imports), "--no-cache"], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert " 0 broken" in proc.stdout, proc.stdout[-2000:]


def test_the_domain_imports_no_services_and_no_commands() -> None:
    """The layers contract (aoi3d_cli above services above aoi3d) carries no exception, no
    module of aoi3d names services or the commands, and there is no CLI inside the domain."""
    import re
    import tomllib

    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    contracts = doc["tool"]["importlinter"]["contracts"]
    assert not any(c.get("ignore_imports") for c in contracts)
    layers = next(c for c in contracts if c["id"] == "layers")
    assert layers["layers"] == ["aoi3d_cli", "services", "aoi3d"]
    naming = [str(p.relative_to(ROOT)) for p in (ROOT / "aoi3d").rglob("*.py")
              if re.search(r"^\s*(from|import) (services|aoi3d_cli)\b", p.read_text(), re.M)]
    assert naming == []
    assert not (ROOT / "aoi3d" / "cli").exists()

def test_make_lint_runs_ruff_the_contracts_and_mypy_and_ci_runs_it_first() -> None:
    """`make lint` is ruff, lint-imports, mypy (in that order; mypy's files and flags are
    pyproject.toml's [tool.mypy]); .ci/run runs it before `make test`."""
    import re

    makefile = (ROOT / "Makefile").read_text()
    recipe = re.search(r"^lint:.*\n((?:\t.*\n)+)", makefile, re.M)
    assert recipe is not None, "the Makefile has no lint target"
    tools = [line.split()[0].rsplit("/", 1)[-1] for line in recipe.group(1).splitlines()]
    assert tools == ["ruff", "lint-imports", "mypy"]
    ci = [line.split("#")[0].strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    assert "make lint" in ci
    assert ci.index("make lint") < next(i for i, line in enumerate(ci)
                                        if line.startswith("make test"))


def test_mypy_checks_every_module_and_its_strict_list_names_real_modules() -> None:
    """No ``[[tool.mypy.overrides]]`` turns the checker off (``ignore_errors``,
    ``follow_imports = skip``) for any module of ours, and every module the strict list names
    exists (a stale name would hide that a module left it)."""
    import tomllib

    mypy = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["mypy"]
    ours = ("aoi3d", "aoi3d_cli", "services", "bench")
    for override in mypy.get("overrides", []):
        modules = override["module"]
        modules = [modules] if isinstance(modules, str) else modules
        if any(m.split(".")[0] in ours for m in modules):
            assert not override.get("ignore_errors"), modules
            assert override.get("follow_imports") not in ("skip", "silent"), modules
        for m in modules:
            if m.split(".")[0] in ours:
                base = ROOT / m.removesuffix(".*").replace(".", "/")
                assert base.with_suffix(".py").is_file() or (base / "__init__.py").is_file(), m
