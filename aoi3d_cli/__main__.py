"""``python -m aoi3d_cli`` — the same as the ``aoi3d`` command."""

from aoi3d_cli import main

main()
