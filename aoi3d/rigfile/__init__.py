"""The rig file: real cameras (ROS 2 over Zenoh, IP cameras, videos) instead of the camera
emulators.

``aoi3d up --rig rig.yaml`` reads it, and so do the ingest service (what to subscribe and how to
turn a ROS message into a :class:`pb.Frame`) and the trainer (the view it renders, the scene
box and the working size). YAML or JSON; validated here with pydantic, and every error names
its field (``cameras[2].pose.topic: …``). The format, with an example, is in
docs/real-cameras.md.

Not :mod:`aoi3d.scene.placement`, which places the emulated cameras around the turbine: this
package is the file that describes a real rig.

Pure: pydantic, numpy and the domain's :class:`Camera`; no bus, no server. Its modules:
:mod:`.poses` (pose conventions and quaternions), :mod:`.spec` (a camera's entries: image
source, intrinsics, pose; the source and the clock), :mod:`.model` (the whole file,
:class:`Rig`, and what it derives) and :mod:`.load` (reading and validating, :class:`RigError`).
"""

from aoi3d.rigfile.load import (
    MAX_RIG_BYTES,
    MAX_RIG_CAMERAS,
    MAX_RIG_VALUES,
    RigError,
    load_rig,
    missing_videos,
    rig_from_dict,
)
from aoi3d.rigfile.model import TRUTH_ID, Rig, scaled_camera
from aoi3d.rigfile.poses import CONVENTIONS, convert_pose, quaternion_matrix
from aoi3d.rigfile.spec import (
    CameraSpec,
    ClockSpec,
    IntrinsicsSpec,
    PoseSpec,
    SourceSpec,
    ViewSpec,
)

__all__ = [
    "CONVENTIONS",
    "MAX_RIG_BYTES",
    "MAX_RIG_CAMERAS",
    "MAX_RIG_VALUES",
    "TRUTH_ID",
    "CameraSpec",
    "ClockSpec",
    "IntrinsicsSpec",
    "PoseSpec",
    "Rig",
    "RigError",
    "SourceSpec",
    "ViewSpec",
    "convert_pose",
    "load_rig",
    "missing_videos",
    "quaternion_matrix",
    "rig_from_dict",
    "scaled_camera",
]
