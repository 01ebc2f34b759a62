"""The import layering of pyproject.toml's ``[tool.importlinter]`` holds (what `make lint`
checks, run here so that `make test` — CI — checks it too): ``aoi3d`` never imports
``services`` but from the CLI's composition root, ``aoi3d.policy`` never imports
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
