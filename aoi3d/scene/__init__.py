"""Synthetic dynamic scenes, the camera rig, and the dataset readers/writers.

The scene is a wind turbine whose three blades turn at ``rotor_rpm`` on a textured field
under a sky, rendered by exact analytic ray casting (:class:`TurbineScene`). Camera 0 of the
rig (:func:`place_cameras`) is the held-out novel view; 1..N train. :func:`ensure_dataset` writes
(or reuses) the frames and D-NeRF-style transforms; :func:`load_dataset` reads them back.
Datasets researchers already have — DyNeRF videos (:mod:`aoi3d.scene.dynerf`), D-NeRF /
nerfstudio transforms (:mod:`aoi3d.scene.dnerf`) — open with :func:`open_dataset`, which
detects the layout; every reader presents the same :class:`SceneDataset` interface.
:func:`write_dataset` writes frames that already exist (a recording's, ``aoi3d scene
import``) in the project's layout.
"""

from aoi3d.scene.camera import Camera, look_at
from aoi3d.scene.dataset import (
    DatasetError,
    DatasetNotFound,
    Progress,
    SceneDataset,
    generate_command,
    load_dataset,
)
from aoi3d.scene.dnerf import DNeRFDataset, export_dnerf, load_dnerf
from aoi3d.scene.dynerf import DyNeRFDataset, export_dynerf, load_dynerf
from aoi3d.scene.layouts import (
    EXPORT_FORMATS,
    LAYOUTS,
    detect_layout,
    export_dataset,
    open_dataset,
)
from aoi3d.scene.placement import HELDOUT_ID, place_cameras
from aoi3d.scene.turbine import SCENE_VERSION, SceneConfig, TurbineScene, to_uint8
from aoi3d.scene.write import ensure_dataset, generate_dataset, write_dataset

__all__ = [
    "EXPORT_FORMATS",
    "HELDOUT_ID",
    "LAYOUTS",
    "SCENE_VERSION",
    "Camera",
    "DNeRFDataset",
    "DatasetError",
    "DatasetNotFound",
    "DyNeRFDataset",
    "Progress",
    "SceneConfig",
    "SceneDataset",
    "TurbineScene",
    "detect_layout",
    "ensure_dataset",
    "export_dataset",
    "export_dnerf",
    "export_dynerf",
    "generate_command",
    "generate_dataset",
    "load_dataset",
    "load_dnerf",
    "load_dynerf",
    "look_at",
    "open_dataset",
    "place_cameras",
    "to_uint8",
    "write_dataset",
]
