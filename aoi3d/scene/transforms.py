"""A transforms JSON (D-NeRF / nerfstudio) read into a fixed rig's cameras: its frames parsed
(:func:`parse_frames`), grouped into cameras (:func:`group_frames`), ordered in time
(:func:`ordered_frames`), and each camera's intrinsics (:func:`group_intrinsics`). The rules
are set out in :mod:`aoi3d.scene.dnerf`, the reader that uses them."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
from PIL import Image

log = logging.getLogger("aoi3d.scene.dnerf")  # the reader's logger, as before the split

DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


@dataclass
class Frame:
    split: str
    file_relpath: str
    time: float | None
    c2w: np.ndarray
    intrinsics: dict[str, Any]
    camera_id: int | None
    frame_index: int | None


@dataclass
class Group:
    key: Any
    split: str
    frames: list[Frame] = field(default_factory=list)


def read_doc(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON: {exc}") from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list):
        raise ValueError(f"{path} has no 'frames' list; not a transforms file")
    if not doc["frames"]:
        raise ValueError(f"{path} has no frames")
    return doc


INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y",
                   *DISTORTION_KEYS)


def resolve_file(file_path: str) -> str:
    rel = file_path[2:] if file_path.startswith("./") else file_path
    return rel if Path(rel).suffix else rel + ".png"


def parse_frames(doc: dict[str, Any], split: str, source: Path) -> list[Frame]:
    out = []
    for i, entry in enumerate(doc["frames"]):
        what = f"{source.name} frame {i}"
        try:
            c2w = np.asarray(entry["transform_matrix"], dtype=np.float64)
            file_path = str(entry["file_path"])
        except KeyError as exc:
            raise ValueError(f"{what} lacks {exc.args[0]!r}") from exc
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{what}: transform_matrix is not a 4×4 matrix ({exc})") from exc
        if c2w.shape != (4, 4):
            raise ValueError(f"{what}: transform_matrix must be 4×4, got shape {c2w.shape}")
        time = entry.get("time")
        try:
            time = None if time is None else float(time)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{what}: time must be a number, got {time!r}") from exc
        if time is not None and not -1e-9 <= time <= 1 + 1e-9:
            raise ValueError(f"{what}: time must be in [0, 1], got {time}")
        intrinsics = {k: entry.get(k, doc.get(k)) for k in INTRINSIC_KEYS}
        out.append(Frame(
            split=split, file_relpath=resolve_file(file_path),
            time=time, c2w=c2w, intrinsics=intrinsics,
            camera_id=None if entry.get("camera_id") is None else int(entry["camera_id"]),
            frame_index=None if entry.get("frame_index") is None else int(entry["frame_index"]),
        ))
    return out


def pose_key(frame: Frame) -> tuple[Any, ...]:
    intr = tuple(frame.intrinsics[k] for k in INTRINSIC_KEYS)
    return (tuple(np.round(frame.c2w, 9).ravel().tolist()), intr)


def group_frames(frames: list[Frame], by_camera_id: bool) -> list[Group]:
    """Groups in order of first appearance; a key already seen in an earlier split is
    dropped for later splits."""
    groups: dict[Any, Group] = {}
    for frame in frames:
        key = frame.camera_id if by_camera_id else pose_key(frame)
        group = groups.get(key)
        if group is None:
            groups[key] = Group(key=key, split=frame.split, frames=[frame])
        elif group.split == frame.split:
            group.frames.append(frame)
        else:
            log.debug("camera %r of split %s already read from %s", key, frame.split,
                      group.split)
    return list(groups.values())


def group_intrinsics(group: Group, root: Path) -> tuple[float, float, float, float, int, int]:
    intr = group.frames[0].intrinsics
    what = f"camera of {group.frames[0].file_relpath}"
    distortion = {k: intr[k] for k in DISTORTION_KEYS if intr.get(k)}
    if distortion:
        raise ValueError(f"{what}: lens distortion {distortion} is not supported (pinhole "
                         "cameras only); undistort the images first")
    w, h = intr.get("w"), intr.get("h")
    if w is None or h is None:
        path = root / group.frames[0].file_relpath
        if not path.is_file():
            raise FileNotFoundError(f"{what}: image {path} is missing (needed for its size)")
        with Image.open(path) as img:
            w, h = img.size
    if intr.get("fl_x") is not None:
        fx = float(intr["fl_x"])
        fy = float(intr["fl_y"]) if intr.get("fl_y") is not None else fx
    elif intr.get("camera_angle_x") is not None:
        fx = 0.5 * float(w) / np.tan(0.5 * float(intr["camera_angle_x"]))
        angle_y = intr.get("camera_angle_y")
        fy = 0.5 * float(h) / np.tan(0.5 * float(angle_y)) if angle_y is not None else fx
    else:
        raise ValueError(f"{what}: no focal length (need fl_x or camera_angle_x)")
    cx = float(intr["cx"]) if intr.get("cx") is not None else w / 2.0
    cy = float(intr["cy"]) if intr.get("cy") is not None else h / 2.0
    return fx, fy, cx, cy, int(w), int(h)


def ordered_frames(group: Group) -> list[Frame]:
    frames = group.frames
    if all(f.frame_index is not None for f in frames):
        indices = [f.frame_index for f in frames]
        if len(set(indices)) != len(indices):
            raise ValueError(f"camera {group.key!r}: repeated frame_index values")
        return sorted(frames, key=lambda f: cast(int, f.frame_index))
    if all(f.time is not None for f in frames):
        return sorted(frames, key=lambda f: cast(float, f.time))
    return frames
