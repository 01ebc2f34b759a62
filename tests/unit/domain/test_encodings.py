"""aoi3d.field.encodings: the gather, the hash grid (both layouts), spherical harmonics and the
flat vertex grids, each against an independent reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from aoi3d.field.encodings import (
    HashEncoding,
    cell_index,
    cells_near,
    corner_rows,
    grid_shape,
    hash_vertices,
    interpolate,
    linear_corners,
    resample,
    row_gather,
    spherical_harmonics,
)

UNIT_BOX = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
FLAT_BOX = np.array([[-2.0, -2.0, -0.05], [2.0, 2.0, 2.7]])  # the turbine's proportions


def _points_in(box: np.ndarray, n: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    lo, hi = (torch.tensor(b, dtype=torch.float32) for b in box)
    points = lo + torch.rand(n, 3, generator=gen) * (hi - lo)
    points[0] = hi  # the far corner
    return points


# --- the gather ---------------------------------------------------------------------------------
@pytest.mark.parametrize("channels", [1, 2, 3])
@pytest.mark.parametrize("sparse", [False, True])
def test_row_gather_matches_autograd(channels: int, sparse: bool) -> None:
    gen = torch.Generator().manual_seed(2)
    table = torch.randn(30, channels, dtype=torch.float64, generator=gen, requires_grad=True)
    idx = torch.randint(30, (8, 40), generator=gen, dtype=torch.int32)
    w = torch.rand(8, 40, dtype=torch.float64, generator=gen)
    grad_out = torch.randn(40, channels, dtype=torch.float64, generator=gen)
    ref = (table[idx.long()] * w[..., None]).sum(0)
    (ref_grad,) = torch.autograd.grad(ref, table, grad_out)
    for rows in (idx, idx.long()):
        out = row_gather(table, rows, w, sparse)
        torch.testing.assert_close(out, ref)
        (grad,) = torch.autograd.grad(out, table, grad_out)
        assert grad.is_sparse == sparse
        torch.testing.assert_close(grad.to_dense() if sparse else grad, ref_grad)
    if sparse:  # only the rows the batch touched
        assert grad.coalesce().indices().shape[1] == idx.unique().numel()
    with pytest.raises(ValueError, match="idx and w"):
        row_gather(table, idx, w[:4])


# --- the hash grid ------------------------------------------------------------------------------
def _reference_hash(x: int, y: int, z: int, mask: int) -> int:
    return (x ^ (y * 2654435761) ^ (z * 805459861)) & 0xFFFFFFFF & mask


def test_hash_is_int32_in_range_deterministic_and_the_uint32_hash() -> None:
    gen = torch.Generator().manual_seed(0)
    v = torch.randint(0, 5000, (3, 20000), generator=gen, dtype=torch.int32)
    mask = (1 << 14) - 1
    h = hash_vertices(v[0], v[1], v[2], mask)
    assert h.dtype == torch.int32
    assert int(h.min()) >= 0 and int(h.max()) <= mask
    assert torch.equal(h, hash_vertices(v[0], v[1], v[2], mask))
    for i in range(50):
        x, y, z = (int(v[a, i]) for a in range(3))
        assert int(h[i]) == _reference_hash(x, y, z, mask)
    # The hash spreads: 20k random vertices fill most of 16k buckets (uniform: 1 − e^−1.22).
    assert torch.unique(h).numel() > 0.6 * (mask + 1)
    with pytest.raises(TypeError, match="int32"):
        hash_vertices(v[0].long(), v[1], v[2], mask)


def test_packed_layout_rows_and_weights() -> None:
    enc = HashEncoding(FLAT_BOX, 6, 2, 12, 4, 64)
    assert 0 < enc.n_dense < enc.n_levels  # both kinds of level are exercised
    extent, longest, rows = FLAT_BOX[1] - FLAT_BOX[0], 4.0, 1 << 12
    cells = [[max(1, math.ceil(e / longest * r - 1e-9)) for e in extent] for r in enc.resolutions]
    sizes = [min(math.prod(c + 1 for c in n), rows) for n in cells]
    assert enc.table.shape == (sum(sizes), 2)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    points = _points_in(FLAT_BOX, 300, 1)
    idx, w = enc.indices(points)
    assert idx.shape == w.shape == (8, 6, 300) and idx.dtype == torch.int32
    torch.testing.assert_close(w.sum(0), torch.ones(6, 300))
    for level, res in enumerate(enc.resolutions):
        n = torch.tensor(cells[level], dtype=torch.float32)
        pos = torch.minimum(((points - points.new_tensor(FLAT_BOX[0])) * (res / longest)), n)
        base = torch.minimum(pos.clamp_min(0.0).floor(), n - 1)
        frac, base = pos - base, base.int()
        for k in range(8):
            bits = torch.tensor([k >> 2 & 1, k >> 1 & 1, k & 1], dtype=torch.int32)
            vertex = base + bits
            if level < enc.n_dense:
                ny, nz = cells[level][1] + 1, cells[level][2] + 1
                row = (vertex[:, 0] * ny + vertex[:, 1]) * nz + vertex[:, 2]
            else:
                row = hash_vertices(vertex[:, 0], vertex[:, 1], vertex[:, 2], rows - 1)
            assert torch.equal(idx[k, level], row + int(offsets[level]))
            weight = torch.where(bits.bool(), frac, 1 - frac).prod(dim=1)
            torch.testing.assert_close(w[k, level], weight)


def test_aligned_layout_rows() -> None:
    enc = HashEncoding(UNIT_BOX, 3, 2, 12, 4, 16, layout="aligned")
    assert enc.resolutions == (4, 8, 16) and enc.n_dense == 2  # 8³, 16³ fit; 32³ does not
    assert enc.table.shape == (3 * 4096, 2)  # one table of 2^12 rows per level
    points = _points_in(UNIT_BOX, 200, 5)
    idx, _ = enc.indices(points)
    for level, (res, bits) in enumerate(zip(enc.resolutions, (3, 4, 5), strict=True)):
        base = torch.minimum((points * res).floor(), torch.tensor(res - 1.0)).int()
        for k in range(8):
            v = base + torch.tensor([k >> 2 & 1, k >> 1 & 1, k & 1], dtype=torch.int32)
            if level < enc.n_dense:  # x + y·2^a + z·2^2a
                row = v[:, 0] + (v[:, 1] << bits) + (v[:, 2] << (2 * bits))
            else:
                row = hash_vertices(v[:, 0], v[:, 1], v[:, 2], 4095)
            assert torch.equal(idx[k, level], row + level * 4096)


def test_hash_encoding_interpolates_its_table_and_has_the_right_gradient() -> None:
    enc = HashEncoding(UNIT_BOX, 3, 2, 12, 4, 16, layout="aligned").double()
    with torch.no_grad():
        enc.table.normal_(generator=torch.Generator().manual_seed(3))
    # At a vertex of level 0 the level's features are that vertex's row (dense: x|y<<3|z<<6).
    x = torch.tensor([[0.25, 0.5, 0.75]], dtype=torch.float64)  # vertex (1, 2, 3) of 4 cells
    torch.testing.assert_close(enc(x)[0, :2], enc.table[1 + (2 << 3) + (3 << 6)].detach())
    pts = torch.rand(6, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    for layout in ("packed", "aligned"):
        for feats in (1, 2, 3):  # the three gather paths; one dense and one hashed level each
            small = HashEncoding(UNIT_BOX, 2, feats, 6, 2, 4, layout=layout).double()
            assert small.n_dense == 1
            table = small.table.detach().clone().requires_grad_()
            torch.autograd.gradcheck(
                lambda t, m=small: torch.func.functional_call(m, {"table": t}, (pts,)), (table,)
            )


def test_dense_levels_index_distinct_vertices_without_collisions() -> None:
    for layout in ("packed", "aligned"):
        enc = HashEncoding(UNIT_BOX, 1, 1, 12, 7, 7, layout=layout)  # 8³ = 512 vertices: dense
        assert enc.n_dense == 1
        with torch.no_grad():
            enc.table.copy_(torch.arange(enc.table.shape[0], dtype=torch.float32)[:, None])
        g = torch.arange(8, dtype=torch.float32) / 7
        rows = enc(torch.cartesian_prod(g, g, g)).squeeze(1).round().long()
        assert rows.unique().numel() == 512


def test_hash_encoding_init_and_validation() -> None:
    a = HashEncoding(UNIT_BOX, 2, 2, 8, 2, 4, generator=torch.Generator().manual_seed(9))
    b = HashEncoding(UNIT_BOX, 2, 2, 8, 2, 4, generator=torch.Generator().manual_seed(9))
    assert torch.equal(a.table, b.table) and float(a.table.detach().abs().max()) <= 1e-4
    assert list(dict(a.state_dict())) == ["table"]  # the rest is derived from the arguments
    with pytest.raises(ValueError, match="layout"):
        HashEncoding(UNIT_BOX, 2, 2, 8, 2, 4, layout="tight")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="base_resolution"):
        HashEncoding(UNIT_BOX, 2, 2, 8, 8, 4)


# --- spherical harmonics ------------------------------------------------------------------------
def _real_sh_scipy(levels: int, dirs: np.ndarray) -> np.ndarray:
    """The standard real SH from scipy's complex ones: √2 (−1)^m Im Y_l^|m| (m < 0), Y_l^0,
    √2 (−1)^m Re Y_l^m (m > 0); scipy's Y_l^m carries the Condon–Shortley phase."""
    special = pytest.importorskip("scipy.special")
    theta = np.arccos(np.clip(dirs[:, 2], -1, 1))
    phi = np.arctan2(dirs[:, 1], dirs[:, 0])

    def y(l: int, m: int) -> np.ndarray:  # noqa: E741
        if hasattr(special, "sph_harm_y"):
            return special.sph_harm_y(l, m, theta, phi)
        return special.sph_harm(m, l, phi, theta)

    out = []
    for l in range(levels):  # noqa: E741
        for m in range(-l, l + 1):
            if m < 0:
                out.append(math.sqrt(2) * (-1) ** m * y(l, -m).imag)
            elif m == 0:
                out.append(y(l, 0).real)
            else:
                out.append(math.sqrt(2) * (-1) ** m * y(l, m).real)
    return np.stack(out, axis=-1)


