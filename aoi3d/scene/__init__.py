"""Synthetic dynamic scenes, the camera rig, and the dataset readers/writers.

The scene is a wind turbine whose three blades turn at ``rotor_rpm`` on a textured field
under a sky, rendered by exact analytic ray casting (:class:`TurbineScene`). Camera 0 of the
rig (:func:`make_rig`) is the held-out novel view; 1..N train. :func:`ensure_dataset` writes
(or reuses) the frames and D-NeRF-style transforms; :func:`load_dataset` reads them back.
"""

from aoi3d.scene.camera import Camera, look_at
from aoi3d.scene.dataset import (
    Progress,
    SceneDataset,
    ensure_dataset,
    generate_dataset,
    load_dataset,
)
from aoi3d.scene.rig import HELDOUT_ID, make_rig
from aoi3d.scene.turbine import SCENE_VERSION, SceneConfig, TurbineScene, to_uint8

__all__ = [
    "HELDOUT_ID",
    "SCENE_VERSION",
    "Camera",
    "Progress",
    "SceneConfig",
    "SceneDataset",
    "TurbineScene",
    "ensure_dataset",
    "generate_dataset",
    "load_dataset",
    "look_at",
    "make_rig",
    "to_uint8",
]
