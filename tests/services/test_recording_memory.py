"""Recordings stream (issue 44): ``aoi3d replay`` and ``aoi3d scene import`` read a recording
incrementally, so a recording far larger than the memory they may use still replays and
imports. Each command runs in a subprocess whose address space is capped (``RLIMIT_AS``) at
what the same command needed for a recording of two epochs, plus a quarter of the big
recording's size: reading the file whole (its pixels) cannot fit."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.recording import write_long_recording

_RUN = """
import resource, sys
cap = int(sys.argv[1])
if cap:
    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
from aoi3d_cli import app
try:
    app(sys.argv[2:], standalone_mode=False)
finally:
    peak = [l for l in open("/proc/self/status") if l.startswith("VmPeak")][0]
    print("VMPEAK", int(peak.split()[1]) * 1024, file=sys.stderr)
"""


def _run(cap: int, *args: str) -> tuple[subprocess.CompletedProcess, int]:
    r = subprocess.run([sys.executable, "-c", _RUN, str(cap), *args], capture_output=True,
                       text=True, timeout=600)
    peak = [int(line.split()[1]) for line in r.stderr.splitlines()
            if line.startswith("VMPEAK")]
    return r, peak[0] if peak else 0


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, int]:
    root = tmp_path_factory.mktemp("long")
    write_long_recording(root / "tiny.mcap", steps=2, size=(160, 120), compression="none")
    size = write_long_recording(root / "big.mcap", steps=500, size=(160, 120),
                                compression="none")
    assert size > 80 * 2**20, size  # 500 epochs × 3 frames of 57.6 kB
    return root / "tiny.mcap", root / "big.mcap", size


@pytest.mark.parametrize("command", ["replay", "import"])
def test_a_recording_far_larger_than_the_memory_cap_replays_and_imports(
        recordings: tuple[Path, Path, int], tmp_path: Path, command: str) -> None:
    tiny, big, size = recordings

    def args(path: Path, out: str) -> list[str]:
        if command == "replay":
            return ["replay", str(path), "--json", "--no-score", "--policy", "all"]
        return ["scene", "import", str(path), "--out", str(tmp_path / out), "--json",
                "--fps", "33"]

    r, peak = _run(0, *args(tiny, "tiny"))
    assert r.returncode == 0 and peak, r.stderr[-2000:]
    cap = peak + size // 4
    r, _ = _run(cap, *args(big, "big"))
    assert r.returncode == 0, f"under {cap >> 20} MiB ({size >> 20} MiB file): {r.stderr[-3000:]}"
    doc = json.loads(r.stdout)
    if command == "replay":
        assert doc["decisions"] == 500 and doc["selections_equal"] == 500
    else:
        assert doc["n_frames"] > 400 and len(doc["cameras"]) == 3
