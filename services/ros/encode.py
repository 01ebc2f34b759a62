"""Messages built (the test robot's and the player's side): ``Image``, ``CompressedImage``,
``CameraInfo``, ``PoseStamped`` and ``Odometry`` as rosbags' dataclasses, ready for
:func:`services.ros.cdr.encode_cdr`."""

from __future__ import annotations

import io

import numpy as np

from services.ros.types import (
    CAMERA_INFO,
    COMPRESSED,
    IMAGE,
    ODOMETRY,
    POSE_STAMPED,
    Message,
    typestore,
)

__all__ = ["camera_info_msg", "compressed_bytes_msg", "compressed_msg", "header", "image_msg",
           "odometry_msg", "pose_stamped_msg"]


def header(stamp: float, frame_id: str) -> Message:
    types = typestore().types
    sec = int(np.floor(stamp))
    nsec = min(round((stamp - sec) * 1e9), 999_999_999)
    return types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id)


def image_msg(stamp: float, frame_id: str, rgb: np.ndarray, encoding: str = "rgb8") -> Message:
    """A ``sensor_msgs/Image`` of an RGB uint8 image (``rgb8`` or ``bgr8``)."""
    arr = np.ascontiguousarray(rgb[:, :, ::-1] if encoding == "bgr8" else rgb, dtype=np.uint8)
    h, w = arr.shape[:2]
    return typestore().types[IMAGE](header=header(stamp, frame_id), height=h, width=w,
                                 encoding=encoding, is_bigendian=0, step=w * 3,
                                 data=arr.reshape(-1))


def compressed_msg(stamp: float, frame_id: str, rgb: np.ndarray, fmt: str = "jpeg") -> Message:
    """A ``sensor_msgs/CompressedImage`` (``jpeg`` quality 95, or ``png``)."""
    from PIL import Image as PILImage

    buf = io.BytesIO()
    im = PILImage.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8), "RGB")
    if fmt == "png":
        im.save(buf, format="PNG", compress_level=1)
    else:
        im.save(buf, format="JPEG", quality=95)
    return typestore().types[COMPRESSED](header=header(stamp, frame_id), format=fmt,
                                      data=np.frombuffer(buf.getvalue(), dtype=np.uint8))


def compressed_bytes_msg(stamp: float, frame_id: str, data: bytes, fmt: str) -> Message:
    """A ``sensor_msgs/CompressedImage`` of image bytes already encoded as ``fmt``."""
    return typestore().types[COMPRESSED](header=header(stamp, frame_id), format=fmt,
                                      data=np.frombuffer(data, dtype=np.uint8))


def camera_info_msg(stamp: float, frame_id: str, fx: float, fy: float, cx: float, cy: float,
                    width: int, height: int) -> Message:
    types = typestore().types
    k = np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], dtype=np.float64)
    p = np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], dtype=np.float64)
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                    do_rectify=False)
    return types[CAMERA_INFO](header=header(stamp, frame_id), height=height, width=width,
                              distortion_model="plumb_bob", d=np.zeros(5), k=k,
                              r=np.eye(3).reshape(-1), p=p, binning_x=0, binning_y=0, roi=roi)


def _pose(m: np.ndarray) -> Message:
    from scipy.spatial.transform import Rotation

    types = typestore().types
    x, y, z, w = Rotation.from_matrix(m[:3, :3]).as_quat()
    return types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=float(m[0, 3]), y=float(m[1, 3]),
                                                  z=float(m[2, 3])),
        orientation=types["geometry_msgs/msg/Quaternion"](x=float(x), y=float(y), z=float(z),
                                                          w=float(w)))


def pose_stamped_msg(stamp: float, frame_id: str, m: np.ndarray) -> Message:
    return typestore().types[POSE_STAMPED](header=header(stamp, frame_id), pose=_pose(m))


def odometry_msg(stamp: float, frame_id: str, child: str, m: np.ndarray) -> Message:
    types = typestore().types
    cov = np.zeros(36)
    vec = types["geometry_msgs/msg/Vector3"]
    return types[ODOMETRY](
        header=header(stamp, frame_id), child_frame_id=child,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=_pose(m), covariance=cov),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](linear=vec(x=0.0, y=0.0, z=0.0),
                                                   angular=vec(x=0.0, y=0.0, z=0.0)),
            covariance=cov))
