"""The test port scheme (tests/support/ports.py): every port below the ephemeral range,
blocks apart, and the slot probe steps around a port in use."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from services.kit.ports import SERVICE_PORTS as DEFAULT_PORTS
from tests.support import ports


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


def test_every_port_comes_from_the_one_table() -> None:
    """services/kit/ports.py is the one home: the services' settings, the supervisor, the
    console's upstreams and the Zenoh defaults read it; the benches' blocks (bench/ports.py)
    are apart from ``make up`` and from each other."""
    import importlib

    from bench.ports import BENCH_BLOCKS
    from services.console.settings import UPSTREAMS
    from services.kit import ports as table
    from services.kit.settings import CommonSettings
    from services.router import RouterSettings
    from services.supervisor import DEFAULT_PORTS as SUPERVISED
    from services.supervisor import SERVICES, UpConfig

    for name, port in table.SERVICE_PORTS.items():
        settings = importlib.import_module(f"services.{name}.settings").Settings
        assert settings.model_fields["port"].default == port, name
    assert SUPERVISED is table.SERVICE_PORTS and tuple(table.SERVICE_PORTS) == SERVICES
    assert {k: v for k, v in table.SERVICE_PORTS.items()
            if k not in ("console", "recorder", "viewer")} == UPSTREAMS
    assert UpConfig().zenoh_port == table.ZENOH_PORT
    assert CommonSettings().zenoh_connect == [f"tcp/127.0.0.1:{table.ZENOH_PORT}"]
    assert RouterSettings().listen == [f"tcp/127.0.0.1:{table.ZENOH_PORT}"]
    taken: dict[int, str] = {p: "up" for p in table.UP.ports()}
    for name, block in BENCH_BLOCKS.items():
        for p in block.ports():
            assert p not in taken, f"bench {name}'s port {p} is also {taken[p]}'s"
            taken[p] = name
    assert table.UP.url("dispatcher", "/status") == "http://127.0.0.1:8104/status"
    assert BENCH_BLOCKS["pipeline"].up_args() == ["--port-offset", "1000",
                                                  "--zenoh-port", "7547"]


def test_the_bench_blocks_comments_say_their_rest_ports() -> None:
    """Each ``# REST first…last`` beside a bench's block in bench/ports.py is its REST ports
    (a service added to the table moves ``last``: 8108 since the viewer)."""
    import re

    from bench import ports as table

    said = re.findall(r'"(\w+)": PortBlock\([^)]*\),\s*# REST (\d+)…(\d+)',
                      Path(table.__file__).read_text())
    assert len(said) >= 5, said
    for name, first, last in said:
        rest = table.BENCH_BLOCKS[name].ports()[:-1]
        assert (int(first), int(last)) == (rest[0], rest[-1]), name
