"""Every service's OpenAPI document names each operation once, the same way on every start.

Clients generated from the documents (and schemathesis's links) key on operationId: a duplicate
makes the document invalid, and an id that changes with PYTHONHASHSEED changes the document
from one start to the next (the console's forwarding route did both).
"""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from aoi3d.rigfile import rig_from_dict
from services.kit.membus import MemoryBus
from tests.support.ingest import rig_doc

ROOT = Path(__file__).resolve().parents[2]
SERVICES = sorted(p.parent.name for p in (ROOT / "services").glob("*/app.py")
                  if p.parent.name != "kit")


def _ids(name: str) -> list[str]:
    extra = {"rig": rig_from_dict(rig_doc())} if name == "ingest" else {}  # it needs a rig
    app = importlib.import_module(f"services.{name}.app").create_app(bus=MemoryBus(), **extra)
    return [op["operationId"] for path in app.openapi()["paths"].values()
            for op in path.values() if isinstance(op, dict) and "operationId" in op]


@pytest.mark.parametrize("name", SERVICES)
def test_operation_ids_are_unique(name: str) -> None:
    ids = _ids(name)
    assert ids, f"{name}: no operations in its OpenAPI document"
    repeated = sorted(i for i, n in Counter(ids).items() if n > 1)
    assert not repeated, f"{name}: operationIds used more than once: {repeated}"


def test_console_document_is_the_same_under_any_hash_seed() -> None:
    code = ("import json; from services.console.app import create_app; "
            "from services.kit.membus import MemoryBus; "
            "print(json.dumps(create_app(bus=MemoryBus()).openapi(), sort_keys=True))")
    docs = set()
    for seed in ("1", "2", "3"):
        env = {**os.environ, "PYTHONHASHSEED": seed, "PYTHONPATH": str(ROOT)}
        out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, check=True,
                             capture_output=True, text=True, timeout=120).stdout
        docs.add(json.dumps(json.loads(out.strip().splitlines()[-1]), sort_keys=True))
    assert len(docs) == 1, "the console's OpenAPI document differs between hash seeds"
