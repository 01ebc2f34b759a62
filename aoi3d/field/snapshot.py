"""A frozen copy of a trained field: rendered from any camera and exported as a point cloud
or a mesh that other tools open (.ply).

The reconstruction worker keeps one per site, taken after each job it renders (its latest
model), so that free views and exports are answered from it while the next job trains the
live model: nothing of the job's model is read or written by them.

Export (:meth:`ModelSnapshot.point_cloud`, :meth:`ModelSnapshot.mesh`, :func:`ply_bytes`):

- **point cloud**: the field's density is sampled on a regular lattice over the scene box
  (``resolution`` points a side, where the field's occupancy grid allows); points whose
  opacity over one of the renderer's fine ray steps δ, 1 − exp(−σ·δ), reaches ``alpha``
  (the empty-space skipping's own test, :meth:`FieldConfig.density_threshold`) are kept (the densest
  ``max_points`` of them), each with the colour the field gives it seen from the box's
  centre outwards (a view-dependent field's colour is one view's). A PLY of ``x y z`` floats
  and ``red green blue`` bytes, plus the density as ``density``. What is lost: the view
  dependence, the background (the environment map is not geometry), sizes (points, not
  splats), and anything finer than the lattice step.
- **mesh**: marching cubes (scikit-image) on the same density lattice at the level σ of
  opacity ``alpha``; vertices coloured as the points are. A PLY with ``vertex`` (x y z, red
  green blue) and ``face`` (vertex_indices) elements. What is lost besides: the inside of
  thin or semi-transparent structure (one iso-surface), and whatever the lattice misses.
"""

from __future__ import annotations

import copy
import io
from dataclasses import dataclass

import numpy as np
import torch

from aoi3d.field.rays import RayBundle, camera_rays, ray_aabb
from aoi3d.field.render import RenderOptions
from aoi3d.field.trainer import FieldTrainer
from aoi3d.scene.camera import Camera

__all__ = ["Cloud", "ModelSnapshot", "ply_bytes"]


@dataclass(frozen=True)
class Cloud:
    """Points (N, 3) float32 inside the box, their colours (N, 3) uint8 and densities (N,);
    ``faces`` (F, 3) int32 for a mesh, else None."""

    points: np.ndarray
    colours: np.ndarray
    density: np.ndarray
    faces: np.ndarray | None = None