def test_spherical_harmonics_are_the_standard_real_ones() -> None:
    gen = torch.Generator().manual_seed(6)
    d = F.normalize(torch.randn(500, 3, dtype=torch.float64, generator=gen), dim=-1)
    d[0] = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    for levels in range(5):
        sh = spherical_harmonics(d, levels)
        assert sh.shape == (500, levels**2)
        if levels:
            np.testing.assert_allclose(sh.numpy(), _real_sh_scipy(levels, d.numpy()), atol=1e-12)
    # The sign convention, pinned by hand: +x gives Y₁₁ = +√(3/4π), Y₂₂ = +¼√(15/π).
    sh = spherical_harmonics(d[:1], 3)[0]
    assert sh[3] == pytest.approx(math.sqrt(3 / (4 * math.pi)))
    assert sh[8] == pytest.approx(0.25 * math.sqrt(15 / math.pi))
    assert sh[6] == pytest.approx(-0.25 * math.sqrt(5 / math.pi))  # Y₂₀ on the equator
    with pytest.raises(ValueError, match="levels"):
        spherical_harmonics(d, 5)


def test_spherical_harmonics_are_orthonormal() -> None:
    d = F.normalize(torch.randn(200000, 3, dtype=torch.float64), dim=-1)
    sh = spherical_harmonics(d, 4)
    gram = 4 * math.pi * sh.T @ sh / d.shape[0]
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.03, rtol=0)


