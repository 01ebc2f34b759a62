"""The scene dataset on disk: its layout, loading, frame access.

Layout under ``root`` (D-NeRF / nerfstudio style)::

    frames/camNN/FFFF.png        uint8 RGB, camera NN (00 = held-out), frame FFFF
    transforms_train.json        cameras 1..N
    transforms_test.json         camera 0

Each JSON holds ``camera_angle_x, fl_x, fl_y, cx, cy, w, h`` (shared intrinsics; a frame
whose camera differs carries its own), ``frames: [{file_path, time, transform_matrix,
camera_id, frame_index}]`` with ``time = frame_index / n_frames`` ∈ [0, 1) and
``file_path`` relative to ``root``, and an ``aoi3d`` block (fps, n_frames, aabb, the scene
config and its hash). :func:`load_dataset` needs nothing but these files.

:class:`SceneDataset` is also the interface (and base class) of the readers of other layouts
(:mod:`aoi3d.scene.dnerf`, :mod:`aoi3d.scene.dynerf`; :func:`aoi3d.scene.open_dataset`).

Writing (generating the turbine's frames, or writing frames that exist) lives in
:mod:`aoi3d.scene.write`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from aoi3d.scene.camera import Camera
from aoi3d.scene.placement import HELDOUT_ID
from aoi3d.scene.turbine import SceneConfig

__all__ = [
    "FORMAT_VERSION",
    "LAYOUT",
    "TEST_JSON",
    "TRAIN_JSON",
    "DatasetError",
    "DatasetNotFound",
    "Progress",
    "SceneDataset",
    "generate_command",
    "load_dataset",
]

FORMAT_VERSION = 1
LAYOUT = "aoi3d"
"""The name of the project's own on-disk layout (see :func:`aoi3d.scene.detect_layout`)."""
TRAIN_JSON = "transforms_train.json"
TEST_JSON = "transforms_test.json"

Progress = Callable[[int, int], None]
"""``progress(done, total)`` in frames (all cameras together)."""

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"
"""A PNG file's first 8 and last 12 bytes (its signature and the empty ``IEND`` chunk): a file
without them is not a PNG or was cut short."""


class DatasetError(ValueError):
    """A dataset that cannot be used as it is.

    ``str(err)`` is one line that names the file (also in :attr:`path`) and says what to do;
    the commands and the services print that line and exit non-zero, no traceback. Readers
    raise it (or :class:`DatasetNotFound`) for a missing folder or file, a file that is not
    valid JSON, a folder of no known layout, a frame that is missing, empty or cut short.
    """

    def __init__(self, message: str, *, path: str | Path | None = None) -> None:
        super().__init__(" ".join(str(message).split()))
        self.path = None if path is None else Path(path)


class DatasetNotFound(DatasetError, FileNotFoundError):
    """The dataset folder, or a file it needs, is not there (also a ``FileNotFoundError``)."""


def generate_command(root: str | Path, config: dict[str, Any] | None = None) -> str:
    """The ``aoi3d scene generate`` command that writes the scene of ``config`` (a
    :class:`SceneConfig` as a dict; default: the default framing's scene) to ``root``: only
    the options that differ from the command's defaults (those of the framing's scene,
    :data:`aoi3d.scene.framings.FRAMING_SCENES`)."""
    from aoi3d.scene.framings import DEFAULT_FRAMING, FRAMING_SCENES

    config = dict(config or {})
    framing = config.get("framing", DEFAULT_FRAMING)
    parts = ["aoi3d scene generate", "--out", str(root)]
    if framing != DEFAULT_FRAMING:
        parts += ["--framing", str(framing)]
    default = (FRAMING_SCENES.get(framing) or SceneConfig(framing=framing)).to_dict()
    for key, value in config.items():
        if key != "framing" and key in default and value != default[key]:
            text = f"{value:g}" if isinstance(value, float) else str(value)
            parts += [f"--{key.replace('_', '-')}", text]
    return " ".join(parts)


def _short_list(items: list[str], shown: int = 3) -> str:
    more = f" and {len(items) - shown} more" if len(items) > shown else ""
    return ", ".join(items[:shown]) + more


def frame_file_relpath(camera_id: int, frame_index: int) -> str:
    return f"frames/cam{camera_id:02d}/{frame_index:04d}.png"


