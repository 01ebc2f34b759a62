"""``aoi3d`` — the command line, the composition root for commands.

Each command group lives in its own module and is mounted here. The modules import only what
their options need (typer, rich, the light scene package); torch, the experiment engine and
the services load inside the commands that use them, so ``import aoi3d_cli`` and
``aoi3d --help`` stay fast (a test checks both).

A dataset that cannot be read (:class:`aoi3d.scene.DatasetError`) ends any command with one
line, ``error: <file>: <what>; <what to do>``, and exit status 1.
"""

from __future__ import annotations

import inspect
from typing import Any

import typer
from typer.core import TyperGroup

from aoi3d.scene.dataset import DatasetError
from aoi3d_cli import channel, experiment, export, field, live, ppo, replay, ros2, scene, up
from aoi3d_cli.common import fail


class _Root(TyperGroup):
    """The ``aoi3d`` group: every command's :class:`DatasetError` becomes one line."""

    # typer.Context: the context typer makes (public), narrower than the base's parameter
    def invoke(self, ctx: typer.Context) -> Any:  # type: ignore[override]
        try:
            return super().invoke(ctx)
        except DatasetError as err:
            fail(err)


app = typer.Typer(
    name="aoi3d",
    help="Timeliness–fidelity tradeoff in real-time 3D scene representation.",
    no_args_is_help=True,
    add_completion=False,
    cls=_Root,
)
app.add_typer(scene.app, name="scene", help="Generate and inspect the synthetic dynamic scene.")
app.add_typer(channel.app, name="channel", help="Simulate the cameras' D/G/1/0 uplinks and AoI.")
app.add_typer(field.app, name="field", help="Radiance-field backends: list, train and score.")
app.add_typer(experiment.app, name="experiment",
              help="Reproduce the paper's tradeoff figures on a virtual clock.")
app.add_typer(ppo.app, name="ppo", help="Train and evaluate the single-step PPO agent.")
app.add_typer(live.app, name="live", help="Drive and measure the running pipeline.")
app.add_typer(ros2.app, name="ros2", help="Real cameras: ROS 2 over Zenoh (a robot that plays a "
                                          "dataset; rig files).")
app.command("up", help=inspect.getdoc(up.up),
            short_help="Run the Zenoh router and the services locally until Ctrl-C.")(up.up)
app.command("export", help=inspect.getdoc(export.export),
            short_help="Write a site's latest reconstruction as a .ply (points or mesh).")(
    export.export)
app.command("replay", help=inspect.getdoc(replay.replay),
            short_help="Re-run a recording on the virtual clock under any policy.")(
    replay.replay)


def main() -> None:
    app()
