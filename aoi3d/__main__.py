"""``python -m aoi3d`` — the same as the ``aoi3d`` command."""

from aoi3d.cli import main

main()
