"""The turbine scene's appearance: light, sky, shading and the procedural textures.

A ray that leaves the box without a hit gets :func:`background` of its direction alone: a sky
gradient with a sun glow above the horizon, hazy distant fields below it. Surfaces are lit by
:func:`shade` (Lambert + ambient, two-sided). Textures are procedural (checkers, stripes,
bricks, value noise); the value-noise lattices of :class:`Albedos` come from the generator it
is given (the scene's ``np.random.default_rng(cfg.seed)``) — no global RNG is touched.
"""

from __future__ import annotations

import math

import numpy as np

from aoi3d.scene.turbine.geometry import (
    BLADE_HALF_CHORD_ROOT,
    BLADE_HALF_CHORD_TIP,
    BLADE_ROOT,
    BLADE_TIP,
    HUB_CENTRE,
)

# --- light and colours (sRGB in [0, 1]) ------------------------------------------------------
SUN_DIR = np.array([-0.35, -0.55, 0.75]) / np.linalg.norm([-0.35, -0.55, 0.75])
AMBIENT = 0.45
DIFFUSE = 0.55
SKY_HORIZON = np.array([0.86, 0.90, 0.95])
SKY_ZENITH = np.array([0.25, 0.45, 0.82])
FAR_FIELD = np.array([0.36, 0.50, 0.26])


class ValueNoise:
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


def mix(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Per-row blend of colours ``a`` and ``b`` (each (3,) or (N, 3)) by weights (N,)."""
    w = w[:, None]
    return a * (1.0 - w) + b * w


def checker(*coords: np.ndarray) -> np.ndarray:
    total = sum(np.floor(c).astype(np.int64) for c in coords)
    return (total % 2).astype(bool)


def background(dirs: np.ndarray) -> np.ndarray:
    """Colour of rays that leave the box without a hit; depends on direction only.

    ``dirs`` (..., 3), unit vectors → float64 (..., 3) sRGB in [0, 1].
    """
    d = np.asarray(dirs, dtype=np.float64)
    shape = d.shape
    d = d.reshape(-1, 3)
    dz = d[:, 2]
    w_sky = np.sqrt(np.clip(dz, 0.0, 1.0))
    sky = mix(SKY_HORIZON, SKY_ZENITH, w_sky)
    glow = np.clip(d @ SUN_DIR, 0.0, 1.0) ** 48
    sky = sky + 0.3 * glow[:, None]
    azimuth = np.arctan2(d[:, 1], d[:, 0])
    fields_ = 1.0 + 0.12 * np.sin(5.0 * azimuth) + 0.08 * np.sin(13.0 * azimuth + 1.0)
    haze = np.exp(-8.0 * np.clip(-dz, 0.0, 1.0))
    ground = mix(FAR_FIELD * fields_[:, None], SKY_HORIZON, haze)
    out = np.where((dz >= 0)[:, None], sky, ground)
    return np.clip(out, 0.0, 1.0).reshape(shape)


def shade(albedo: np.ndarray, normals: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Lambert + ambient with the normal turned towards the viewer (two-sided surfaces)."""
    facing = np.einsum("ij,ij->i", normals, dirs)
    n = np.where((facing > 0)[:, None], -normals, normals)
    lambert = np.clip(n @ SUN_DIR, 0.0, 1.0)
    return np.clip(albedo * (AMBIENT + DIFFUSE * lambert)[:, None], 0.0, 1.0)


class Albedos:
    """The textures of the static solids: ``albedo(points (N, 3), normals (N, 3)) → (N, 3)``.

    The two value-noise lattices are drawn from ``rng`` in a fixed order (coarse, then fine).
    """

    def __init__(self, rng: np.random.Generator) -> None:
        self._noise = ValueNoise(rng)
        self._noise_fine = ValueNoise(rng)

    def ground(self, p: np.ndarray, _n: np.ndarray) -> np.ndarray:
        x, y = p[:, 0], p[:, 1]
        grass = mix(
            np.array([0.20, 0.42, 0.14]),
            np.array([0.50, 0.66, 0.26]),
            self._noise.fractal(x * 3.0, y * 3.0),
        )
        mowed = checker(x / 0.5, y / 0.5)
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

    def tower(self, p: np.ndarray, _n: np.ndarray) -> np.ndarray:
        theta = np.arctan2(p[:, 1], p[:, 0])
        z = p[:, 2]
        cell = checker(theta / (2.0 * math.pi / 16.0), z / 0.16)
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

    def nacelle(self, p: np.ndarray, n: np.ndarray) -> np.ndarray:
        axis = np.argmax(np.abs(n), axis=1)
        frac = (p / 0.06) % 1.0
        lines: np.ndarray = frac < 0.15
        lines[np.arange(len(p)), axis] = False
        hit = np.asarray(lines.any(axis=1))
        out = np.where(hit[:, None], np.array([0.55, 0.58, 0.62]), 0.91)
        side = (np.abs(n[:, 0]) > 0.5) & (p[:, 2] > 1.65) & (p[:, 2] < 1.70)
        out[side] = (0.12, 0.30, 0.72)
        rear = n[:, 1] > 0.5
        rear_check = checker(p[:, 0] / 0.045, p[:, 2] / 0.045)
        out[rear & rear_check] = (0.95, 0.58, 0.18)
        return out

    def hub(self, p: np.ndarray, _n: np.ndarray) -> np.ndarray:
        along = p[:, 1] - HUB_CENTRE[1]
        ring = checker(along / 0.03)
        out = np.where(ring[:, None], np.array([0.82, 0.14, 0.10]), np.array([0.95, 0.95, 0.95]))
        out[along < -0.12] = (0.25, 0.25, 0.27)
        return out

    def hut(self, p: np.ndarray, n: np.ndarray) -> np.ndarray:
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

    def rock(self, p: np.ndarray, n: np.ndarray) -> np.ndarray:
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        grain = 0.7 + 0.6 * self._noise_fine(x * 30.0 + 5.0, (y + z) * 30.0)
        out = np.array([0.52, 0.48, 0.43]) * grain[:, None]
        moss = (n[:, 2] > 0.6) & (self._noise(x * 12.0, y * 12.0) > 0.5)
        out[moss] = (0.33, 0.46, 0.22)
        return out


def blade_albedo(u: np.ndarray, v: np.ndarray, face: np.ndarray) -> np.ndarray:
    band = checker(u / 0.1)
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