@dataclass(frozen=True, eq=False)
class SceneDataset:
    """A dynamic scene seen by a fixed camera rig: cameras, timing and frame access.

    This is the interface every reader presents to the services and to experiments (the
    project's own layout here, :mod:`aoi3d.scene.dnerf` and :mod:`aoi3d.scene.dynerf` for the
    D-NeRF/nerfstudio and DyNeRF layouts, :func:`aoi3d.scene.open_dataset` to pick one):
    camera ids are ``0..len(cameras)-1``, :attr:`heldout_id` is the novel view, every camera
    has every frame ``0..n_frames-1``. This class reads the project's own layout (one PNG per
    camera and frame, ``frames/camNN/FFFF.png``); readers of other layouts subclass it and
    override :meth:`frame_relpath`, :meth:`frame`, :meth:`frame_png` and
    :meth:`missing_frames` as needed.
    """

    root: Path
    fps: int
    n_frames: int
    width: int
    height: int
    cameras: list[Camera]
    """Index = camera id; id :attr:`heldout_id` is the held-out novel view."""
    aabb: np.ndarray
    train_ids: list[int]
    config: dict[str, Any] = field(default_factory=dict)
    """The generating :class:`SceneConfig` as a dict; empty for datasets from elsewhere."""
    config_hash: str = ""
    heldout_id: int = HELDOUT_ID
    layout: str = LAYOUT
    """Which on-disk layout this was read from: ``aoi3d``, ``dnerf`` or ``dynerf``."""
    camera_names: tuple[str, ...] = ()
    """The source's name of each camera (e.g. ``cam03`` in DyNeRF); empty = ``camNN``."""
    imported: dict[str, Any] = field(default_factory=dict)
    """Where an imported dataset's frames came from (``aoi3d scene import``); else empty."""

    @property
    def duration_ms(self) -> float:
        """Length of one loop of the scene, in ms."""
        return self.n_frames * 1000.0 / self.fps

    def frame_index(self, time_ms: float) -> int:
        """The frame shown at ``time_ms`` (looped): ``floor(time_ms·fps/1000) mod n_frames``."""
        # The tiny epsilon keeps k·1000/fps on frame k despite float rounding.
        return math.floor(time_ms * self.fps / 1000.0 + 1e-9) % self.n_frames

    def scene_time_ms(self, time_ms: float) -> float:
        """Scene time (ms, within the loop) of the frame shown at ``time_ms``."""
        return self.frame_index(time_ms) * 1000.0 / self.fps

    def camera_name(self, camera_id: int) -> str:
        """The source's name of a camera (``camNN`` unless the reader recorded another)."""
        self._check(camera_id, 0)
        return self.camera_names[camera_id] if self.camera_names else f"cam{camera_id:02d}"

    def frame_time(self, camera_id: int, frame_index: int) -> float:
        """Capture time of a frame as a fraction of the loop (the D-NeRF ``time``), [0, 1]."""
        self._check(camera_id, frame_index)
        return frame_index / self.n_frames

    def _check(self, camera_id: int, frame_index: int) -> None:
        if not 0 <= camera_id < len(self.cameras):
            raise ValueError(f"camera_id must be in [0, {len(self.cameras)}), got {camera_id}")
        if not 0 <= frame_index < self.n_frames:
            raise ValueError(f"frame_index must be in [0, {self.n_frames}), got {frame_index}")

    def frame_relpath(self, camera_id: int, frame_index: int) -> str:
        """Path, relative to :attr:`root`, of the file that holds a frame."""
        self._check(camera_id, frame_index)
        return frame_file_relpath(camera_id, frame_index)

    def frame_path(self, camera_id: int, frame_index: int) -> Path:
        """Absolute path of the file that holds a frame (raises ``ValueError`` on bad ids)."""
        return self.root / self.frame_relpath(camera_id, frame_index)

    def fix_hint(self) -> str:
        """What to do about a missing or damaged file of this dataset (the end of a
        :class:`DatasetError`'s line)."""
        if self.layout == LAYOUT and self.config:
            return f"regenerate the dataset: {generate_command(self.root, self.config)} --force"
        return (f"restore the file from where the {self.layout} dataset came from (or export "
                "it again with `aoi3d scene export`)")

    def frame_png(self, camera_id: int, frame_index: int) -> bytes:
        """The frame as PNG bytes (here: the PNG file's bytes, as stored).

        Raises :class:`DatasetNotFound` / :class:`DatasetError` (naming the file) when the file
        is missing, unreadable or not a whole PNG (signature and end chunk are checked)."""
        path = self.frame_path(camera_id, frame_index)
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            raise DatasetNotFound(f"{path}: frame file is missing; {self.fix_hint()}",
                                  path=path) from None
        except OSError as err:
            raise DatasetError(f"{path}: frame file cannot be read ({err.strerror or err}); "
                               f"{self.fix_hint()}", path=path) from None
        problem = png_problem(data[:8], data[-12:], len(data))
        if problem:
            raise DatasetError(f"{path}: {problem}; {self.fix_hint()}", path=path)
        return data

    def frame(self, camera_id: int, frame_index: int) -> np.ndarray:
        """The decoded frame: uint8 (H, W, 3). Raises :class:`DatasetError` (naming the
        file) when it cannot be read or decoded."""
        data = self.frame_png(camera_id, frame_index)
        try:
            with Image.open(BytesIO(data)) as img:
                return np.asarray(img.convert("RGB"), dtype=np.uint8)
        except (OSError, SyntaxError, ValueError) as err:  # PIL's errors for broken images
            path = self.frame_path(camera_id, frame_index)
            raise DatasetError(f"{path}: frame cannot be decoded ({err}); {self.fix_hint()}",
                               path=path) from None

    def missing_frames(self) -> int:
        """How many of the frame files listed by the dataset are absent."""
        return sum(
            not self.frame_path(c, k).is_file()
            for c in range(len(self.cameras))
            for k in range(self.n_frames)
        )

    def check_frames(self, *, decode: int = 1) -> list[tuple[Path, str]]:
        """Every frame file's problems, as ``(path, what)``: missing, empty, or (PNG files)
        without a PNG's first or last bytes, i.e. not a PNG or cut short. Then ``decode``
        frames spread over the cameras are decoded too. Empty when all is well.

        Reads 20 bytes of each file: ≈ 0.1 s of CPU for 19 cameras × 300 frames."""
        problems: list[tuple[Path, str]] = []
        seen: set[str] = set()
        for c in range(len(self.cameras)):
            for k in range(self.n_frames):
                rel = self.frame_relpath(c, k)
                if rel in seen:
                    continue
                seen.add(rel)
                path = self.root / rel
                what = _file_problem(path)
                if what:
                    problems.append((path, what))
        if problems or decode < 1:
            return problems
        n = len(self.cameras)
        for i in range(decode):
            c, k = (self.heldout_id + i) % n, (i * 7919) % self.n_frames
            try:
                self.frame(c, k)
            except DatasetError as err:
                problems.append((err.path or self.frame_path(c, k), str(err)))
        return problems

    def require_frames(self, *, decode: int = 1) -> SceneDataset:
        """Raise :class:`DatasetError` (one line naming the bad files and what to do) unless
        :meth:`check_frames` finds nothing; returns self."""
        problems = self.check_frames(decode=decode)
        if problems:
            missing = [p for p, what in problems if what == "missing"]
            cls = DatasetNotFound if len(missing) == len(problems) else DatasetError
            files = _short_list([f"{p.relative_to(self.root) if p.is_relative_to(self.root) else p}"
                                 f" ({what if len(what) < 60 else 'cannot be decoded'})"
                                 for p, what in problems])
            raise cls(f"{self.root}: {len(problems)} frame file(s) missing or damaged: {files}; "
                      f"{self.fix_hint()}", path=problems[0][0])
        return self

    def scene_config(self) -> SceneConfig:
        """The :class:`SceneConfig` this dataset was generated from (aoi3d layout only)."""
        if not self.config:
            raise ValueError(
                f"{self.root}: a {self.layout} dataset has no aoi3d scene config "
                "(only datasets generated by aoi3d do)"
            )
        return SceneConfig.from_dict(self.config)


