"""``FieldTrainer``: online training of a radiance field on a changing set of views.

The training set is swapped with :meth:`FieldTrainer.set_views` without touching the model
(the live trainer swaps frames in and out continuously). Each step draws ``batch_rays``
random pixels from the current views and hands them to the field's
:meth:`~aoi3d.field.base.Field.render_rays` (which samples, queries and composites: the shared
uniform sampler with empty-space skipping by default, proposal sampling for ``nerfacto``),
then takes one Adam step on the mean squared colour error plus the regularisers of
``FieldConfig`` plus the field's own ``RenderResult.aux_loss``. One loop for every backend.
The rays of each camera are computed once and cached by camera (the ``Camera`` hashes by its
pose and intrinsics).

Per-image appearance: each view has a stable key, its ``TrainView.appearance_id`` (the camera
id in the services) or, when that is None, its camera. The trainer maps keys to rows of a
fixed table of ``FieldConfig.appearance_slots`` rows and passes each ray's row to the field
(``RayBundle.appearance``). A key keeps its row across ``set_views`` calls (and ``reset``), so
embeddings survive the live trainer's view swaps; when a new key finds the table full, the
least recently used row outside the current views is recycled (the field resets it). Novel
views are rendered with ``appearance=None``: the field's neutral embedding.

Image age: a view may carry ``TrainView.age_ms``, how old its frame is at the decision it
trains for (its AoI). A config that uses it (``FieldConfig.uses_age``) needs it on every
view: the timeliness embedding (a field that ``takes_age``) gets each ray's age in
``RayBundle.age_ms``; the weighted-sum loss (``FieldConfig.age_weight_tau_ms`` = τ) weights
each ray's data terms by exp(−age/τ), normalised over the batch. Novel views are rendered
without an age: the scene at age 0, the time the decision stands for.
"""

from __future__ import annotations

import copy
import math
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from aoi3d.device import resolve_device
from aoi3d.field import native
from aoi3d.field.base import Field, FieldConfig
from aoi3d.field.optim import LazyAdam
from aoi3d.field.rays import RayBundle, as_aabb, camera_rays, ray_aabb
from aoi3d.field.render import RenderOptions

if TYPE_CHECKING:
    from aoi3d.scene.camera import Camera

__all__ = ["FieldTrainer", "TrainView"]


@dataclass(frozen=True, eq=False)
class TrainView:
    """One training frame: the camera it was taken with, its image (uint8 or float32 H×W×3
    in [0, 1]), ``appearance_id``, the stable key of its per-image appearance embedding
    (e.g. the camera id; None: keyed by the camera itself), and ``age_ms``, how old the frame
    is at the time the model is trained for (its AoI, ms ≥ 0; None: not known, which only a
    config that uses ages refuses)."""

    camera: Camera
    image: np.ndarray
    appearance_id: int | None = None
    age_ms: float | None = None

    def __post_init__(self) -> None:
        a = self.appearance_id
        if a is not None and (isinstance(a, bool) or not isinstance(a, int | np.integer)):
            raise TypeError(f"appearance_id must be an int or None, got {a!r}")
        age = self.age_ms
        if age is not None and (isinstance(age, bool)
                                or not isinstance(age, int | float | np.integer | np.floating)
                                or not math.isfinite(age) or age < 0):
            raise ValueError(f"age_ms must be a finite number >= 0 or None, got {age!r}")


def _image_tensor(image: np.ndarray, camera: Camera) -> torch.Tensor:
    """The view's image as float32 (H·W, 3) in [0, 1], after checking it fits the camera."""
    arr = np.asarray(image)
    expected = (camera.height, camera.width, 3)
    if arr.shape != expected:
        raise ValueError(f"image shape {arr.shape} does not match the camera's {expected}")
    if arr.dtype == np.uint8:
        out = arr.astype(np.float32) / 255.0
    elif np.issubdtype(arr.dtype, np.floating):
        out = arr.astype(np.float32)
        if not np.isfinite(out).all():
            raise ValueError("image contains non-finite values")
    else:
        raise ValueError(f"image must be uint8 or float in [0, 1], got dtype {arr.dtype}")
    return torch.from_numpy(np.ascontiguousarray(out)).reshape(-1, 3)


def _appearance_key(view: TrainView) -> Hashable:
    """The stable key of a view's appearance embedding: its id, else its camera."""
    if view.appearance_id is not None:
        return ("id", int(view.appearance_id))
    return ("camera", view.camera)


_RENDER_CACHE_SIZE = 8


