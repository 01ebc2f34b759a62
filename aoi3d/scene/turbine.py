"""The synthetic dynamic scene: a wind turbine on a textured field under a sky.

World is z-up, metres-ish, the turbine stands at the origin and its rotor faces −y (where the
camera rig stands). Everything that can be hit lies inside :attr:`TurbineScene.aabb`:

- a square slab of textured ground (top at z = 0, ``|x|, |y| ≤ GROUND_HALF``),
- a tapered tower (cone frustum), a nacelle (box), a spinner (ellipsoid), a brick hut (box)
  and a rock (ellipsoid) — all static,
- three identical tapered blades (thin trapezoidal prisms) turning at ``rotor_rpm`` about the
  horizontal rotor axis — the only moving part.

A ray that leaves the box without a hit gets :meth:`TurbineScene.background` of its direction
alone: a sky gradient with a sun glow above the horizon, hazy distant fields below it.

Rendering is exact analytic ray casting with ``spp × spp`` stratified samples per pixel (sample
centres of a regular sub-grid, no randomness), averaged in sRGB. Because only the blades move,
the static layer of a camera (colour and depth of every sample) is cast once and cached; a
frame then intersects only the sample rays that can reach the rotor disc with the blades and
keeps whichever hit is nearer (z-compositing). The result equals a full re-render.

Textures are procedural (checkers, stripes, bricks, value noise); the value-noise lattices come
from ``np.random.default_rng(cfg.seed)`` — no global RNG is touched.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np

from aoi3d.scene.camera import Camera

__all__ = [
    "AABB",
    "BLADES",
    "FRAMINGS",
    "ROTOR_AABB",
    "SCENE_VERSION",
    "SceneConfig",
    "TurbineScene",
    "to_uint8",
]

SCENE_VERSION = 1
"""Bump when the rendered images change for an unchanged config (invalidates cached datasets)."""

BLADES = 3
"""Number of (identical) rotor blades: the image repeats every 1/3 revolution."""

# --- geometry (world units, z-up) ------------------------------------------------------------
GROUND_HALF = 2.0
"""Half side of the square textured ground slab (its top is the plane z = 0)."""
AABB = np.array([[-GROUND_HALF, -GROUND_HALF, -0.05], [GROUND_HALF, GROUND_HALF, 2.7]])
"""The box that holds every surface of the scene, (2, 3): rows min, max."""
ROTOR_AABB = np.array([[-1.0, -0.65, 0.55], [1.0, 0.45, 2.6]])
"""The box that holds every surface the ``rotor`` framing can see (the rotor, the spinner, the
nacelle and the top of the tower; the ground lies outside its cameras' view)."""
FRAMINGS = ("site", "rotor")
"""How the rig frames the scene (:attr:`SceneConfig.framing`)."""

TOWER_HEIGHT = 1.62
TOWER_R_BASE = 0.10
TOWER_R_TOP = 0.06
NACELLE_LO = np.array([-0.12, -0.26, 1.55])
NACELLE_HI = np.array([0.12, 0.38, 1.79])
HUB_CENTRE = np.array([0.0, -0.34, 1.67])
"""Centre of the spinner and of the rotor; the blades turn in the plane y = HUB_CENTRE[1]."""
HUB_RADII = np.array([0.10, 0.16, 0.10])
ROTOR_AXIS = np.array([0.0, -1.0, 0.0])
"""Unit rotor axis (pointing from the nacelle towards the rig)."""
ROTOR_E1 = np.array([1.0, 0.0, 0.0])
ROTOR_E2 = np.array([0.0, 0.0, 1.0])
"""In-plane basis of the rotor disc: blade 0 points along ``ROTOR_E2`` (up) at t = 0."""
BLADE_ROOT = 0.06
BLADE_TIP = 0.88
BLADE_HALF_CHORD_ROOT = 0.075
BLADE_HALF_CHORD_TIP = 0.025
BLADE_HALF_THICKNESS = 0.015
HUT_LO = np.array([0.35, 0.10, 0.0])
HUT_HI = np.array([0.65, 0.35, 0.22])
ROCK_CENTRE = np.array([-0.75, -0.45, 0.0])
ROCK_RADII = np.array([0.18, 0.13, 0.11])

# --- light and colours (sRGB in [0, 1]) ------------------------------------------------------
SUN_DIR = np.array([-0.35, -0.55, 0.75]) / np.linalg.norm([-0.35, -0.55, 0.75])
AMBIENT = 0.45
DIFFUSE = 0.55
SKY_HORIZON = np.array([0.86, 0.90, 0.95])
SKY_ZENITH = np.array([0.25, 0.45, 0.82])
FAR_FIELD = np.array([0.36, 0.50, 0.26])

_EPS_T = 1e-9


# =============================================================================================
# Configuration
# =============================================================================================
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
    """How the rig frames the turbine (see :mod:`aoi3d.scene.rig`): ``site`` — the whole
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


# =============================================================================================
# Procedural textures
# =============================================================================================
class _ValueNoise:
    """Periodic 2-D value noise in [0, 1] on a 64×64 lattice, smoothstep-interpolated."""

    SIZE = 64

    def __init__(self, rng: np.random.Generator) -> None:
        self._grid = rng.random((self.SIZE, self.SIZE))

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x0 = np.floor(x)
        y0 = np.floor(y)
        fx = x - x0
        fy = y - y0
        fx = fx * fx * (3.0 - 2.0 * fx)
        fy = fy * fy * (3.0 - 2.0 * fy)
        ix = x0.astype(np.int64) % self.SIZE
        iy = y0.astype(np.int64) % self.SIZE
        jx = (ix + 1) % self.SIZE
        jy = (iy + 1) % self.SIZE
        g = self._grid
        top = g[iy, ix] * (1.0 - fx) + g[iy, jx] * fx
        bottom = g[jy, ix] * (1.0 - fx) + g[jy, jx] * fx
        return top * (1.0 - fy) + bottom * fy

    def fractal(self, x: np.ndarray, y: np.ndarray, octaves: int = 3) -> np.ndarray:
        total = np.zeros_like(x, dtype=np.float64)
        amp, norm, freq = 1.0, 0.0, 1.0
        for k in range(octaves):
            total += amp * self(x * freq + 17.0 * k, y * freq + 31.0 * k)
            norm += amp
            amp *= 0.5
            freq *= 2.0
        return total / norm


def _mix(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Per-row blend of colours ``a`` and ``b`` (each (3,) or (N, 3)) by weights (N,)."""
    w = w[:, None]
    return a * (1.0 - w) + b * w


def _checker(*coords: np.ndarray) -> np.ndarray:
    total = sum(np.floor(c).astype(np.int64) for c in coords)
    return (total % 2).astype(bool)


# =============================================================================================
# Ray–primitive intersections: (origins (N,3), dirs (N,3)) → (t (N,), unit normals (N,3))
# t is +inf on a miss; rays start outside every primitive (cameras stand outside the box).
# =============================================================================================
def _hit_ground(o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[:, 2] / d[:, 2]
    x = o[:, 0] + t * d[:, 0]
    y = o[:, 1] + t * d[:, 1]
    ok = (d[:, 2] < 0) & (o[:, 2] > 0) & (np.abs(x) <= GROUND_HALF) & (np.abs(y) <= GROUND_HALF)
    t = np.where(ok, t, np.inf)
    normal = np.broadcast_to(np.array([0.0, 0.0, 1.0]), o.shape)
    return t, normal


def _hit_box(
    o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    d_safe = np.where(np.abs(d) < 1e-15, 1e-15, d)
    inv = 1.0 / d_safe
    t1 = (lo - o) * inv
    t2 = (hi - o) * inv
    t_near = np.minimum(t1, t2)
    t_far = np.maximum(t1, t2)
    axis = np.argmax(t_near, axis=1)
    t_in = np.take_along_axis(t_near, axis[:, None], axis=1)[:, 0]
    t_out = np.min(t_far, axis=1)
    ok = (t_in <= t_out) & (t_in > _EPS_T)
    t = np.where(ok, t_in, np.inf)
    normal = np.zeros_like(o)
    rows = np.arange(len(o))
    normal[rows, axis] = -np.sign(d_safe[rows, axis])
    return t, normal


def _hit_frustum(
    o: np.ndarray, d: np.ndarray, r_base: float, r_top: float, height: float
) -> tuple[np.ndarray, np.ndarray]:
    """Lateral surface of a vertical cone frustum standing on z = 0 at the origin."""
    a, b = r_base, (r_top - r_base) / height
    ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    r_o = a + b * oz
    qa = dx * dx + dy * dy - b * b * dz * dz
    qb = 2.0 * (ox * dx + oy * dy - r_o * b * dz)
    qc = ox * ox + oy * oy - r_o * r_o
    disc = qb * qb - 4.0 * qa * qc
    t = np.full(len(o), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        sq = np.sqrt(np.maximum(disc, 0.0))
        roots = ((-qb - sq) / (2.0 * qa), (-qb + sq) / (2.0 * qa))
    for root in reversed(roots):  # the nearer root last, so it wins where both are valid
        z = oz + root * dz
        ok = (disc >= 0) & np.isfinite(root) & (root > _EPS_T) & (z >= 0.0) & (z <= height)
        t = np.where(ok & (root < t), root, t)
    p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    normal = np.stack([p[:, 0], p[:, 1], -(a + b * p[:, 2]) * b], axis=1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    return t, normal


def _hit_ellipsoid(
    o: np.ndarray, d: np.ndarray, centre: np.ndarray, radii: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    os_ = (o - centre) / radii
    ds = d / radii
    qa = np.einsum("ij,ij->i", ds, ds)
    qb = 2.0 * np.einsum("ij,ij->i", os_, ds)
    qc = np.einsum("ij,ij->i", os_, os_) - 1.0
    disc = qb * qb - 4.0 * qa * qc
    root = (-qb - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * qa)
    t = np.where((disc >= 0) & (root > _EPS_T), root, np.inf)
    p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    normal = (p - centre) / (radii * radii)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    return t, normal


# =============================================================================================
# Per-camera cached static layer
# =============================================================================================
@dataclass(frozen=True)
class _StaticLayer:
    """The static part of one camera's image, plus what the blades need per frame."""

    height: int
    width: int
    n_sub: int
    image: np.ndarray
    """Static image, float32 (H, W, 3)."""
    cand_pixels: np.ndarray
    """Flat indices (H·W order) of the pixels whose samples may hit a blade, (Pc,)."""
    cand_rgb: np.ndarray
    """Static colour of every sample of those pixels, (Pc, S, 3)."""
    ray_p0: np.ndarray
    """Ray origin in rotor-disc coordinates (e1, e2) for those samples, (2, M), M = Pc·S."""
    ray_d2: np.ndarray
    """Ray direction in rotor-disc coordinates, (2, M)."""
    ray_w: np.ndarray
    """Ray direction along the rotor axis, (M,)."""
    t_lo: np.ndarray
    """Where the ray enters the rotor slab (≥ 0), (M,)."""
    t_hi: np.ndarray
    """Where it leaves the slab or meets the static scene, whichever first, (M,)."""
    ray_alpha: np.ndarray
    """Polar angle (atan2(e1, e2), like the blade angle) of the ray's path in the slab, (M,)."""
    ray_reach: np.ndarray
    """A blade at angle psi can be hit only if |alpha − psi| ≤ reach (wrapped), (M,)."""


def _resolve(samples: np.ndarray) -> np.ndarray:
    """Average over the sample axis (−2) in a fixed order (bit-identical for any batch)."""
    acc = samples[..., 0, :].copy()
    for k in range(1, samples.shape[-2]):
        acc += samples[..., k, :]
    return acc / samples.shape[-2]


# =============================================================================================
# The scene
# =============================================================================================
class TurbineScene:
    """The wind-turbine scene of a :class:`SceneConfig`; renders any :class:`Camera`."""

    def __init__(
        self, cfg: SceneConfig | None = None, *, cache_size: int = 32, _cull: bool = True
    ) -> None:
        self.cfg = cfg if cfg is not None else SceneConfig()
        self._cull = _cull  # False: intersect every ray with every blade (reference path)
        rng = np.random.default_rng(self.cfg.seed)
        self._noise = _ValueNoise(rng)
        self._noise_fine = _ValueNoise(rng)
        self._cache: OrderedDict[Camera, _StaticLayer] = OrderedDict()
        self._cache_size = cache_size
        s = (BLADE_HALF_CHORD_TIP - BLADE_HALF_CHORD_ROOT) / (BLADE_TIP - BLADE_ROOT)
        e_side = BLADE_HALF_CHORD_ROOT - s * BLADE_ROOT
        # Blade outline in its own disc frame (u radial, v chord): rows (n_u, n_v, e), n·(u,v) ≤ e.
        self._blade_edges = np.array(
            [
                [-1.0, 0.0, -BLADE_ROOT],
                [1.0, 0.0, BLADE_TIP],
                [-s, 1.0, e_side],
                [-s, -1.0, e_side],
            ]
        )
        corners = [
            (BLADE_ROOT, BLADE_HALF_CHORD_ROOT),
            (BLADE_TIP, BLADE_HALF_CHORD_TIP),
        ]
        self._rotor_radius = max(math.hypot(u, v) for u, v in corners) + 1e-6
        self._solids: list[
            tuple[
                Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
                Callable[[np.ndarray, np.ndarray], np.ndarray],
            ]
        ] = [
            (_hit_ground, self._albedo_ground),
            (
                lambda o, d: _hit_frustum(o, d, TOWER_R_BASE, TOWER_R_TOP, TOWER_HEIGHT),
                self._albedo_tower,
            ),
            (lambda o, d: _hit_box(o, d, NACELLE_LO, NACELLE_HI), self._albedo_nacelle),
            (lambda o, d: _hit_ellipsoid(o, d, HUB_CENTRE, HUB_RADII), self._albedo_hub),
            (lambda o, d: _hit_box(o, d, HUT_LO, HUT_HI), self._albedo_hut),
            (lambda o, d: _hit_ellipsoid(o, d, ROCK_CENTRE, ROCK_RADII), self._albedo_rock),
        ]

    # -- public API -------------------------------------------------------------------------
    @property
    def aabb(self) -> np.ndarray:
        """The box (2, 3) holding every surface the rig sees; outside it only the background
        remains (the ``rotor`` framing's cameras see only the upper part of the turbine)."""
        return (ROTOR_AABB if self.cfg.framing == "rotor" else AABB).copy()

    def rotor_angle_rad(self, t_s: float | np.ndarray) -> np.ndarray:
        """Rotor angle at scene time ``t_s`` (blade 0 points up at t = 0)."""
        return 2.0 * math.pi * self.cfg.rotor_rpm / 60.0 * np.asarray(t_s, dtype=np.float64)

    def background(self, dirs: np.ndarray) -> np.ndarray:
        """Colour of rays that leave the box without a hit; depends on direction only.

        ``dirs`` (..., 3), unit vectors → float64 (..., 3) sRGB in [0, 1].
        """
        d = np.asarray(dirs, dtype=np.float64)
        shape = d.shape
        d = d.reshape(-1, 3)
        dz = d[:, 2]
        w_sky = np.sqrt(np.clip(dz, 0.0, 1.0))
        sky = _mix(SKY_HORIZON, SKY_ZENITH, w_sky)
        glow = np.clip(d @ SUN_DIR, 0.0, 1.0) ** 48
        sky = sky + 0.3 * glow[:, None]
        azimuth = np.arctan2(d[:, 1], d[:, 0])
        fields_ = 1.0 + 0.12 * np.sin(5.0 * azimuth) + 0.08 * np.sin(13.0 * azimuth + 1.0)
        haze = np.exp(-8.0 * np.clip(-dz, 0.0, 1.0))
        ground = _mix(FAR_FIELD * fields_[:, None], SKY_HORIZON, haze)
        out = np.where((dz >= 0)[:, None], sky, ground)
        return np.clip(out, 0.0, 1.0).reshape(shape)

    def render(self, camera: Camera, t_s: float) -> np.ndarray:
        """The anti-aliased image of ``camera`` at scene time ``t_s``: float32 (H, W, 3)."""
        return self.render_times(camera, [t_s])[0]

    def render_frames(self, camera: Camera, frame_indices: Sequence[int]) -> np.ndarray:
        """Frames ``k`` (scene time k / fps) of ``camera``: uint8 (F, H, W, 3)."""
        times = self.cfg.frame_time_s(np.asarray(frame_indices, dtype=np.int64))
        return to_uint8(self.render_times(camera, np.atleast_1d(times)))

    def render_times(self, camera: Camera, times_s: Sequence[float] | np.ndarray) -> np.ndarray:
        """Images of ``camera`` at several scene times: float32 (F, H, W, 3)."""
        times = np.asarray(times_s, dtype=np.float64).reshape(-1)
        if not np.all(np.isfinite(times)):
            raise ValueError("scene times must be finite")
        layer = self._layer(camera)
        h, w = layer.height, layer.width
        out = np.empty((len(times), h * w, 3), dtype=np.float32)
        out[:] = layer.image.reshape(1, h * w, 3)
        n_cand = len(layer.cand_pixels)
        if n_cand and len(times):
            chunk = max(1, 400_000 // (n_cand * layer.n_sub))
            for start in range(0, len(times), chunk):
                stop = min(start + chunk, len(times))
                out[start:stop, layer.cand_pixels] = self._blade_pixels(layer, times[start:stop])
        return out.reshape(len(times), h, w, 3)

    # -- static layer -----------------------------------------------------------------------
    def _sample_rays(self, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        """Origins and directions of all samples, (H·W·S, 3), pixel-major, sample-minor."""
        n = self.cfg.spp
        offsets = (np.arange(n) + 0.5) / n
        j, i, sy, sx = np.meshgrid(
            np.arange(camera.height), np.arange(camera.width), offsets, offsets, indexing="ij"
        )
        return camera.pixel_rays((i + sx).reshape(-1), (j + sy).reshape(-1))

    def _cast_static(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Colour (N, 3) and hit distance (N,) of the static scene (inf = background)."""
        t_best = np.full(len(o), np.inf)
        which = np.full(len(o), -1)
        normals = np.zeros_like(o)
        for k, (hit, _) in enumerate(self._solids):
            t, n = hit(o, d)
            closer = t < t_best
            t_best = np.where(closer, t, t_best)
            which = np.where(closer, k, which)
            normals = np.where(closer[:, None], n, normals)
        rgb = self.background(d)
        for k, (_, albedo) in enumerate(self._solids):
            sel = np.nonzero(which == k)[0]
            if len(sel) == 0:
                continue
            p = o[sel] + t_best[sel, None] * d[sel]
            rgb[sel] = self._shade(albedo(p, normals[sel]), normals[sel], d[sel])
        return rgb, t_best

    def _layer(self, camera: Camera) -> _StaticLayer:
        layer = self._cache.get(camera)
        if layer is not None:
            self._cache.move_to_end(camera)
            return layer
        camera.validate()
        layer = self._build_layer(camera)
        self._cache[camera] = layer
        while len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return layer

    def _build_layer(self, camera: Camera) -> _StaticLayer:
        h, w, n_sub = camera.height, camera.width, self.cfg.spp**2
        o, d = self._sample_rays(camera)
        rgb, t_static = self._cast_static(o, d)
        image = _resolve(rgb.reshape(h * w, n_sub, 3)).astype(np.float32).reshape(h, w, 3)

        # Rotor-disc coordinates and the slab |w| ≤ half thickness the blades live in.
        rel = o - HUB_CENTRE
        p0 = np.stack([rel @ ROTOR_E1, rel @ ROTOR_E2])
        d2 = np.stack([d @ ROTOR_E1, d @ ROTOR_E2])
        w0, dw = rel @ ROTOR_AXIS, d @ ROTOR_AXIS
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (-BLADE_HALF_THICKNESS - w0) / dw
            tb = (BLADE_HALF_THICKNESS - w0) / dw
        parallel = np.abs(dw) < 1e-15
        inside = np.abs(w0) <= BLADE_HALF_THICKNESS
        t_enter = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))
        t_exit = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
        t_lo = np.maximum(t_enter, _EPS_T)
        t_hi = np.minimum(t_exit, t_static)
        # Conservative cull: the ray segment inside the slab must pass within the rotor radius.
        dd = np.einsum("ij,ij->j", d2, d2)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            t_star = np.where(dd > 1e-30, -np.einsum("ij,ij->j", p0, d2) / dd, 0.0)
            t_star = np.clip(t_star, t_lo, np.where(np.isfinite(t_hi), t_hi, t_lo))
            closest = np.hypot(p0[0] + t_star * d2[0], p0[1] + t_star * d2[1])
        may_hit = (t_lo < t_hi) & (closest <= self._rotor_radius)
        if not self._cull:
            may_hit = np.ones_like(may_hit)
        cand_pixels = np.nonzero(may_hit.reshape(h * w, n_sub).any(axis=1))[0]
        samples = (cand_pixels[:, None] * n_sub + np.arange(n_sub)).reshape(-1)

        # Angular reach: the path in the slab sweeps polar angles between its end points
        # (less than pi, as a segment); a blade point at radius ≥ r_min lies within
        # asin(max half chord / r_min) of the blade's direction.
        t_lo, t_hi = t_lo[samples], t_hi[samples]
        with np.errstate(invalid="ignore", over="ignore"):
            p0s, d2s = p0[:, samples], d2[:, samples]
            ends = [(p0s[0] + t * d2s[0], p0s[1] + t * d2s[1]) for t in (t_lo, t_hi)]
            alpha_a = np.arctan2(*ends[0])
            sweep = (np.arctan2(*ends[1]) - alpha_a + math.pi) % (2.0 * math.pi) - math.pi
            r_min = closest[samples]
            half_width = np.arcsin(np.clip(BLADE_HALF_CHORD_ROOT / np.maximum(r_min, 1e-12), 0, 1))
            reach = np.abs(sweep) / 2.0 + half_width + 1e-6
        alpha = alpha_a + sweep / 2.0
        finite = np.isfinite(t_lo) & np.isfinite(t_hi)
        wide = ~finite | ~np.isfinite(reach) | (half_width >= math.pi / 2 - 1e-9)
        if not self._cull:
            wide[:] = True
        reach = np.where(wide, 4.0, reach)  # > pi: always intersect exactly
        alpha = np.where(np.isfinite(alpha), alpha, 0.0)
        return _StaticLayer(
            height=h,
            width=w,
            n_sub=n_sub,
            image=image,
            cand_pixels=cand_pixels,
            cand_rgb=rgb[samples].reshape(len(cand_pixels), n_sub, 3),
            ray_p0=p0s,
            ray_d2=d2s,
            ray_w=dw[samples],
            t_lo=t_lo,
            t_hi=t_hi,
            ray_alpha=alpha,
            ray_reach=reach,
        )

    # -- blades -----------------------------------------------------------------------------
    def _blade_pixels(self, layer: _StaticLayer, times_s: np.ndarray) -> np.ndarray:
        """Composited colours of the candidate pixels at each time: float32 (F, Pc, 3)."""
        n_f, m = len(times_s), layer.ray_w.shape[0]
        angle = self.rotor_angle_rad(times_s)  # (F,)
        t_best = np.full((n_f, m), np.inf)
        blade_best = np.zeros((n_f, m), dtype=np.int8)
        face_best = np.zeros((n_f, m), dtype=np.int8)
        px, py = layer.ray_p0
        dx, dy = layer.ray_d2
        for blade in range(BLADES):
            psi_f = angle + 2.0 * math.pi * blade / BLADES
            # Angular pre-cull: only (frame, ray) pairs whose crossing of the disc lies within
            # reach of the blade's direction are intersected exactly.
            off = np.abs((layer.ray_alpha - psi_f[:, None] + math.pi) % (2.0 * math.pi) - math.pi)
            fi, mi = np.nonzero(off <= layer.ray_reach)
            if len(fi) == 0:
                continue
            psi = psi_f[fi]
            c, s = np.cos(psi), np.sin(psi)
            # Blade k points along (sin psi, cos psi) in (e1, e2); rotate the rays by −psi.
            t_in, face = self._clip_blade(
                s * px[mi] + c * py[mi],
                c * px[mi] - s * py[mi],
                s * dx[mi] + c * dy[mi],
                c * dx[mi] - s * dy[mi],
                layer.t_lo[mi],
                layer.t_hi[mi],
            )
            better = t_in < t_best[fi, mi]
            fi, mi = fi[better], mi[better]
            t_best[fi, mi] = t_in[better]
            blade_best[fi, mi] = blade
            face_best[fi, mi] = face[better]

        rgb = np.broadcast_to(layer.cand_rgb.reshape(1, m, 3), (n_f, m, 3)).copy()
        fi, mi = np.nonzero(np.isfinite(t_best))
        if len(fi):
            t = t_best[fi, mi]
            psi = angle[fi] + 2.0 * math.pi * blade_best[fi, mi] / BLADES
            c, s = np.cos(psi), np.sin(psi)
            u = s * (px[mi] + t * dx[mi]) + c * (py[mi] + t * dy[mi])
            v = c * (px[mi] + t * dx[mi]) - s * (py[mi] + t * dy[mi])
            face = face_best[fi, mi].astype(np.int64)
            edges = self._blade_edges[np.maximum(face - 1, 0)]
            n_u, n_v = edges[:, 0], edges[:, 1]
            # Back to the disc frame (rotate by +psi), then to world; faces use the axis.
            n_e1 = s * n_u + c * n_v
            n_e2 = c * n_u - s * n_v
            n_edge = n_e1[:, None] * ROTOR_E1 + n_e2[:, None] * ROTOR_E2
            n_edge /= np.linalg.norm(n_edge, axis=1, keepdims=True)
            n_face = np.broadcast_to(ROTOR_AXIS, n_edge.shape)
            normals = np.where((face == 0)[:, None], n_face, n_edge)
            dirs = (
                dx[mi, None] * ROTOR_E1
                + dy[mi, None] * ROTOR_E2
                + layer.ray_w[mi, None] * ROTOR_AXIS
            )
            rgb[fi, mi] = self._shade(self._albedo_blade(u, v, face), normals, dirs)
        return _resolve(rgb.reshape(n_f, -1, layer.n_sub, 3)).astype(np.float32)

    def _clip_blade(
        self,
        u0: np.ndarray,
        v0: np.ndarray,
        du: np.ndarray,
        dv: np.ndarray,
        t_lo: np.ndarray,
        t_hi: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Clip rays (in the blade's own (u, v) frame, restricted to the slab [t_lo, t_hi])
        against the blade outline. Returns the entry distance (inf = miss) and the face hit:
        0 = a flat side of the blade, k ≥ 1 = outline edge k − 1."""
        t_in = t_lo.copy()
        t_out = t_hi.copy()
        face = np.zeros(len(u0), dtype=np.int8)
        miss = np.zeros(len(u0), dtype=bool)
        for k, (nu, nv, e) in enumerate(self._blade_edges):
            num = e - (nu * u0 + nv * v0)
            den = nu * du + nv * dv
            with np.errstate(divide="ignore", invalid="ignore"):
                t_k = num / den
            later = (den < 0) & (t_k > t_in)
            t_in = np.where(later, t_k, t_in)
            face = np.where(later, k + 1, face).astype(np.int8)
            t_out = np.where(den > 0, np.minimum(t_out, t_k), t_out)
            miss |= (den == 0) & (num < 0)
        hit = ~miss & (t_in <= t_out)
        return np.where(hit, t_in, np.inf), face

    # -- shading and albedos ----------------------------------------------------------------
    @staticmethod
    def _shade(albedo: np.ndarray, normals: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Lambert + ambient with the normal turned towards the viewer (two-sided surfaces)."""
        facing = np.einsum("ij,ij->i", normals, dirs)
        n = np.where((facing > 0)[:, None], -normals, normals)
        lambert = np.clip(n @ SUN_DIR, 0.0, 1.0)
        return np.clip(albedo * (AMBIENT + DIFFUSE * lambert)[:, None], 0.0, 1.0)

    def _albedo_ground(self, p: np.ndarray, _n: np.ndarray) -> np.ndarray:
        x, y = p[:, 0], p[:, 1]
        grass = _mix(
            np.array([0.20, 0.42, 0.14]),
            np.array([0.50, 0.66, 0.26]),
            self._noise.fractal(x * 3.0, y * 3.0),
        )
        mowed = _checker(x / 0.5, y / 0.5)
        grass = grass * np.where(mowed, 0.85, 1.0)[:, None]
        flowers = self._noise_fine(x * 14.0 + 11.0, y * 14.0 + 7.0) > 0.87
        grass[flowers] = np.array([0.92, 0.80, 0.22])
        grit = 0.85 + 0.3 * self._noise_fine(x * 25.0, y * 25.0)
        gravel = np.array([0.64, 0.61, 0.56]) * grit[:, None]
        road = np.array([0.55, 0.50, 0.42]) * grit[:, None]
        dash = (np.abs(y) < 0.008) & (np.floor(x / 0.08) % 2 == 0)
        road[dash] = np.array([0.95, 0.95, 0.9])
        on_pad = np.hypot(x, y) < 0.32
        on_road = (np.abs(y) < 0.09) & (x > 0.0)
        out = np.where(on_road[:, None], road, grass)
        return np.where(on_pad[:, None], gravel, out)

    def _albedo_tower(self, p: np.ndarray, _n: np.ndarray) -> np.ndarray:
        theta = np.arctan2(p[:, 1], p[:, 0])
        z = p[:, 2]
        cell = _checker(theta / (2.0 * math.pi / 16.0), z / 0.16)
        out = np.where(cell[:, None], np.array([0.93, 0.93, 0.90]), np.array([0.72, 0.77, 0.86]))
        bands = [
            (0.07, (0.22, 0.42, 0.28)),
            (0.14, (0.38, 0.58, 0.40)),
            (0.21, (0.58, 0.74, 0.58)),
        ]
        for z_top, colour in reversed(bands):
            out[z < z_top] = colour
        out[(z > 1.30) & (z < 1.40)] = (0.80, 0.18, 0.14)
        grain = 0.92 + 0.16 * self._noise_fine(theta * 4.0, z * 12.0)
        return out * grain[:, None]

    def _albedo_nacelle(self, p: np.ndarray, n: np.ndarray) -> np.ndarray:
        axis = np.argmax(np.abs(n), axis=1)
        frac = (p / 0.06) % 1.0
        lines = frac < 0.15
        lines[np.arange(len(p)), axis] = False
        out = np.where(lines.any(axis=1)[:, None], np.array([0.55, 0.58, 0.62]), 0.91)
        side = (np.abs(n[:, 0]) > 0.5) & (p[:, 2] > 1.65) & (p[:, 2] < 1.70)
        out[side] = (0.12, 0.30, 0.72)
        rear = n[:, 1] > 0.5
        rear_check = _checker(p[:, 0] / 0.045, p[:, 2] / 0.045)
        out[rear & rear_check] = (0.95, 0.58, 0.18)
        return out

    def _albedo_hub(self, p: np.ndarray, _n: np.ndarray) -> np.ndarray:
        along = p[:, 1] - HUB_CENTRE[1]
        ring = _checker(along / 0.03)
        out = np.where(ring[:, None], np.array([0.82, 0.14, 0.10]), np.array([0.95, 0.95, 0.95]))
        out[along < -0.12] = (0.25, 0.25, 0.27)
        return out

    def _albedo_hut(self, p: np.ndarray, n: np.ndarray) -> np.ndarray:
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        across = np.where(np.abs(n[:, 0]) > 0.5, y, x)
        row = np.floor(z / 0.04)
        brick_x = across / 0.08 + 0.5 * (row % 2)
        mortar = ((z / 0.04) % 1.0 < 0.15) | (brick_x % 1.0 < 0.08)
        tint = 0.8 + 0.4 * self._noise_fine(np.floor(brick_x) * 3.1, row * 2.7)
        out = np.array([0.66, 0.30, 0.20]) * tint[:, None]
        out[mortar] = (0.82, 0.80, 0.74)
        door = (n[:, 1] < -0.5) & (x > 0.45) & (x < 0.53) & (z < 0.15)
        out[door] = (0.14, 0.36, 0.25)
        roof = n[:, 2] > 0.5
        slate = np.where(((x / 0.05) % 1.0) < 0.5, 0.30, 0.38)
        out[roof] = slate[roof, None] * np.array([1.0, 1.05, 1.2])
        return out

    def _albedo_rock(self, p: np.ndarray, n: np.ndarray) -> np.ndarray:
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        grain = 0.7 + 0.6 * self._noise_fine(x * 30.0 + 5.0, (y + z) * 30.0)
        out = np.array([0.52, 0.48, 0.43]) * grain[:, None]
        moss = (n[:, 2] > 0.6) & (self._noise(x * 12.0, y * 12.0) > 0.5)
        out[moss] = (0.33, 0.46, 0.22)
        return out

    @staticmethod
    def _albedo_blade(u: np.ndarray, v: np.ndarray, face: np.ndarray) -> np.ndarray:
        band = _checker(u / 0.1)
        out = np.where(band[:, None], np.array([0.94, 0.94, 0.94]), np.array([0.80, 0.83, 0.88]))
        half_chord = BLADE_HALF_CHORD_ROOT + (BLADE_HALF_CHORD_TIP - BLADE_HALF_CHORD_ROOT) * (
            u - BLADE_ROOT
        ) / (BLADE_TIP - BLADE_ROOT)
        leading = v > 0.4 * half_chord
        out[leading] *= 0.82
        from_tip = BLADE_TIP - u
        red = (from_tip < 0.08) | ((from_tip >= 0.16) & (from_tip < 0.24))
        out[red] = (0.85, 0.12, 0.10)
        out[face > 0] = (0.55, 0.55, 0.58)
        return out
