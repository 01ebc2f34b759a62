"""The fused C kernels (aoi3d.field.native) against the torch code they replace."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from aoi3d.field import native
from aoi3d.field.background import latlong_background
from aoi3d.field.encodings import interpolate, vertex_coords
from aoi3d.field.optim import LazyAdam
from aoi3d.field.rays import sample_uniform
from aoi3d.field.render import volume_render

pytestmark = pytest.mark.skipif(not native.available(), reason="no C compiler: torch path only")


@pytest.fixture
def torch_only(monkeypatch: pytest.MonkeyPatch):
    """A context in which the kernels are off (the torch code runs)."""
    lib = native._lib()

    class Off:
        def __enter__(self) -> None:
            monkeypatch.setattr(native, "_LIB", None)

        def __exit__(self, *exc: object) -> None:
            monkeypatch.setattr(native, "_LIB", lib)

    return Off()


def _close(a: torch.Tensor, b: torch.Tensor, atol: float = 1e-6) -> None:
    torch.testing.assert_close(a, b, atol=atol, rtol=1e-5)


def test_volume_render_matches_torch(torch_only) -> None:
    g = torch.Generator().manual_seed(0)
    counts = torch.randint(0, 20, (50,), generator=g)
    counts[3] = 0  # a ray without samples sees the background only
    ray = torch.repeat_interleave(torch.arange(50), counts)
    n = ray.numel()
    sigma = (torch.rand(n, generator=g) * 5).requires_grad_()
    rgb = torch.rand(n, 3, generator=g).requires_grad_()
    bg = torch.rand(50, 3, generator=g).requires_grad_()
    deltas = torch.rand(n, generator=g) * 0.1

    def run() -> tuple[torch.Tensor, ...]:
        out = volume_render(sigma, rgb, deltas, ray, bg)
        loss = ((out.rgb ** 2).sum() + (out.weights * torch.arange(n)).sum() * 0.01
                + out.opacity.sum() * 0.1 + (out.transmittance * torch.arange(50)).sum() * 0.05)
        return (out.rgb, out.transmittance, out.weights, out.opacity,
                *torch.autograd.grad(loss, (sigma, rgb, bg)))

    fused = run()
    with torch_only:
        reference = run()
    for a, b in zip(fused, reference, strict=True):
        _close(a, b)


def test_grid_query_matches_torch(torch_only) -> None:
    g = torch.Generator().manual_seed(1)
    shape = (7, 5, 9)
    table = torch.randn(7 * 5 * 9, 4, generator=g).requires_grad_()
    aabb = torch.tensor([[-1.0, -0.5, 0.0], [1.0, 0.5, 2.0]])
    # points inside and outside the box (clamped to it)
    points = torch.rand(300, 3, generator=g) * torch.tensor([2.4, 1.2, 2.4]) + torch.tensor(
        [-1.2, -0.6, -0.2])
    ws, wc = torch.randn(300, generator=g), torch.randn(300, 3, generator=g)
    fused = native.grid_query(table, points, aabb, shape)
    assert fused is not None
    raw = interpolate(table, shape, vertex_coords(points, aabb, shape), sparse=True)
    sigma, rgb = F.softplus(raw[:, 0]), torch.sigmoid(raw[:, 1:])
    _close(fused[0], sigma)
    _close(fused[1], rgb)
    g1, = torch.autograd.grad((fused[0] * ws).sum() + (fused[1] * wc).sum(), table)
    g2, = torch.autograd.grad((sigma * ws).sum() + (rgb * wc).sum(), table)
    assert g1.is_sparse
    _close(g1.to_dense(), g2.to_dense())
    torch.testing.assert_close(g1._indices(), g2.coalesce()._indices())
    # the scatter buffers are left zero: a second backward gives the same gradient
    again = native.grid_query(table, points, aabb, shape)
    g3, = torch.autograd.grad((again[0] * ws).sum() + (again[1] * wc).sum(), table)
    torch.testing.assert_close(g3.to_dense(), g1.to_dense(), atol=0, rtol=0)


@pytest.mark.parametrize("jittered", [False, True])
def test_sample_uniform_matches_torch(torch_only, jittered: bool) -> None:
    g = torch.Generator().manual_seed(2)
    origins = torch.randn(300, 3, generator=g)
    dirs = F.normalize(torch.randn(300, 3, generator=g), dim=1)
    t_near = torch.rand(300, generator=g)
    t_far = t_near + torch.rand(300, generator=g) * 2 - 0.3  # some rays miss
    jitter = torch.rand(300, generator=g) if jittered else None
    fused = sample_uniform(origins, dirs, t_near, t_far, 0.047, jitter)
    with torch_only:
        reference = sample_uniform(origins, dirs, t_near, t_far, 0.047, jitter)
    assert torch.equal(fused.ray_index, reference.ray_index)
    assert torch.equal(fused.deltas, reference.deltas)
    _close(fused.points, reference.points)


@pytest.mark.parametrize("up_axis", [1, 2])
def test_latlong_background_matches_torch(torch_only, up_axis: int) -> None:
    g = torch.Generator().manual_seed(3)
    env = torch.randn(16, 32, 3, generator=g).requires_grad_()
    dirs = F.normalize(torch.randn(500, 3, generator=g), dim=1)
    dirs[0] = torch.tensor([0.0, 0.0, 1.0])
    dirs[1] = torch.tensor([0.0, -1.0, 0.0])
    weights = torch.randn(500, 3, generator=g)
    fused = latlong_background(env, dirs, up_axis)
    g1, = torch.autograd.grad((fused * weights).sum(), env)
    with torch_only:
        reference = latlong_background(env, dirs, up_axis)
        g2, = torch.autograd.grad((reference * weights).sum(), env)
    _close(fused, reference, atol=1e-5)  # acos / atan2 rounding
    _close(g1, g2, atol=1e-5)


def test_weighted_colour_error_matches_torch() -> None:
    g = torch.Generator().manual_seed(4)
    colours = torch.rand(500, 3, generator=g).requires_grad_()
    weights = torch.rand(500, generator=g).requires_grad_()
    target = torch.rand(40, 3, generator=g)
    ray = torch.sort(torch.randint(0, 40, (500,), generator=g))[0]
    fused = native.weighted_colour_error(colours, weights, target, ray)
    reference = (weights * ((colours - target[ray]) ** 2).sum(1)).sum()
    _close(fused, reference, atol=1e-4)
    for a, b in zip(torch.autograd.grad(fused * 3, (colours, weights)),
                    torch.autograd.grad(reference * 3, (colours, weights)), strict=True):
        _close(a, b)


@pytest.mark.parametrize("sparse", [False, True])
def test_lazy_adam_matches_torch(torch_only, sparse: bool) -> None:
    def run() -> torch.Tensor:
        g = torch.Generator().manual_seed(5)
        table = torch.nn.Parameter(torch.randn(30, 4, generator=g))
        opt = LazyAdam([{"params": [table], "lr": 0.1}])
        for _ in range(5):
            rows = torch.randint(0, 30, (12,), generator=g)
            if sparse:
                unique = torch.unique(rows)
                values = torch.randn(unique.shape[0], 4, generator=g)
                table.grad = torch.sparse_coo_tensor(unique[None], values, (30, 4),
                                                     check_invariants=True)
            else:
                table.grad = torch.randn(30, 4, generator=g)
            opt.step()
        return table.detach().clone()

    fused = run()
    with torch_only:
        reference = run()
    _close(fused, reference)


def test_lazy_adam_kernel_refuses_unsorted_rows() -> None:
    p, m, v = torch.zeros(4, 2), torch.zeros(4, 2), torch.zeros(4, 2)
    rows = torch.tensor([2, 1])  # not increasing: the torch path sums duplicates first
    assert not native.lazy_adam_rows(p, m, v, rows, torch.ones(2, 2), 0.9, 0.99, 0.1, 1.0, 1e-15)
    assert torch.equal(p, torch.zeros(4, 2))


def test_disabled_by_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AOI3D_NATIVE", "0")
    monkeypatch.setattr(native, "_TRIED", False)
    monkeypatch.setattr(native, "_LIB", None)
    assert not native.available()
    assert native.volume_render(torch.zeros(1), torch.zeros(1, 3), torch.zeros(1),
                                torch.zeros(1, dtype=torch.long), torch.zeros(1, 3)) is None


@pytest.mark.parametrize("sample_rgb_loss, opacity_loss", [(0.0, 0.0), (0.05, 0.01)])
def test_grid_training_grads_are_autograds(sample_rgb_loss: float, opacity_loss: float) -> None:
    """The grid's step without autograd gives the loss and gradients that autograd gives
    through the same kernels, with and without the regularisers."""
    g = torch.Generator().manual_seed(5)
    shape = (6, 5, 7)
    aabb = torch.tensor([[-1.0, -0.5, 0.0], [1.0, 0.5, 2.0]])
    table = torch.randn(6 * 5 * 7, 4, generator=g).requires_grad_()
    env = torch.randn(4, 8, 3, generator=g).requires_grad_()
    dirs = F.normalize(torch.randn(40, 3, generator=g), dim=1)
    origins = torch.tensor([0.0, 0.0, 1.0]) - 1.5 * dirs
    samples = sample_uniform(origins, dirs, torch.full((40,), 0.5), torch.full((40,), 2.5), 0.1,
                             torch.rand(40, generator=g))
    target = torch.rand(40, 3, generator=g)
    mse, rows, values, grad_env = native.grid_training_grads(
        table, aabb, shape, env, 2, samples.points, samples.deltas, samples.ray_index, dirs,
        target, sample_rgb_loss, opacity_loss)

    sigma, rgb = native.grid_query(table, samples.points, aabb, shape)
    out = volume_render(sigma, rgb, samples.deltas, samples.ray_index,
                        latlong_background(env, dirs, 2))
    ref_mse = torch.mean((out.rgb - target) ** 2)
    loss = (ref_mse + sample_rgb_loss * native.weighted_colour_error(
        rgb, out.weights, target, samples.ray_index) / 40 + opacity_loss * out.opacity.sum() / 40)
    g_table, g_env = torch.autograd.grad(loss, (table, env))
    assert mse == pytest.approx(float(ref_mse.detach()), rel=1e-6)
    _close(torch.sparse_coo_tensor(rows[None], values, table.shape,
                                   check_invariants=True).to_dense(),
           g_table.to_dense())
    torch.testing.assert_close(rows, g_table._indices()[0])
    _close(grad_env, g_env)