def _age_weights(age_ms: torch.Tensor, tau_ms: float) -> torch.Tensor:
    """Per-ray weights exp(−age/τ) of the weighted-sum loss, normalised to sum to 1 (shifted
    by the batch's youngest age first, which the normalisation cancels: no underflow to an
    all-zero batch however old the frames are)."""
    w = torch.exp(-(age_ms - age_ms.min()) / tau_ms)
    return w / w.sum()


class FieldTrainer:
    """Trains the field ``cfg`` builds on the current views; renders any camera."""

    def __init__(
        self,
        cfg: FieldConfig,
        aabb: np.ndarray,
        device: torch.device | str | None = None,
        seed: int = 0,
    ) -> None:
        self.cfg = cfg
        self.aabb = as_aabb(aabb)
        self._device = torch.device(device if device is not None else resolve_device("auto"))
        self.seed = seed
        self._aabb_t = torch.as_tensor(self.aabb, dtype=torch.float32, device=self._device)
        self._ray_cache: dict[Camera, tuple[torch.Tensor, ...]] = {}  # training cameras
        self._render_cache: dict[Camera, tuple[torch.Tensor, ...]] = {}  # other cameras
        self._colour_cache: dict[int, tuple[TrainView, torch.Tensor]] = {}  # by view identity
        self._views: list[TrainView] = []
        # origins, dirs, t_near, t_far, rgb, appearance row of every pixel of the views:
        self._rays: tuple[torch.Tensor, ...] | None = None
        self._packed: torch.Tensor | None = None  # the float columns of _rays, side by side
        self._focus: torch.Tensor | None = None  # rows of _packed a share of each batch comes from
        self._focus_rays = 0
        # appearance key → row, least recently used first:
        self._appearance_rows: OrderedDict[Hashable, int] = OrderedDict()
        self.reset()

    # --- state ----------------------------------------------------------------------------
    @property
    def device(self) -> torch.device:
        return self._device

    @property
    def steps(self) -> int:
        """Training steps taken since the last reset."""
        return self._steps

    @property
    def n_views(self) -> int:
        return len(self._views)

    @property
    def field(self) -> Field:
        return self._field

    def appearance_row(self, view: TrainView) -> int | None:
        """The appearance-table row of ``view``'s key, None when it has none yet."""
        return self._appearance_rows.get(_appearance_key(view))

    def reset(self) -> None:
        """A fresh model, optimizer and random stream (the views and the appearance rows of
        their keys are kept; the fresh field's embeddings start neutral)."""
        self._generator = torch.Generator(device=self._device)
        self._generator.manual_seed(self.seed)
        self._field = self.cfg.build(self.aabb).to(self._device)
        self._steps = 0
        self._field.on_step(0)
        self._optimizer = self._make_optimizer()

    def fork(self) -> FieldTrainer:
        """An independent copy of this trainer: the model, its optimizer state, its step count
        and its random stream are copied, the views and the ray caches shared (read-only).

        Training the copy leaves this trainer untouched: the live trainer and the experiments'
        ``fork`` carry train a copy of the warm model on one decision's frames, render it and
        drop it (see :mod:`aoi3d.field.carry`).
        """
        twin = object.__new__(FieldTrainer)
        twin.__dict__.update(self.__dict__)
        twin._field = copy.deepcopy(self._field)
        twin._optimizer = twin._make_optimizer()
        # load_state_dict keeps tensors already on the right device and dtype: copy them first
        twin._optimizer.load_state_dict(copy.deepcopy(self._optimizer.state_dict()))
        twin._generator = torch.Generator(device=self._device)
        twin._generator.set_state(self._generator.get_state())
        twin._ray_cache = dict(self._ray_cache)
        twin._render_cache = dict(self._render_cache)
        twin._colour_cache = dict(self._colour_cache)
        twin._appearance_rows = OrderedDict(self._appearance_rows)
        return twin

    def checkpoint(self) -> dict[str, Any]:
        """What :meth:`restore` needs to go on training this model: the field (as a module,
        so a structure grown since step 0 — an upsampled grid — is kept), the optimizer's
        state, the step count, the random stream and the appearance rows. Views are not part
        of it (they come with the next decision). For ``torch.save``."""
        return {"field": self._field, "optimizer": self._optimizer.state_dict(),
                "steps": self._steps, "generator": self._generator.get_state(),
                "appearance_rows": list(self._appearance_rows.items())}

    def restore(self, doc: dict[str, Any]) -> None:
        """Go on from a :meth:`checkpoint` of a trainer of the same config (views kept)."""
        self._field = doc["field"].to(self._device)
        self._optimizer = self._make_optimizer()
        self._optimizer.load_state_dict(doc["optimizer"])
        self._steps = int(doc["steps"])
        self._generator.set_state(doc["generator"])
        self._appearance_rows = OrderedDict(doc["appearance_rows"])

    def set_schedule_step(self, step: int) -> None:
        """Go on from training step ``step`` (model and optimizer kept): the step-driven
        schedule — coarse to fine, the ray step, empty-space skipping — continues from there.
        The streaming warm start (:mod:`aoi3d.field.carry`) holds a carried model at the
        schedule of a fresh reconstruction's last steps this way, so that carrying it does not
        upsample it or refine its ray step decision after decision. Moving into an earlier
        coarse-to-fine stage resamples the grids down at the next step."""
        if isinstance(step, bool) or not isinstance(step, int) or step < 0:
            raise ValueError(f"step must be an int >= 0, got {step!r}")
        self._steps = step

    def forget(self, changed: Callable[[torch.Tensor], torch.Tensor]) -> int | None:
        """Reset the model where ``changed`` says the scene changed: ``changed(points)`` maps
        world points (P, 3) to a bool mask (P,); the field's parameters at those points return
        to their initial values (:meth:`Field.forget`) and their optimizer moments to zero,
        so what was there is neither rendered nor pulled back by momentum. Returns the rows
        reset, None when the field cannot forget locally (it is kept as it is)."""
        found = self._field.forget(changed)
        if found is None:
            return None
        total = 0
        for param, rows in found:
            state = self._optimizer.state.get(param)
            if state:
                state["exp_avg"].index_fill_(0, rows, 0.0)
                state["exp_avg_sq"].index_fill_(0, rows, 0.0)
            total += int(rows.numel())
        return total

    def advance(self, dt_ms: float) -> bool:
        """Move the time the model stands for ``dt_ms`` later (``Field.advance``: a time-aware
        field carries itself along its motion, and the optimizer's moments of what it moved
        follow); True when anything moved (a static field: nothing, False)."""
        moved = self._field.advance(dt_ms)
        if not moved:
            return False
        for param, carry in moved:
            state = self._optimizer.state.get(param)
            if state:
                state["exp_avg"].copy_(carry(state["exp_avg"]))
                state["exp_avg_sq"].copy_(carry(state["exp_avg_sq"]).clamp_min_(0.0))
        return True

    @contextmanager
    def lr_scaled(self, factor: float) -> Iterator[None]:
        """Inside: every parameter group's learning rate times ``factor`` (the optimizer's
        state kept); after: as before."""
        if not (math.isfinite(factor) and factor > 0):
            raise ValueError(f"factor must be a finite number > 0, got {factor}")
        groups = self._optimizer.param_groups
        saved = [g["lr"] for g in groups]
        for g in groups:
            g["lr"] *= factor
        try:
            yield
        finally:
            for g, lr in zip(self._optimizer.param_groups, saved, strict=False):
                g["lr"] = lr

    def set_focus(self, pixels: torch.Tensor | None, fraction: float) -> None:
        """Draw ``fraction`` of each batch's rays from ``pixels`` (int64 indices into the
        current views' pixels, concatenated in view order, row-major), the rest from all of
        them, until the next :meth:`set_views`; None, an empty set or a fraction of 0: every
        ray from all pixels (the default)."""
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"fraction must be in [0, 1], got {fraction}")
        if pixels is None or pixels.numel() == 0 or fraction == 0.0 or self._packed is None:
            self._focus, self._focus_rays = None, 0
            return
        pixels = pixels.to(device=self._device, dtype=torch.long).reshape(-1)
        if int(pixels.min()) < 0 or int(pixels.max()) >= self._packed.shape[0]:
            raise ValueError("focus pixels outside the current views")
        self._focus = pixels
        self._focus_rays = round(fraction * self.cfg.batch_rays)

    def _make_optimizer(self) -> LazyAdam:
        return LazyAdam(self._field.param_groups(), betas=(0.9, 0.99), eps=self.cfg.adam_eps)

    # --- views ----------------------------------------------------------------------------
    def _new_rays(self, camera: Camera) -> tuple[torch.Tensor, ...]:
        """origins, dirs, t_near, t_far of every pixel of ``camera`` (validated)."""
        camera.validate()
        origins, dirs = camera_rays(camera, self._device)
        return (origins, dirs, *ray_aabb(origins, dirs, self._aabb_t))

    def _colours(self, view: TrainView) -> torch.Tensor:
        """The view's pixels as float32 (H·W, 3), cached while the view object is in use."""
        cached = self._colour_cache.get(id(view))
        if cached is None or cached[0] is not view:
            cached = (view, _image_tensor(view.image, view.camera).to(self._device))
        return cached[1]

    def _assign_appearance(self, views: list[TrainView]) -> list[int]:
        """The appearance row of each view: a key keeps its row; a new key takes a free row or
        recycles the least recently used one outside ``views`` (the field resets it)."""
        keys = [_appearance_key(v) for v in views]
        current = set(keys)
        slots = self.cfg.appearance_slots
        if len(current) > slots:
            raise ValueError(
                f"{len(current)} distinct appearance ids in one training set, more than "
                f"appearance_slots = {slots}"
            )
        rows = self._appearance_rows
        for key in keys:  # the current views become the most recently used
            if key in rows:
                rows.move_to_end(key)
        recycled = []
        for key in keys:
            if key in rows:
                continue
            if len(rows) < slots:
                rows[key] = len(rows)
            else:
                oldest = next(k for k in rows if k not in current)
                row = rows.pop(oldest)
                rows[key] = row
                recycled.append(row)
        if recycled:
            self._field.reset_appearance(torch.tensor(recycled, device=self._device))
        return [rows[k] for k in keys]

    def set_views(self, views: Sequence[TrainView]) -> None:
        """Train on ``views`` from now on; the model and optimizer state are kept.

        Rays are cached per camera and pixels per view object, so swapping a few views in a
        large set costs little. Each view's appearance key keeps its row (see the module).
        """
        views = list(views)
        for v in views:
            if not isinstance(v, TrainView):
                raise TypeError(f"views must be TrainView objects, got {type(v).__name__}")
        if self.cfg.uses_age and any(v.age_ms is None for v in views):
            raise ValueError("this field config uses each image's age (timeliness embedding or "
                             "age-weighted loss): every TrainView needs age_ms")
        colours = [self._colours(v) for v in views]
        rays = []
        for v in views:
            if v.camera not in self._ray_cache:
                self._ray_cache[v.camera] = self._new_rays(v.camera)
            rays.append(self._ray_cache[v.camera])
        appearance = self._assign_appearance(views)
        cameras = {v.camera for v in views}
        self._ray_cache = {c: r for c, r in self._ray_cache.items() if c in cameras}
        self._colour_cache = {id(v): (v, c) for v, c in zip(views, colours, strict=True)}
        self._views = views
        self._focus, self._focus_rays = None, 0
        if views and self.cfg.time_aware and self._steps == 0:  # before training: the pivot
            self._field.set_pivot(float(np.mean([float(v.age_ms) for v in views])))  # type: ignore[arg-type]
        if not views:
            self._rays = self._packed = None
            return
        parts = [torch.cat([r[i] for r in rays]) for i in range(4)]
        rows = torch.cat(
            [
                torch.full((c.shape[0],), row, dtype=torch.long, device=self._device)
                for c, row in zip(colours, appearance, strict=True)
            ]
        )
        self._rays = (*parts, torch.cat(colours), rows)
        # the float columns side by side, so that a step gathers its batch in one call:
        # origins 0:3, dirs 3:6, t_near 6, t_far 7, rgb 8:11 (and the image's age 11)
        o, d, near, far, rgb = self._rays[:5]
        columns = [o, d, near[:, None], far[:, None], rgb]
        if self.cfg.uses_age:
            columns.append(torch.cat([
                torch.full((c.shape[0], 1), float(v.age_ms), device=self._device)  # type: ignore[arg-type]
                for c, v in zip(colours, views, strict=True)
            ]))
        self._packed = torch.cat(columns, dim=1)

    # --- training -------------------------------------------------------------------------
    def step(self, n: int = 1) -> float:
        """``n`` training steps; the last step's photometric loss (MSE of the batch's colours,
        unweighted, without the regularisers and the field's ``aux_loss``), NaN when there are
        no views. A field that can take a whole step itself (``Field.train_step``: the grid on
        the CPU, without autograd) does, with the unweighted loss below; the others, and the
        age-weighted loss, train under autograd here."""
        if n < 0:
            raise ValueError(f"n must be >= 0, got {n}")
        if self._rays is None:
            return math.nan
        loss_value = math.nan
        appearance = self._rays[5]
        packed = self._packed
        assert packed is not None
        n_rays = packed.shape[0]
        tau = self.cfg.age_weight_tau_ms
        takes_age = self.cfg.takes_age
        self._field.train()
        for _ in range(n):
            if self._field.on_step(self._steps):
                self._optimizer = self._make_optimizer()
            batch = torch.randint(
                n_rays, (self.cfg.batch_rays - self._focus_rays,), generator=self._generator,
                device=self._device
            )
            if self._focus is not None:  # a share of the batch from the focus pixels
                pick = torch.randint(self._focus.numel(), (self._focus_rays,),
                                     generator=self._generator, device=self._device)
                batch = torch.cat([self._focus.index_select(0, pick), batch])
            jitter = torch.rand(self.cfg.batch_rays, generator=self._generator, device=self._device)
            picked = packed.index_select(0, batch)
            rays = RayBundle(
                picked[:, 0:3],
                picked[:, 3:6],
                picked[:, 6],
                picked[:, 7],
                appearance.index_select(0, batch),
                picked[:, 11] if takes_age else None,
            )
            options = RenderOptions(
                self.cfg.ray_step(self.aabb, self._steps),
                jitter,
                self.cfg.explore_empty,
                self._generator,
            )
            target = picked[:, 8:11]
            if tau is None:  # the field's own fused step, where it has one
                mse_fused = self._field.train_step(rays, options, target, self._optimizer)
                if mse_fused is not None:
                    self._steps += 1
                    loss_value = mse_fused
                    continue
            out = self._field.render_rays(rays, options)
            # the loss (native.grid_training_grads computes the same for the fused step)
            sq = (out.rgb - target) ** 2
            mse = torch.mean(sq)
            sample_weights = out.weights
            if tau is None:
                loss = mse
            else:  # the weighted sum: w = exp(−age/τ), normalised (equal ages: the plain loss)
                ray_w = _age_weights(picked[:, 11], tau)
                loss = (sq.mean(dim=1) * ray_w).sum()
                sample_weights = out.weights * (ray_w * len(batch)).index_select(0, out.ray_index)
            if self.cfg.sample_rgb_loss > 0:
                err = native.weighted_colour_error(out.sample_rgb, sample_weights, target,
                                                   out.ray_index)
                loss = loss + self.cfg.sample_rgb_loss * err / len(batch)
            if self.cfg.opacity_loss > 0:
                loss = loss + self.cfg.opacity_loss * out.opacity.sum() / len(batch)
            if out.aux_loss is not None:
                loss = loss + out.aux_loss
            self._optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self._optimizer.step()
            self._steps += 1
            loss_value = float(mse.detach())
        return loss_value

    # --- rendering ------------------------------------------------------------------------
    @torch.no_grad()
    def render(self, camera: Camera, ahead_ms: float = 0.0) -> np.ndarray:
        """The field seen from ``camera``: float32 H×W×3 in [0, 1] (a novel view: rendered
        with the field's neutral appearance, whatever the camera). ``ahead_ms``: the scene
        that long after the time the field stands for (a field whose config is
        ``time_aware`` renders every ray at age −``ahead_ms``: the display time; the others
        show the same scene at every time and ignore it)."""
        if not math.isfinite(ahead_ms):
            raise ValueError(f"ahead_ms must be finite, got {ahead_ms}")
        if camera in self._ray_cache:
            origins, dirs, t_near, t_far = self._ray_cache[camera]
        else:
            cached = self._render_cache.pop(camera, None)
            if cached is None:
                cached = self._new_rays(camera)
            self._render_cache[camera] = cached  # most recent last
            while len(self._render_cache) > _RENDER_CACHE_SIZE:
                del self._render_cache[next(iter(self._render_cache))]
            origins, dirs, t_near, t_far = cached
        self._field.eval()
        options = RenderOptions(self.cfg.ray_step(self.aabb, self._steps))
        age = None
        if ahead_ms and self.cfg.time_aware:
            age = torch.full((origins.shape[0],), -float(ahead_ms), device=self._device)
        rays = RayBundle(origins, dirs, t_near, t_far, None, age)
        chunk = self.cfg.render_chunk_rays
        out = torch.empty_like(origins)
        for i in range(0, origins.shape[0], chunk):
            s = slice(i, i + chunk)
            out[s] = self._field.render_rays(rays[s], options).rgb
        image = out.clamp_(0.0, 1.0).reshape(camera.height, camera.width, 3)
        return image.cpu().numpy().astype(np.float32, copy=False)
