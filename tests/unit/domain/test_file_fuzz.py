"""Rig files and trace files fuzzed (issue 44), on top of the ROS wire's fuzz: whatever bytes,
encodings, values, sizes or URLs a file holds, reading it gives a rig or a trace that can be
used — every number finite, a url rtsp/rtsps or a path, a trace's period within its cap and
its mean computed at once — or one error that names the file; never another exception, never
a slow read. A refused trace leaves the network's links as they were. Budget: tests/support/
fuzz.py (``make fuzz`` runs it 20 times deeper)."""

from __future__ import annotations

import json
import math
import tempfile
import time
from pathlib import Path

import yaml
from hypothesis import given
from hypothesis import strategies as st

from aoi3d.channel import ChannelSpecError, parse_channel
from aoi3d.channel.varying import MAX_TRACE_PERIOD_MS
from aoi3d.rigfile import Rig, RigError, load_rig, rig_from_dict
from services.network.core import NetworkCore
from tests.support.fuzz import fuzz
from tests.support.ingest import rig_doc
from tests.support.timeouts import timeout_scale

SLOW_S = 2.0 * timeout_scale()
"""No file may take longer than this to accept or refuse."""
TMP = Path(tempfile.mkdtemp(prefix="aoi3d-fuzz-"))

VALUES = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-2**80, max_value=2**80),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=30),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=17),
    st.lists(st.lists(st.floats(min_value=-2, max_value=2), max_size=5), max_size=5),
    st.dictionaries(st.text(max_size=8), st.integers(), max_size=3))
ENCODINGS = st.sampled_from(["utf-8", "utf-8-sig", "utf-16", "utf-16-le", "utf-32", "latin-1",
                             "cp1252", "utf-7"])


def _leaves(doc: object, at: tuple = ()) -> list[tuple]:
    if isinstance(doc, dict):
        return [p for k, v in doc.items() for p in _leaves(v, (*at, k))] or [at]
    if isinstance(doc, list):
        return [p for i, v in enumerate(doc) for p in _leaves(v, (*at, i))] or [at]
    return [at]


def _set(doc: object, path: tuple, value: object) -> None:
    for key in path[:-1]:
        doc = doc[key]  # type: ignore[index]
    doc[path[-1]] = value  # type: ignore[index]


def _base() -> dict:
    doc = rig_doc()
    doc["cameras"].append({"name": "ip", "url": "rtsp://10.0.0.7/s", "intrinsics": dict(
        doc["cameras"][0]["intrinsics"]), "pose": {"position": [0, 0, 1],
                                                   "orientation": [0, 0, 0, 1]}})
    return doc


def _finite_everywhere(value: object) -> bool:
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, dict):
        return all(_finite_everywhere(v) for v in value.values())
    if isinstance(value, list | tuple):
        return all(_finite_everywhere(v) for v in value)
    return True


def _check_rig(path: Path) -> Rig | None:
    t = time.perf_counter()
    try:
        rig = load_rig(path)
    except RigError as err:
        text = str(err)
        assert text and all(line.startswith(str(path)) for line in text.splitlines()), text
        rig = None
    took = time.perf_counter() - t
    assert took < SLOW_S, f"{took:.2f} s"
    if rig is not None:
        assert _finite_everywhere(rig.model_dump())
        assert all(c.protocol in (None, "rtsp", "rtsps") or c.protocol in rig.url_protocols
                   for c in rig.cameras)
    return rig


@fuzz(150)
@given(st.data(), st.sampled_from([".yaml", ".json", ".JSON", ".yml"]))
def test_a_rig_with_any_values_is_a_usable_rig_or_one_error_per_field(data, suffix) -> None:
    doc = _base()
    leaves = _leaves(doc)
    for _ in range(data.draw(st.integers(1, 4))):
        _set(doc, data.draw(st.sampled_from(leaves)), data.draw(VALUES))
    path = TMP / f"rig{suffix}"
    text = (json.dumps(doc) if suffix.lower() == ".json"
            else yaml.safe_dump(doc, allow_unicode=data.draw(st.booleans())))
    path.write_bytes(text.encode("utf-8", "surrogatepass"))
    _check_rig(path)


@fuzz(100)
@given(st.binary(max_size=3000), st.sampled_from([".yaml", ".json"]))
def test_any_bytes_are_a_rig_or_one_error(raw: bytes, suffix: str) -> None:
    path = TMP / f"bytes{suffix}"
    path.write_bytes(raw)
    _check_rig(path)