def png_problem(head: bytes, tail: bytes, size: int) -> str:
    if size == 0:
        return "frame file is empty"
    if head != PNG_SIGNATURE:
        return "frame file is not a PNG"
    if tail != PNG_END:
        return "frame file is cut short (a truncated PNG)"
    return ""


def _file_problem(path: Path) -> str:
    """``""`` if ``path`` looks whole, else what is wrong (PNG files: first and last bytes)."""
    try:
        size = path.stat().st_size
        if path.suffix.lower() != ".png" or size == 0:
            return "" if size else "empty"
        with open(path, "rb") as f:
            head = f.read(8)
            f.seek(max(0, size - 12))
            tail = f.read(12)
    except FileNotFoundError:
        return "missing"
    except OSError as err:
        return f"unreadable ({err.strerror or err})"
    problem = png_problem(head, tail, size)
    return {"frame file is not a PNG": "not a PNG",
            "frame file is cut short (a truncated PNG)": "truncated"}.get(problem, problem)


# =============================================================================================
# Reading
# =============================================================================================
def _regenerate(root: Path, config: Any = None) -> str:
    if isinstance(config, dict):
        return f"regenerate it: {generate_command(root, config)} --force"
    return f"regenerate it: {generate_command(root)} --force (with the scene's options)"


