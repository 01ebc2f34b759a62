"""Radiance fields: backends, ray sampling, volume rendering and the online trainer.

A backend is a config dataclass and the field it builds (``GridConfig`` → ``DenseGridField``);
rays (``rays.py``), the sampler, the volume renderer (``render.py``), the optimizer
(``optim.py``) and the training loop (``FieldTrainer``) are shared by all backends. Named
backends live in :data:`BACKENDS`; :func:`field_config` builds one by name.
"""

from __future__ import annotations

from typing import Any

from aoi3d.field.base import Field, FieldConfig
from aoi3d.field.flow import FlowConfig, FlowField
from aoi3d.field.grid import DenseGridField, GridConfig
from aoi3d.field.nerf import NerfMlpConfig, NerfMlpField
from aoi3d.field.nerfacto import NerfactoConfig, NerfactoField
from aoi3d.field.ngp import NgpConfig, NgpField
from aoi3d.field.optim import LazyAdam
from aoi3d.field.rays import RayBundle, RaySamples, camera_rays, ray_aabb, sample_uniform
from aoi3d.field.render import RenderOptions, RenderResult, render_uniform, volume_render
from aoi3d.field.tensorf import TensorfConfig, TensorfField
from aoi3d.field.trainer import FieldTrainer, TrainView

__all__ = [
    "BACKENDS",
    "DenseGridField",
    "Field",
    "FieldConfig",
    "FieldTrainer",
    "FlowConfig",
    "FlowField",
    "GridConfig",
    "LazyAdam",
    "NerfMlpConfig",
    "NerfMlpField",
    "NerfactoConfig",
    "NerfactoField",
    "NgpConfig",
    "NgpField",
    "RayBundle",
    "RaySamples",
    "RenderOptions",
    "RenderResult",
    "TensorfConfig",
    "TensorfField",
    "TrainView",
    "UnknownBackendError",
    "camera_rays",
    "check_backend",
    "field_config",
    "ray_aabb",
    "render_uniform",
    "sample_uniform",
    "volume_render",
]

BACKENDS: dict[str, type[FieldConfig]] = {
    "grid": GridConfig,
    "ngp": NgpConfig,
    "tensorf": TensorfConfig,
    "nerf": NerfMlpConfig,
    "nerfacto": NerfactoConfig,
    "flow": FlowConfig,
}
"""Radiance-field backends by name: grid, ngp, tensorf, nerfacto, the reference nerf MLP and
``flow``, the time-aware grid (a 4-D field: the grid carried by a learned velocity field)."""


class UnknownBackendError(ValueError):
    """A backend name that is not in :data:`BACKENDS`; the message lists those that are."""


def check_backend(name: str) -> str:
    """``name`` if it is a registered backend, else :class:`UnknownBackendError` — the one
    check of a backend name (the CLI, the trainer's settings and ``PUT /backend``, the
    benches)."""
    if name not in BACKENDS:
        raise UnknownBackendError(
            f"unknown field backend {name!r}; available: {', '.join(BACKENDS)}")
    return name


def field_config(name: str, **overrides: Any) -> FieldConfig:
    """The default config of backend ``name`` with ``overrides`` applied."""
    return BACKENDS[check_backend(name)](**overrides)
