"""Tests of the command line (aoi3d_cli): its start-up, its checks before `aoi3d up`, and the
commands run through typer's CliRunner."""
