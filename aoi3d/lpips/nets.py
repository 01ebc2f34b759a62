"""LPIPS v0.1 (Zhang et al. 2018) in torch: the AlexNet / VGG16 feature extractors and the metric.

The backbones are defined here, layer for layer as torchvision's ``alexnet().features`` and
``vgg16().features`` (same module indices, so the state-dict keys match), without importing
torchvision. LPIPS taps the output of the ReLU after each of 5 convolutions (AlexNet: all five
convolutions; VGG16: relu1_2, relu2_2, relu3_3, relu4_3, relu5_3).

Distance of two images x, y (N×3×H×W, **float in [0, 1]**):

1. scale to [-1, 1] (``2·x − 1``), then the LPIPS ScalingLayer ``(z − shift) / scale`` with
   shift = (−.030, −.088, −.188), scale = (.458, .448, .450);
2. features of both images; each tap unit-normalised along channels (``f / (‖f‖₂ + 1e−10)``);
3. squared difference, a 1×1 convolution with non-negative weights and no bias (the v0.1
   linear layer, one per tap), spatial mean;
4. the sum over the 5 taps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

__all__ = ["LPIPS", "NETS", "NetSpec", "build_features"]

_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
_EPS = 1e-10
_RANGE_TOL = 1e-4  # inputs may leave [0, 1] by this much (float round-off) before we refuse


@dataclass(frozen=True)
class NetSpec:
    """A backbone: torchvision's ``features`` layout, where LPIPS taps it, how wide the taps are.

    ``layers`` lists the ``features`` modules in order: ``("conv", out_channels, kernel, stride,
    padding)``, ``("relu",)`` or ``("pool", kernel, stride)``. ``taps`` are the indices (into
    ``features``) of the ReLUs whose outputs LPIPS compares.
    """

    name: str
    layers: tuple[tuple, ...]
    taps: tuple[int, ...]

    @property
    def conv_indices(self) -> tuple[int, ...]:
        """Indices of the convolutions in ``features``, in order."""
        return tuple(i for i, layer in enumerate(self.layers) if layer[0] == "conv")

    @property
    def tap_channels(self) -> tuple[int, ...]:
        """Channels of each tap (the width of its linear layer)."""
        return tuple(self._channels_before(t) for t in self.taps)

    def _channels_before(self, index: int) -> int:
        convs = [layer for layer in self.layers[: index + 1] if layer[0] == "conv"]
        return convs[-1][1]

    def out_size(self, size: int) -> int:
        """Side of the last tap for an input side ``size`` (≤ 0: the image is too small)."""
        for layer in self.layers[: self.taps[-1] + 1]:
            if layer[0] == "conv":
                _, _, k, s, p = layer
                size = (size + 2 * p - k) // s + 1
            elif layer[0] == "pool":
                _, k, s = layer
                size = (size - k) // s + 1
            if size <= 0:
                return 0
        return size

    @property
    def min_size(self) -> int:
        """Smallest image side (pixels) for which every tap has at least one pixel."""
        size = 1
        while self.out_size(size) < 1:
            size += 1
        return size


def _vgg16_layers() -> tuple[tuple, ...]:
    layers: list[tuple] = []
    for item in (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M",
                 512, 512, 512):
        if item == "M":
            layers.append(("pool", 2, 2))
        else:
            layers += [("conv", item, 3, 1, 1), ("relu",)]
    return tuple(layers)


NETS: dict[str, NetSpec] = {
    "alex": NetSpec(
        name="alex",
        layers=(("conv", 64, 11, 4, 2), ("relu",), ("pool", 3, 2),
                ("conv", 192, 5, 1, 2), ("relu",), ("pool", 3, 2),
                ("conv", 384, 3, 1, 1), ("relu",),
                ("conv", 256, 3, 1, 1), ("relu",),
                ("conv", 256, 3, 1, 1), ("relu",)),
        taps=(1, 4, 7, 9, 11)),
    "vgg": NetSpec(name="vgg", layers=_vgg16_layers(), taps=(3, 8, 15, 22, 29)),
}
"""The LPIPS backbones by name: ``alex`` (the paper's metric) and ``vgg`` (VGG16)."""


def net_spec(net: str) -> NetSpec:
    """The :class:`NetSpec` named ``net``; a clear ``ValueError`` for an unknown name."""
    try:
        return NETS[net]
    except KeyError:
        raise ValueError(f"unknown LPIPS net {net!r}; choose one of {sorted(NETS)}") from None


def build_features(spec: NetSpec) -> nn.Sequential:
    """The backbone's ``features`` (torchvision's layout and indices), up to its last tap."""
    modules: list[nn.Module] = []
    in_channels = 3
    for layer in spec.layers[: spec.taps[-1] + 1]:
        if layer[0] == "conv":
            _, out_channels, k, s, p = layer
            modules.append(nn.Conv2d(in_channels, out_channels, k, stride=s, padding=p))
            in_channels = out_channels
        elif layer[0] == "relu":
            modules.append(nn.ReLU(inplace=False))
        else:
            _, k, s = layer
            modules.append(nn.MaxPool2d(k, stride=s))
    return nn.Sequential(*modules)


class _Backbone(nn.Module):
    """Runs ``features`` and returns the outputs at the tap indices."""

    def __init__(self, spec: NetSpec) -> None:
        super().__init__()
        self.features = build_features(spec)
        self._taps = frozenset(spec.taps)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self._taps:
                out.append(x)
        return out


class LPIPS(nn.Module):
    """The LPIPS v0.1 distance with an AlexNet (``net="alex"``) or VGG16 (``"vgg"``) backbone.

    Build it with :func:`aoi3d.lpips.load_lpips` (pretrained weights); a bare ``LPIPS(net)`` has
    randomly initialised weights. State-dict keys: ``net.features.<i>.weight|bias`` (the
    torchvision indices) and ``lins.<k>.weight`` (1×C×1×1, the linear layer of tap k). The
    parameters are frozen (``requires_grad=False``) by :func:`load_lpips`; gradients still flow
    to the inputs, so the module also works as a loss.
    """

    shift: torch.Tensor  # buffers: the input normalisation (1, 3, 1, 1)
    scale: torch.Tensor

    def __init__(self, net: str = "alex") -> None:
        super().__init__()
        self.spec = net_spec(net)
        self.net = _Backbone(self.spec)
        self.lins = nn.ModuleList(
            nn.Conv2d(c, 1, kernel_size=1, bias=False) for c in self.spec.tap_channels)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)

    @property
    def net_name(self) -> str:
        return self.spec.name

    @property
    def min_size(self) -> int:
        """Smallest image side (pixels) this backbone accepts."""
        return self.spec.min_size

    @property
    def device(self) -> torch.device:
        return self.shift.device

    def _check(self, x: torch.Tensor, y: torch.Tensor) -> None:
        for name, t in (("x", x), ("y", y)):
            if not isinstance(t, torch.Tensor) or t.ndim != 4 or t.shape[1] != 3:
                shape = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
                raise ValueError(f"LPIPS input {name} must be an N×3×H×W tensor, got {shape}")
            if not t.is_floating_point():
                raise ValueError(f"LPIPS input {name} must be float in [0, 1], got {t.dtype}")
        if x.shape != y.shape:
            raise ValueError(f"LPIPS inputs differ in shape: {tuple(x.shape)} vs {tuple(y.shape)}")
        h, w = x.shape[-2:]
        if min(h, w) < self.min_size:
            raise ValueError(f"LPIPS ({self.net_name}) needs images of at least "
                             f"{self.min_size}×{self.min_size} pixels, got {w}×{h}")
        x_lo, x_hi, y_lo, y_hi = torch.stack(
            (x.detach().amin(), x.detach().amax(), y.detach().amin(), y.detach().amax())).tolist()
        lo, hi = min(x_lo, y_lo), max(x_hi, y_hi)
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError("LPIPS inputs contain non-finite values")
        if lo < -_RANGE_TOL or hi > 1 + _RANGE_TOL:
            raise ValueError(f"LPIPS inputs must be in [0, 1], got values in [{lo:.4g}, "
                             f"{hi:.4g}]; map [-1, 1] images with (x + 1) / 2")

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """LPIPS distance of each pair: x, y float N×3×H×W **in [0, 1]** (RGB) → shape (N,)."""
        self._check(x, y)
        n = x.shape[0]
        z = torch.cat((x, y)).to(self.shift.dtype) * 2.0 - 1.0  # [0, 1] → [-1, 1]
        z = (z - self.shift) / self.scale
        total = z.new_zeros(n)
        for feat, lin in zip(self.net(z), self.lins, strict=True):
            feat = feat / (feat.square().sum(dim=1, keepdim=True).sqrt() + _EPS)
            diff = (feat[:n] - feat[n:]).square()
            total = total + lin(diff).mean(dim=(1, 2, 3))
        return total

    def distance(self, pred: np.ndarray, truth: np.ndarray) -> float:
        """LPIPS of two H×W×3 images (uint8, or float in [0, 1]); the ``lpips_fn`` of
        :func:`aoi3d.quality.score`."""
        x = _image_tensor(pred, "pred", self.device)
        y = _image_tensor(truth, "truth", self.device)
        if x.shape != y.shape:
            raise ValueError(f"image shapes differ: pred {tuple(pred.shape)} vs truth "
                             f"{tuple(truth.shape)}")
        with torch.inference_mode():
            return float(self(x, y)[0])

    def distances(self, pred: np.ndarray, truths: list[np.ndarray]) -> list[float]:
        """LPIPS of ``pred`` against each of ``truths`` (H×W×3, uint8 or float in [0, 1]):
        the same values as :meth:`distance` of each pair, bit for bit, with ``pred`` and
        every truth through the network in one batch (``pred``'s features once). A batch of
        one image takes another convolution path than a batch of two or more, whose per-image
        results agree (tests/unit/domain/test_quality_many.py holds it), hence never one image
        alone."""
        x = _image_tensor(pred, "pred", self.device)
        ys = [_image_tensor(t, "truth", self.device) for t in truths]
        for y, t in zip(ys, truths, strict=True):
            if x.shape != y.shape:
                raise ValueError(f"image shapes differ: pred {tuple(pred.shape)} vs truth "
                                 f"{tuple(t.shape)}")
        if not ys:
            return []
        with torch.inference_mode():
            for y in ys:
                self._check(x, y)
            z = torch.cat((x, *ys)).to(self.shift.dtype) * 2.0 - 1.0  # as forward()
            z = (z - self.shift) / self.scale
            totals = [z.new_zeros(1) for _ in ys]
            for feat, lin in zip(self.net(z), self.lins, strict=True):
                feat = feat / (feat.square().sum(dim=1, keepdim=True).sqrt() + _EPS)
                for i in range(len(ys)):
                    diff = (feat[0:1] - feat[1 + i:2 + i]).square()
                    totals[i] = totals[i] + lin(diff).mean(dim=(1, 2, 3))
            return [float(t[0]) for t in totals]


def _image_tensor(image: np.ndarray, name: str, device: torch.device) -> torch.Tensor:
    """H×W×3 uint8 (÷255) or float in [0, 1] → float32 1×3×H×W on ``device``."""
    arr = np.asarray(image)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"{name} must be an H×W×3 RGB image, got shape {arr.shape}")
    if arr.dtype != np.uint8 and not np.issubdtype(arr.dtype, np.floating):
        raise ValueError(f"{name} must be uint8 or float in [0, 1], got dtype {arr.dtype}")
    t = torch.from_numpy(np.array(arr, dtype=np.float32))  # a copy: inputs may be read-only
    if arr.dtype == np.uint8:
        t /= 255.0
    return t.to(device).permute(2, 0, 1).unsqueeze(0)
