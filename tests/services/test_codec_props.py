"""Property tests of every bus decoder (issue 11): arbitrary bytes never raise anything but
the codec's own ``Rejected`` (so a worker drops and counts them), and valid messages
round-trip."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from aoi3d.scene.camera import Camera, look_at
from services.kit.codec import (
    decode_decision,
    decode_frame,
    decode_quality,
    decode_render,
    encode_frame,
    encode_png,
    with_delivery,
)
from services.kit.observe import Rejected
from services.kit.pb import aoi3d_pb2 as pb
from tests.support.fuzz import fuzz

SETTINGS = fuzz(300)  # tests/support/fuzz.py: `make fuzz` runs it deeper
DECODERS = [lambda b: decode_frame(b), lambda b: decode_frame(b, {1, 2}, (8, 6)),
            decode_decision, decode_render, decode_quality, lambda b: with_delivery(b, 1.0)]
CAMERA = Camera(c2w=look_at((0.0, -4.0, 1.0), (0.0, 0.0, 0.5)), fx=8.0, fy=8.0, cx=4.0,
                cy=3.0, width=8, height=6)
FRAME = encode_frame(camera_id=1, sequence=3, generation_ms=30.0, scene_time_ms=30.0,
                     camera=CAMERA, image=encode_png(np.zeros((6, 8, 3), np.uint8)))


def _only_rejected(payload: bytes) -> None:
    for decode in DECODERS:
        try:
            got = decode(payload)
            if hasattr(got, "rgb"):
                got.rgb()  # the image too: decoded only after the size checks
        except Rejected:
            pass


@SETTINGS
@given(st.binary(max_size=2048))
def test_arbitrary_bytes_are_decoded_or_rejected(payload: bytes) -> None:
    _only_rejected(payload)


@SETTINGS
@given(st.data())
def test_mutated_valid_frames_are_decoded_or_rejected(data) -> None:
    """Bit flips and truncations of a real frame: the parser reaches deep fields."""
    raw = bytearray(FRAME)
    for _ in range(data.draw(st.integers(1, 8))):
        i = data.draw(st.integers(0, len(raw) - 1))
        raw[i] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(raw)))
    _only_rejected(bytes(raw[:cut]))


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@SETTINGS
@given(decision_id=st.integers(0, 2**64 - 1), incarnation=st.integers(0, 2**64 - 1),
       time_ms=finite, cams=st.lists(st.integers(1, 2**32 - 1), max_size=32), data=st.data())
def test_decisions_round_trip(decision_id, incarnation, time_ms, cams, data) -> None:
    aoi = data.draw(st.lists(st.floats(width=64), min_size=len(cams), max_size=len(cams)))
    msg = pb.Decision(decision_id=decision_id, incarnation=incarnation, time_ms=time_ms,
                      camera_ids=cams, aoi_ms=aoi, policy="mat:70")
    got = decode_decision(msg.SerializeToString())
    assert (got.decision_id, got.incarnation, got.time_ms, list(got.camera_ids)) == (
        decision_id, incarnation, time_ms, cams)
    assert all(a == b or (math.isnan(a) and math.isnan(b)) for a, b in zip(got.aoi_ms, aoi,
                                                                           strict=True))


@SETTINGS
@given(time_ms=st.floats(width=64), fraction=st.floats(width=64))
def test_quality_times_and_fractions_are_checked(time_ms: float, fraction: float) -> None:
    msg = pb.Quality(decision_id=1, time_ms=time_ms, dynamic_fraction=fraction)
    try:
        got = decode_quality(msg.SerializeToString())
    except Rejected:
        assert not math.isfinite(time_ms) or not 0.0 <= fraction <= 1.0
    else:
        assert got.time_ms == time_ms and 0.0 <= got.dynamic_fraction <= 1.0


@SETTINGS
@given(gen=finite, seq=st.integers(0, 2**64 - 1))
def test_frames_round_trip(gen: float, seq: int) -> None:
    payload = encode_frame(camera_id=2, sequence=seq, generation_ms=gen, scene_time_ms=0.0,
                           camera=CAMERA, image=encode_png(np.zeros((6, 8, 3), np.uint8)))
    frame = decode_frame(with_delivery(payload, 5.0), {2}, (8, 6))
    assert (frame.camera_id, frame.sequence, frame.generation_ms, frame.delivery_ms) == (
        2, seq, gen, 5.0)
    assert frame.rgb().shape == (6, 8, 3)
