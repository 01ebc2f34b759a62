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


#: The composition root's edges into services (docs/architecture.md, "The CLI above the
#: services"): `aoi3d up`, `aoi3d ros2` and `aoi3d replay`, and no other.
COMPOSITION_EDGES = [
    "aoi3d.cli.up -> services.supervisor",
    "aoi3d.cli.up -> services.kit.rig",
    "aoi3d.cli.replay -> services.recorder.replay",
    "aoi3d.cli.replay -> services.recorder.importer",
    "aoi3d.cli.replay -> services.recorder.player",
    "aoi3d.cli.replay -> services.ingest.publish",
    "aoi3d.cli.scene -> services.recorder.importer",
    "aoi3d.cli.ros2 -> services.ingest.publish",
    "aoi3d.cli.ros2 -> services.kit.rig",
]


def test_the_domain_imports_services_in_the_composition_root_only() -> None:
    """The contract's exceptions are exactly the composition root's named edges, and no other
    module of aoi3d names services (ports and site names come from aoi3d.ports)."""
    import re
    import tomllib

    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    contract = next(c for c in doc["tool"]["importlinter"]["contracts"]
                    if c["id"] == "domain-not-services")
    assert contract["ignore_imports"] == COMPOSITION_EDGES
    naming = [str(p.relative_to(ROOT)) for p in (ROOT / "aoi3d").rglob("*.py")
              if re.search(r"^\s*(from|import) services\b", p.read_text(), re.M)]
    assert sorted(naming) == ["aoi3d/cli/replay.py", "aoi3d/cli/ros2.py", "aoi3d/cli/scene.py",
                              "aoi3d/cli/up.py"]


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
