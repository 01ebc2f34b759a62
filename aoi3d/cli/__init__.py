"""``aoi3d`` — the command line, the composition root for commands.

Each command group lives in its own module and is mounted here.
"""

from __future__ import annotations

import typer

from aoi3d.cli import channel, experiment, field, live, ppo, scene, up

app = typer.Typer(
    name="aoi3d",
    help="Timeliness–fidelity tradeoff in real-time 3D scene representation.",
    no_args_is_help=True,
    add_completion=False,
)
app.add_typer(scene.app, name="scene", help="Generate and inspect the synthetic dynamic scene.")
app.add_typer(channel.app, name="channel", help="Simulate the cameras' D/G/1/0 uplinks and AoI.")
app.add_typer(field.app, name="field", help="Radiance-field backends: list, train and score.")
app.add_typer(experiment.app, name="experiment",
              help="Reproduce the paper's tradeoff figures on a virtual clock.")
app.add_typer(ppo.app, name="ppo", help="Train and evaluate the single-step PPO agent.")
app.add_typer(live.app, name="live", help="Drive and measure the running pipeline.")
app.command("up", help=up.up.__doc__)(up.up)


def main() -> None:
    app()