@fuzz(100)
@given(ENCODINGS, st.integers(0, 4000), st.binary(max_size=40))
def test_a_rig_in_any_encoding_cut_or_spliced_is_a_rig_or_one_error(
        encoding: str, cut: int, splice: bytes) -> None:
    raw = yaml.safe_dump(_base(), allow_unicode=True).encode(encoding)
    path = TMP / "enc.yaml"
    path.write_bytes(raw)
    assert _check_rig(path) is not None or encoding in ("utf-16-le", "utf-7")
    path.write_bytes(raw[:cut] + splice + raw[cut:])
    _check_rig(path)


@fuzz(150)
@given(st.text(max_size=60), st.lists(st.from_regex(r"[a-z][a-z0-9+.-]{0,8}", fullmatch=True),
                                      max_size=3))
def test_any_url_is_rtsp_a_path_or_an_allowed_protocol(url: str, allowed: list[str]) -> None:
    doc = _base()
    doc["cameras"][3]["url"] = url
    if allowed:
        doc["url_protocols"] = allowed
    try:
        rig = rig_from_dict(doc, "rig.yaml")
    except RigError as err:
        assert all(line.startswith("rig.yaml: ") for line in str(err).splitlines())
        return
    protocol = rig.cameras[3].protocol
    assert protocol in (None, "rtsp", "rtsps", *allowed), url
    assert rig.cameras[3].kind == ("rtsp" if protocol in ("rtsp", "rtsps") else "video")


@fuzz(40)
@given(st.integers(0, 400), st.booleans())
def test_any_number_of_cameras_is_a_rig_or_refused_at_once(n: int, as_json: bool) -> None:
    doc = _base()
    cam = doc["cameras"][2]
    doc["cameras"] = doc["cameras"][:1] + [
        {**cam, "name": f"c{i}", "image": f"/c{i}/image_raw/compressed"} for i in range(n)]
    path = TMP / ("many.json" if as_json else "many.yaml")
    path.write_text(json.dumps(doc) if as_json else yaml.safe_dump(doc))
    rig = _check_rig(path)
    assert (rig is not None) == (1 <= n <= 256)


# ---------------------------------------------------------------- traces
def _check_trace(path: Path, options: str = "") -> None:
    t = time.perf_counter()
    try:
        channel = parse_channel(f"trace:{path}{options}")
        assert channel.trace.period_ms <= MAX_TRACE_PERIOD_MS
        mean = channel.mean_ms
        assert math.isfinite(mean) and mean >= 1
    except ChannelSpecError as err:
        assert "\n" not in str(err)
        assert str(path) in str(err) or "option" in str(err) or "must be" in str(err), err
    took = time.perf_counter() - t
    assert took < SLOW_S, f"{took:.2f} s"


NUMBERS = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                    st.integers(min_value=-2**70, max_value=2**70),
                    st.integers(min_value=0, max_value=10**9))


@fuzz(150)
@given(st.lists(NUMBERS, max_size=60), st.booleans(), st.sampled_from(["\n", "\r\n", " "]))
def test_a_trace_of_any_numbers_is_a_bounded_channel_or_one_error(
        values: list, ordered: bool, sep: str) -> None:
    if ordered:
        values = sorted(v for v in values if not (isinstance(v, float) and math.isnan(v)))
    path = TMP / "t.up"
    path.write_text(sep.join(str(v) for v in values))
    _check_trace(path)


@fuzz(100)
@given(st.binary(max_size=4000))
def test_a_trace_of_any_bytes_is_a_channel_or_one_error(raw: bytes) -> None:
    path = TMP / "b.up"
    path.write_bytes(raw)
    _check_trace(path)


OPTION = st.one_of(st.text(max_size=12), st.floats(allow_nan=True, allow_infinity=True).map(str),
                   st.integers(-10**12, 10**12).map(str))


@fuzz(100)
@given(st.lists(st.tuples(st.sampled_from(["offset", "spread", "scale", "x"]), OPTION),
                max_size=3),
       st.lists(st.integers(0, 10**8), min_size=1, max_size=30))
def test_trace_options_and_the_links_a_refusal_leaves_alone(options, times) -> None:
    path = TMP / "o.up"
    path.write_text("\n".join(str(t) for t in sorted(times)))
    opts = "".join(f",{k}={v}" for k, v in options)
    _check_trace(path, opts)
    core = NetworkCore(3, delay="const:40", per_camera={2: "exp:10"}, seed=4)
    before = (core.config, core.started_ms, [s.delay.spec for s in core.link_stats(0.0)])
    try:
        core.update(delay=f"trace:{path}{opts}", seed=5, now_ms=100.0)
    except ValueError:
        assert (core.config, core.started_ms,
                [s.delay.spec for s in core.link_stats(0.0)]) == before
