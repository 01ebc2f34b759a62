"""The import layering of pyproject.toml's ``[tool.importlinter]`` holds (what `make lint`
checks, run here so that `make test` — CI — checks it too): ``aoi3d`` never imports
``services`` but in `aoi3d up`, the composition root (one edge, argued in
docs/architecture.md, "The CLI above the services"), ``aoi3d.policy`` never imports
``aoi3d.rl``, and no package has an import cycle between its modules."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_import_contracts_are_kept() -> None:
    lint_imports = Path(sys.executable).parent / "lint-imports"
    assert lint_imports.exists(), "import-linter is missing: make install (dev extras)"
    proc = subprocess.run([str(lint_imports), "--no-cache"], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert " 0 broken" in proc.stdout, proc.stdout[-2000:]


def test_the_domain_imports_services_in_one_place_only() -> None:
    """The contract's exception is exactly one edge, `aoi3d up`'s import of the supervisor,
    and no other module of aoi3d names services (ports and site names come from
    aoi3d.ports)."""
    import re
    import tomllib

    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    contract = next(c for c in doc["tool"]["importlinter"]["contracts"]
                    if c["id"] == "domain-not-services")
    assert contract["ignore_imports"] == ["aoi3d.cli.up -> services.supervisor"]
    naming = [str(p.relative_to(ROOT)) for p in (ROOT / "aoi3d").rglob("*.py")
              if re.search(r"^\s*(from|import) services\b", p.read_text(), re.M)]
    assert naming == ["aoi3d/cli/up.py"]
