"""The project's two scenes, by framing, and the folders their datasets are generated in.

``rotor`` — the turbine's rotor in close-up, turning at 6 rpm: the scene of the experiments
(:data:`aoi3d.experiment.config.EXPERIMENT_SCENE`, where the reasons are given) and of the live
pipeline (``aoi3d up``, compose). ``site`` — the whole turbine, its ground and the hut at the
default 18 rpm (``SceneConfig()``), one option away (``aoi3d up --framing site``).

Kept here, in the light scene package, so that the command line knows them without importing
the experiment engine (and torch).
"""

from __future__ import annotations

from aoi3d.scene.turbine import SceneConfig

__all__ = ["DEFAULT_FRAMING", "FRAMING_DATASETS", "FRAMING_SCENES"]

FRAMING_SCENES: dict[str, SceneConfig] = {
    "rotor": SceneConfig(framing="rotor", rotor_rpm=6.0),
    "site": SceneConfig(),
}
"""The scene config of each framing."""
FRAMING_DATASETS: dict[str, str] = {
    "rotor": "data/turbine-rotor",
    "site": "data/turbine",
}
"""Where each framing's dataset is generated (relative to the working directory)."""
DEFAULT_FRAMING = "rotor"
"""The framing ``aoi3d up``, compose and the experiments run on by default."""