# --- vertex grids stored flat -------------------------------------------------------------------
def test_grid_shape_has_cubic_voxels() -> None:
    assert grid_shape(FLAT_BOX, 129) == (129, 129, 89)
    assert grid_shape(UNIT_BOX, 2) == (2, 2, 2)


@pytest.mark.parametrize("shape", [(5, 4, 6), (5, 7), (9,)])
def test_interpolate_matches_grid_sample_and_its_gradient(shape: tuple[int, ...]) -> None:
    torch.manual_seed(1)
    dims = len(shape)
    table = torch.randn(math.prod(shape), 3, requires_grad=True)
    hi = torch.tensor([n - 1.0 for n in shape])
    coords = torch.rand(50, dims) * hi
    coords[0] = hi  # the far corner
    coords[1] = -0.5  # outside: clamped to the first vertex
    for sparse in (False, True):
        out = interpolate(table, shape, coords, sparse)
        # grid_sample wants (x, y, …) = (last, …, first) axis, normalised to [-1, 1]; a line is
        # a 1-pixel-wide image.
        norm = (coords.clamp_min(0) / hi * 2 - 1).flip(-1)
        if dims == 1:
            vol, norm = table.T.reshape(1, 3, 1, shape[0]), torch.cat([norm, 0 * norm], 1)
        else:
            vol = table.T.reshape(1, 3, *shape)
        grid = norm.view(1, *([1] * (vol.ndim - 3)), -1, max(dims, 2))
        ref = F.grid_sample(vol, grid, align_corners=True).reshape(3, -1).T
        torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-5)
        weights = torch.randn(50, 3)
        (grad,) = torch.autograd.grad((out * weights).sum(), table)
        (ref_grad,) = torch.autograd.grad((ref * weights).sum(), table)
        assert grad.is_sparse == sparse
        torch.testing.assert_close(grad.to_dense(), ref_grad, atol=1e-5, rtol=1e-5)