class ModelSnapshot:
    """A copy of ``trainer``'s field at this moment, with what rendering it needs (config,
    box, step count). Thread-safe to read while the trainer trains on (they share nothing
    that changes)."""

    def __init__(self, trainer: FieldTrainer) -> None:
        self.cfg = trainer.cfg
        self.aabb = np.array(trainer.aabb, dtype=np.float64)
        self.steps = trainer.steps
        self.device = trainer.device
        self.field = copy.deepcopy(trainer.field).eval()
        self._aabb_t = torch.as_tensor(self.aabb, dtype=torch.float32, device=self.device)

    @torch.no_grad()
    def render(self, camera: Camera) -> np.ndarray:
        """The field seen from ``camera``: float32 H×W×3 in [0, 1] (as the trainer renders a
        novel view: neutral appearance, no age)."""
        camera.validate()
        origins, dirs = camera_rays(camera, self.device)
        t_near, t_far = ray_aabb(origins, dirs, self._aabb_t)
        options = RenderOptions(self.cfg.ray_step(self.aabb, self.steps))
        rays = RayBundle(origins, dirs, t_near, t_far)
        out = torch.empty_like(origins)
        chunk = self.cfg.render_chunk_rays
        for i in range(0, origins.shape[0], chunk):
            s = slice(i, i + chunk)
            out[s] = self.field.render_rays(rays[s], options).rgb
        image = out.clamp_(0.0, 1.0).reshape(camera.height, camera.width, 3)
        return image.cpu().numpy().astype(np.float32, copy=False)

    # ------------------------------------------------------------------ export
    def _lattice(self, resolution: int) -> tuple[np.ndarray, float]:
        lo, hi = self.aabb
        axes = [np.linspace(lo[i], hi[i], resolution) for i in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
        step = float(np.max((hi - lo) / max(resolution - 1, 1)))
        return grid.reshape(-1, 3), step

    @torch.no_grad()
    def _query(self, points: np.ndarray, chunk: int = 65536) -> tuple[np.ndarray, np.ndarray]:
        """Density (P,) and colour (P, 3) at ``points``, seen from the box's centre outwards
        (σ = 0 where the occupancy grid says empty)."""
        centre = self.aabb.mean(axis=0)
        sigma = np.zeros(len(points), dtype=np.float32)
        rgb = np.zeros((len(points), 3), dtype=np.float32)
        for i in range(0, len(points), chunk):
            p = torch.as_tensor(points[i:i + chunk], dtype=torch.float32, device=self.device)
            d = p - torch.as_tensor(centre, dtype=torch.float32, device=self.device)
            d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-6)
            mask = self.field.occupied(p)
            s, c = self.field.query(p, d)
            if mask is not None:
                s = torch.where(mask, s, torch.zeros_like(s))
            sigma[i:i + chunk] = s.float().cpu().numpy().reshape(-1)
            rgb[i:i + chunk] = c.float().clamp(0, 1).cpu().numpy().reshape(-1, 3)
        return sigma, rgb

    def point_cloud(self, *, resolution: int = 96, alpha: float = 0.1,
                    max_points: int = 200_000) -> Cloud:
        """The coloured points where the field is dense (see the module docstring)."""
        if not 8 <= resolution <= 512:
            raise ValueError(f"resolution must be 8..512, got {resolution}")
        if not 0.0 < alpha < 1.0:
            raise ValueError(f"alpha must be in (0, 1), got {alpha}")
        points, _ = self._lattice(resolution)
        sigma, rgb = self._query(points)
        keep = np.flatnonzero(sigma >= self.cfg.density_threshold(self.aabb, alpha))
        if len(keep) > max_points:
            keep = keep[np.argsort(-sigma[keep], kind="stable")[:max_points]]
            keep.sort()
        return Cloud(points[keep].astype(np.float32), _bytes(rgb[keep]),
                     sigma[keep].astype(np.float32))

    def mesh(self, *, resolution: int = 96, alpha: float = 0.1) -> Cloud:
        """The iso-surface of opacity ``alpha`` (marching cubes), vertices coloured."""
        from skimage.measure import marching_cubes

        points, _ = self._lattice(resolution)
        sigma, _ = self._query(points)
        volume = sigma.reshape(resolution, resolution, resolution)
        level = self.cfg.density_threshold(self.aabb, alpha)
        if not volume.min() < level < volume.max():
            raise ValueError("the field has no surface at this opacity (empty or all dense): "
                             "train longer or lower alpha")
        lo, hi = self.aabb
        spacing = tuple(float(v) for v in (hi - lo) / (resolution - 1))
        verts, faces, _, _ = marching_cubes(volume, level=level, spacing=spacing)
        verts = verts + lo
        vsigma, vrgb = self._query(verts)
        return Cloud(verts.astype(np.float32), _bytes(vrgb), vsigma.astype(np.float32),
                     faces.astype(np.int32))


def _bytes(rgb: np.ndarray) -> np.ndarray:
    return np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8).reshape(-1, 3)


def ply_bytes(cloud: Cloud, comment: str = "aoi3d export") -> bytes:
    """``cloud`` as a binary little-endian PLY: ``vertex`` (x y z float, red green blue
    uchar, density float) and, for a mesh, ``face`` (vertex_indices, uchar count + int)."""
    n = len(cloud.points)
    header = ["ply", "format binary_little_endian 1.0", f"comment {comment}",
              f"element vertex {n}", "property float x", "property float y",
              "property float z", "property uchar red", "property uchar green",
              "property uchar blue", "property float density"]
    if cloud.faces is not None:
        header += [f"element face {len(cloud.faces)}",
                   "property list uchar int vertex_indices"]
    header.append("end_header")
    vertex = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"),
                                ("green", "u1"), ("blue", "u1"), ("density", "<f4")])
    vertex["x"], vertex["y"], vertex["z"] = cloud.points.T
    vertex["red"], vertex["green"], vertex["blue"] = cloud.colours.T
    vertex["density"] = cloud.density
    buf = io.BytesIO()
    buf.write(("\n".join(header) + "\n").encode("ascii"))
    buf.write(vertex.tobytes())
    if cloud.faces is not None:
        face = np.empty(len(cloud.faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
        face["n"] = 3
        face["i"] = cloud.faces
        buf.write(face.tobytes())
    return buf.getvalue()
