"""A ROS camera rig as the ingest's tests describe it (tests/unit/cores/test_ingest_core.py, the
ingest fuzz, the rig file and the ingest service): a truth camera, a camera posed by a topic and
one by a fixed pose, and the robot's clock."""

from __future__ import annotations

import copy

import numpy as np

from aoi3d.scene import look_at

W, H = 24, 18

EPOCH = 1_700_000_000.0
T0 = EPOCH + 100.0  # the robot's stamps: 100 s into the run
C2W = look_at((0.0, -4.0, 1.0), (0.0, 0.0, 0.5))
OPTICAL = np.diag([1.0, -1.0, -1.0, 1.0])
GID = bytes(range(16))
INTR = {"fx": 20.0, "fy": 20.0, "cx": W / 2, "cy": H / 2, "width": W, "height": H}


def rig_doc(**over) -> dict:
    doc = {
        "source": {"format": "rmw_zenoh", "domain_id": 0},
        "cameras": [
            {"name": "truth", "image": "/truth/image_raw", "intrinsics": INTR,
             "pose": {"c2w": C2W.ravel().tolist()}},
            {"name": "cam1", "image": "/cam1/image_raw",
             "intrinsics": {"camera_info": "/cam1/camera_info"},
             "pose": {"topic": "/cam1/pose", "type": "PoseStamped"}},
            {"name": "cam2", "image": "/cam2/image_raw/compressed", "intrinsics": INTR,
             "pose": {"c2w": C2W.ravel().tolist()}},
        ],
        "truth": "truth", "aabb": [-2, -2, -1, 2, 2, 2],
    }
    doc.update(over)
    return copy.deepcopy(doc)
