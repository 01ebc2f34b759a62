"""The test port scheme (tests/ports.py): every port below the ephemeral range, blocks apart,
and the slot probe steps around a port in use."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from services.supervisor import DEFAULT_PORTS
from tests import ports


def test_every_block_lies_below_the_ephemeral_range_and_apart() -> None:
    low = ports.ephemeral_low()
    seen: set[int] = set()
    for name in ports.NAMES:
        b = ports.block(name)
        assert b.first >= ports.FIRST and b.ports()[-1] < low
        assert not seen & set(b.ports()), f"{name} overlaps another block"
        seen |= set(b.ports())
        rest = {DEFAULT_PORTS[s] + b.rest_offset for s in DEFAULT_PORTS}
        assert rest | {b.zenoh} | {b.extra(i) for i in range(ports.EXTRAS)} <= set(b.ports())
        assert len(rest | {b.zenoh} | {b.extra(i) for i in range(ports.EXTRAS)}) == ports.SIZE
    with pytest.raises(IndexError):
        ports.block("pipeline").extra(ports.EXTRAS)
    with pytest.raises(ValueError):
        ports.block("not a test")


def test_the_ephemeral_range_is_read_and_defaults(tmp_path: Path) -> None:
    f = tmp_path / "range"
    f.write_text("40000\t60999\n")
    assert ports.ephemeral_low(f) == 40000
    assert ports.ephemeral_low(tmp_path / "missing") == 32_768


def test_a_slot_with_a_port_in_use_is_stepped_over() -> None:
    span = ports.SIZE * len(ports.NAMES)
    first = ports.find_slot(0)
    with socket.socket() as s:  # a listener on the slot's last port
        s.bind(("127.0.0.1", first + span - 1))
        s.listen()
        assert ports.find_slot(0) >= first + span
