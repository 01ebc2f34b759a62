"""The turbine scene's configuration: everything that determines the rendered frames.

:class:`SceneConfig` (and its :attr:`~SceneConfig.config_hash`, the dataset cache key) and
:func:`to_uint8`, the one float → 8-bit conversion of the project.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np

from aoi3d.scene.turbine.geometry import BLADES

SCENE_VERSION = 1
"""Bump when the rendered images change for an unchanged config (invalidates cached datasets)."""

FRAMINGS = ("site", "rotor")
"""How the rig frames the scene (:attr:`SceneConfig.framing`)."""


def _is_integral(x: float, tol: float = 1e-6) -> bool:
    return abs(x - round(x)) <= tol


@dataclass(frozen=True)
class SceneConfig:
    """Everything that determines the rendered frames (and hence the dataset).

    The dataset loops (frame ``n_frames`` is shown as frame 0). The loop is seamless when the
    blades come back to an equivalent position, i.e. when ``rotor_rpm · duration_s / 60 · 3``
    (blade passes per loop) is an integer — true for the defaults (9 passes). Other values are
    allowed (the blades then jump once per loop); see :attr:`seamless` and
    :meth:`seamless_rpm`.
    """

    width: int = 96
    height: int = 72
    fps: int = 30
    duration_s: float = 10.0
    n_train: int = 18
    rotor_rpm: float = 18.0
    spp: int = 3
    """Samples per pixel *per axis* (spp × spp stratified samples)."""
    seed: int = 0
    """Seed of the texture noise (not of the geometry or the rig)."""
    framing: str = "site"
    """How the rig frames the turbine (see :mod:`aoi3d.scene.placement`): ``site`` — the whole
    turbine, its ground and the hut from a 170° arc, the blades a few per cent of the pixels;
    ``rotor`` — a close-up of the rotor from a 60° forward-facing arc (the DyNeRF-like capture
    the experiments use), the blades a large share of the pixels."""

    def __post_init__(self) -> None:
        if self.framing not in FRAMINGS:
            raise ValueError(f"framing must be one of {FRAMINGS}, got {self.framing!r}")
        for name in ("width", "height", "fps", "n_train", "spp", "seed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise ValueError(f"{name} must be an int, got {value!r}")
        if self.width < 1 or self.height < 1:
            raise ValueError(f"image size must be positive, got {self.width}×{self.height}")
        if self.fps < 1:
            raise ValueError(f"fps must be ≥ 1, got {self.fps}")
        if self.n_train < 1:
            raise ValueError(f"n_train must be ≥ 1, got {self.n_train}")
        if self.spp < 1:
            raise ValueError(f"spp must be ≥ 1, got {self.spp}")
        if self.seed < 0:
            raise ValueError(f"seed must be ≥ 0, got {self.seed}")
        if not (math.isfinite(self.duration_s) and self.duration_s > 0):
            raise ValueError(f"duration_s must be finite and > 0, got {self.duration_s}")
        if not math.isfinite(self.rotor_rpm):
            raise ValueError(f"rotor_rpm must be finite, got {self.rotor_rpm}")
        frames = self.fps * self.duration_s
        if not _is_integral(frames) or round(frames) < 1:
            raise ValueError(
                f"fps · duration_s must be a positive whole number of frames, got {frames:g}"
            )

    @property
    def blade_passes(self) -> float:
        """Blade passes per loop: ``rotor_rpm · duration_s / 60 · 3``."""
        return self.rotor_rpm * self.duration_s / 60.0 * BLADES

    @property
    def seamless(self) -> bool:
        """Whether the looped frames show no jump of the blades (whole blade passes)."""
        return _is_integral(self.blade_passes)

    def seamless_rpm(self) -> tuple[float, float]:
        """The nearest rotor speeds (rpm, below and above) that make the loop seamless."""
        step = 60.0 / (BLADES * self.duration_s)
        return math.floor(self.blade_passes) * step, math.ceil(self.blade_passes) * step

    @property
    def n_frames(self) -> int:
        """Frames per camera in one loop (``fps · duration_s``)."""
        return round(self.fps * self.duration_s)

    def frame_time_s(self, frame_index: int | np.ndarray) -> float | np.ndarray:
        """Scene time of a frame: ``frame_index / fps``."""
        return np.asarray(frame_index, dtype=np.float64) / self.fps

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> SceneConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError``."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown SceneConfig keys: {unknown}")
        return cls(**dict(data))

    @property
    def config_hash(self) -> str:
        """A short stable hash of the config and :data:`SCENE_VERSION` (dataset cache key)."""
        doc = self.to_dict()
        if doc["framing"] == "site":  # the original framing: datasets made before it stay valid
            del doc["framing"]
        payload = json.dumps({"scene_version": SCENE_VERSION, **doc}, sort_keys=True, default=float)
        return hashlib.sha256(payload.encode()).hexdigest()[:16]


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Float image in [0, 1] → uint8 (clipped, rounded to nearest); uint8 passes through.

    The one float → 8-bit conversion of the project (scene frames, renders on the bus,
    experiment and env renders)."""
    arr = np.asarray(image)
    if arr.dtype == np.uint8:
        return arr
    return np.floor(np.clip(arr, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