def _read_json(path: Path, config: Any = None) -> dict[str, Any]:
    """A transforms file's JSON; ``config``: the scene config, if known, for the hint."""
    if not path.is_file():
        raise DatasetNotFound(f"no scene dataset here: {path} is missing; generate one with "
                              f"`{generate_command(path.parent)}`", path=path)
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path} is not valid JSON ({exc}); "
                           f"{_regenerate(path.parent, config)}", path=path) from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("aoi3d"), dict):
        raise DatasetError(f"{path} has no 'aoi3d' block; not an aoi3d scene dataset: "
                           f"{_regenerate(path.parent, config)}", path=path)
    if doc["aoi3d"].get("format_version") != FORMAT_VERSION:
        raise DatasetError(
            f"{path}: format_version {doc['aoi3d'].get('format_version')!r}, "
            f"expected {FORMAT_VERSION}; {_regenerate(path.parent, config)}", path=path
        )
    return doc


def _cameras_of(doc: dict[str, Any], source: Path) -> dict[int, Camera]:
    cams: dict[int, Camera] = {}
    try:
        for entry in doc["frames"]:
            cam_id = int(entry["camera_id"])
            if cam_id in cams:
                continue
            cam = Camera(
                c2w=np.asarray(entry["transform_matrix"], dtype=np.float64),
                fx=entry.get("fl_x", doc["fl_x"]),
                fy=entry.get("fl_y", doc["fl_y"]),
                cx=entry.get("cx", doc["cx"]),
                cy=entry.get("cy", doc["cy"]),
                width=entry.get("w", doc["w"]),
                height=entry.get("h", doc["h"]),
            )
            cam.validate()
            cams[cam_id] = cam
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{source}: malformed frames/intrinsics ({exc!r}); "
                           f"{_regenerate(source.parent)}", path=source) from exc
    return cams


def load_dataset(path: str | Path) -> SceneDataset:
    """Read a dataset from its two transforms files (no scene code involved)."""
    root = Path(path).absolute()

    train = _read_json(root / TRAIN_JSON)
    meta = train["aoi3d"]

    def bad(what: str) -> DatasetError:
        return DatasetError(f"{root / TRAIN_JSON}: {what}; {_regenerate(root, meta.get('config'))}",
                            path=root / TRAIN_JSON)

    test = _read_json(root / TEST_JSON, meta.get("config"))
    if test["aoi3d"].get("config_hash") != meta.get("config_hash"):
        raise bad("train and test transforms come from different configs")
    train_cams = _cameras_of(train, root / TRAIN_JSON)
    test_cams = _cameras_of(test, root / TEST_JSON)
    if set(train_cams) & set(test_cams):
        raise bad(f"cameras {sorted(set(train_cams) & set(test_cams))} in both")
    all_cams = {**train_cams, **test_cams}
    if sorted(all_cams) != list(range(len(all_cams))):
        raise bad(f"camera ids must be 0..N, got {sorted(all_cams)}")
    try:
        heldout = int(meta.get("heldout_id", HELDOUT_ID))
    except (TypeError, ValueError) as exc:
        raise bad(f"malformed heldout_id ({exc!r})") from exc
    if heldout not in test_cams:
        raise bad(f"held-out camera {heldout} not in {TEST_JSON}")
    try:
        aabb = np.asarray(meta["aabb"], dtype=np.float64)
        fps, n_frames = int(meta["fps"]), int(meta["n_frames"])
        config, config_hash = dict(meta["config"]), str(meta["config_hash"])
    except (KeyError, TypeError, ValueError) as exc:
        raise bad(f"malformed 'aoi3d' block ({exc!r})") from exc
    if aabb.shape != (2, 3) or not np.all(aabb[0] < aabb[1]):
        raise bad(f"aabb must be (2, 3) with min < max, got {aabb.tolist()}")
    if fps < 1 or n_frames < 1:
        raise bad(f"fps and n_frames must be ≥ 1, got {fps}, {n_frames}")
    cameras = [all_cams[i] for i in range(len(all_cams))]
    return SceneDataset(
        root=root,
        fps=fps,
        n_frames=n_frames,
        width=cameras[heldout].width,
        height=cameras[heldout].height,
        cameras=cameras,
        aabb=aabb,
        train_ids=sorted(train_cams),
        config=config,
        config_hash=config_hash,
        heldout_id=heldout,
        imported=dict(meta.get("imported") or {}),
    )
