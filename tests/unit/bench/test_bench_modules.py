"""Every benchmark is a module of the ``bench`` package with a ``run()`` that returns its result
document and a ``main()`` whose options include ``--json`` (bench/__init__.py says so; issue 39
asked it). Read from the source, so nothing is imported or run."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
NOT_BENCHMARKS = {
    "__init__": "the package",
    "common": "what the benchmarks share (start and stop the pipeline, write JSON)",
    "ports": "the benches' fixed ports (a table)",
    "docs": "renders results/ into docs/measurements.md; it measures nothing",
    "science": "make science: its document is results/science/claims.json, its page "
               "docs/science.md, its exit status the claims' verdict",
    "science_display": "a part of make science (python -m bench.science --only display)",
    "science_twin": "a part of make science (python -m bench.science --only twin)",
}


def _functions(tree: ast.Module) -> set[str]:
    return {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}


def _offers_json(source: str) -> bool:
    return "add_json_option(" in source or '"--json"' in source


def test_every_benchmark_has_run_main_and_json() -> None:
    missing = {}
    for path in sorted((ROOT / "bench").glob("*.py")):
        if path.stem in NOT_BENCHMARKS:
            continue
        source = path.read_text()
        functions = _functions(ast.parse(source))
        lacks = [name for name in ("run", "main") if name not in functions]
        if not _offers_json(source):
            lacks.append("--json")
        if lacks:
            missing[path.name] = lacks
    assert not missing, f"benchmarks without run(), main() or --json: {missing}"


def test_the_check_sees_a_module_without_them() -> None:
    tree = ast.parse("def main():\n    pass\n")
    assert "run" not in _functions(tree)
    assert not _offers_json("ap.add_argument('--seeds')")
    assert _offers_json("common.add_json_option(ap)")