def test_corner_rows_are_row_major_with_the_first_axis_major() -> None:
    coords = torch.tensor([[1.25, 2.5, 0.75]])
    shape = (4, 5, 3)
    axes = [linear_corners(coords[:, d], n) for d, n in enumerate(shape)]
    idx, w = corner_rows(axes, shape)
    assert idx.shape == w.shape == (8, 1)
    for k in range(8):
        i, j, l = 1 + (k >> 2 & 1), 2 + (k >> 1 & 1), k & 1  # noqa: E741
        assert int(idx[k, 0]) == (i * 5 + j) * 3 + l
        fx, fy, fz = 0.25, 0.5, 0.75
        expected = (fx if k & 4 else 1 - fx) * (fy if k & 2 else 1 - fy) * (fz if k & 1 else 1 - fz)
        assert float(w[k, 0]) == pytest.approx(expected)
    lo, frac = linear_corners(torch.tensor([-1.0, 0.0, 2.5, 3.0, 9.0]), 4)
    assert lo.tolist() == [0, 0, 2, 2, 2] and frac.tolist() == [0.0, 0.0, 0.5, 1.0, 1.0]


def test_cell_index_is_row_major_and_clamped() -> None:
    coords = torch.tensor([[0.5, 1.5, 2.5], [-3.0, 9.0, 0.0], [2.99, 0.0, 3.5]])
    assert cell_index(coords, (3, 2, 4)).tolist() == [(0 * 2 + 1) * 4 + 2, 4, 2 * 8 + 3]
    assert cell_index(coords[:, :2], (3, 2)).tolist() == [1, 1, 4]


@pytest.mark.parametrize(
    "shape, new_shape", [((3, 4, 5), (5, 7, 9)), ((3, 4), (5, 7)), ((3,), (5,))]
)
def test_resample_keeps_a_linear_function(
    shape: tuple[int, ...], new_shape: tuple[int, ...]
) -> None:
    def linear(s: tuple[int, ...]) -> torch.Tensor:  # f = Σ_d (d + 1) · x_d over [0, 1]^D
        axes = [torch.linspace(0, 1, n) for n in s]
        grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(s))
        f = (grid * torch.arange(1.0, len(s) + 1)).sum(-1)
        return torch.stack([f, -f], 1)

    out = resample(linear(shape), shape, new_shape)
    assert out.shape == (math.prod(new_shape), 2) and out.is_contiguous()
    torch.testing.assert_close(out, linear(new_shape), atol=1e-5, rtol=0)


def test_cells_near_matches_max_pooling() -> None:
    torch.manual_seed(2)
    for shape in [(2, 3, 4), (6, 7, 9)]:
        flags = torch.rand(shape) > 0.9
        ref = F.max_pool3d(flags.float()[None, None], 2, stride=1)
        ref = F.max_pool3d(ref, 3, stride=1, padding=1)[0, 0] > 0
        assert torch.equal(cells_near(flags), ref)
