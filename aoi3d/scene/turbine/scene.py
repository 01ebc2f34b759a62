"""The turbine scene's renderer: :class:`TurbineScene` casts any :class:`Camera`'s rays.

Rendering is exact analytic ray casting with ``spp × spp`` stratified samples per pixel (sample
centres of a regular sub-grid, no randomness), averaged in sRGB. Because only the blades move,
the static layer of a camera (colour and depth of every sample) is cast once and cached; a
frame then intersects only the sample rays that can reach the rotor disc with the blades and
keeps whichever hit is nearer (z-compositing). The result equals a full re-render.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from aoi3d.scene.camera import Camera
from aoi3d.scene.turbine.appearance import Albedos, background, blade_albedo, shade
from aoi3d.scene.turbine.config import SceneConfig, to_uint8
from aoi3d.scene.turbine.geometry import (
    AABB,
    BLADE_HALF_CHORD_ROOT,
    BLADE_HALF_CHORD_TIP,
    BLADE_HALF_THICKNESS,
    BLADE_ROOT,
    BLADE_TIP,
    BLADES,
    EPS_T,
    HUB_CENTRE,
    HUB_RADII,
    HUT_HI,
    HUT_LO,
    NACELLE_HI,
    NACELLE_LO,
    ROCK_CENTRE,
    ROCK_RADII,
    ROTOR_AABB,
    ROTOR_AXIS,
    ROTOR_E1,
    ROTOR_E2,
    TOWER_HEIGHT,
    TOWER_R_BASE,
    TOWER_R_TOP,
    hit_box,
    hit_ellipsoid,
    hit_frustum,
    hit_ground,
)


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
        self._albedos = Albedos(rng)
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
            (hit_ground, self._albedos.ground),
            (
                lambda o, d: hit_frustum(o, d, TOWER_R_BASE, TOWER_R_TOP, TOWER_HEIGHT),
                self._albedos.tower,
            ),
            (lambda o, d: hit_box(o, d, NACELLE_LO, NACELLE_HI), self._albedos.nacelle),
            (lambda o, d: hit_ellipsoid(o, d, HUB_CENTRE, HUB_RADII), self._albedos.hub),
            (lambda o, d: hit_box(o, d, HUT_LO, HUT_HI), self._albedos.hut),
            (lambda o, d: hit_ellipsoid(o, d, ROCK_CENTRE, ROCK_RADII), self._albedos.rock),
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
        return background(dirs)

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
            rgb[sel] = shade(albedo(p, normals[sel]), normals[sel], d[sel])
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
        t_lo = np.maximum(t_enter, EPS_T)
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
            rgb[fi, mi] = shade(blade_albedo(u, v, face), normals, dirs)
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
