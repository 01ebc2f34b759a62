"""Every live test's ports, from one scheme.

Linux gives every outgoing connection a local port from its ephemeral range
(``/proc/sys/net/ipv4/ip_local_port_range``, 32768–60999 by default). A listener there can find
its port already held by any client socket on the machine: a CI run failed on exactly that (a
TLS router's port 36296, "Address already in use", while the suite's own Zenoh and HTTP clients
held ports of that range). So every test port lies in ``[FIRST, low end of that range)``, and each
test file that listens has a block of ports of its own: ``block("pipeline")``.

A pytest process takes one *slot* (one block per name in :data:`NAMES`): the first slot, counting
from ``pid % slots``, whose every port can be bound on 127.0.0.1 right now — so two suites side by
side, or a pipeline left running, are stepped around instead of collided with.

A block is :data:`SIZE` ports: the eight REST ports of ``aoi3d up`` (8101…8108 moved by
:attr:`Block.rest_offset`), then the Zenoh port, then extras (:meth:`Block.extra`)."""

from __future__ import annotations

import os
import socket
from dataclasses import dataclass
from functools import cache
from pathlib import Path

from services.kit.ports import REST_FIRST, REST_LAST

FIRST = 12_000
"""Lowest test port: above the fixed ports of ``make up`` (7447, 8101…), ``make bench``
(bench/ports.py's blocks: pipeline, scale, online_live) and below the ephemeral range."""
SIZE = 16
NAMES = ("pipeline", "recovery", "pool", "sites", "browser", "prometheus", "supervisor",
         "cli-startup", "dataset-errors", "dataset-errors-service", "zenoh-auth", "zenoh-tls",
         "compose", "multihost", "recording", "ros2")
"""The test files that listen; each has one block per slot."""
_REST_FIRST = REST_FIRST
_REST_COUNT = REST_LAST - REST_FIRST + 1
EXTRAS = SIZE - _REST_COUNT - 1


def ephemeral_low(path: Path = Path("/proc/sys/net/ipv4/ip_local_port_range")) -> int:
    """The lowest port Linux may hand to an outgoing connection (32768 when unknown)."""
    try:
        return int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32_768


def _free(port: int) -> bool:
    """True when a listener could bind ``port`` on 127.0.0.1 now (with SO_REUSEADDR, as
    uvicorn and Zenoh bind, so a TIME_WAIT leftover does not count as taken)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def find_slot(start: int) -> int:
    """The first port of the first slot, counting from ``start % slots``, whose ports are all
    free."""
    span = SIZE * len(NAMES)
    slots = (ephemeral_low() - FIRST) // span
    if slots < 1:
        raise RuntimeError(f"no room for test ports between {FIRST} and the ephemeral range "
                           f"starting at {ephemeral_low()}")
    for i in range(slots):
        base = FIRST + (start + i) % slots * span
        if all(_free(p) for p in range(base, base + span)):
            return base
    raise RuntimeError(f"every one of the {slots} test port slots from {FIRST} has a port in use")


@cache
def slot_base() -> int:
    """The first port of this process's slot (found once, from its pid)."""
    return find_slot(os.getpid())


@dataclass(frozen=True)
class Block:
    """One test file's ports."""

    first: int

    @property
    def rest_offset(self) -> int:
        """``aoi3d up --port-offset``: puts 8101…8108 at ``first``…``first + 7``."""
        return self.first - _REST_FIRST

    @property
    def zenoh(self) -> int:
        return self.first + _REST_COUNT

    def extra(self, i: int) -> int:
        """The i-th further port of this block (0 ≤ i < :data:`EXTRAS`)."""
        if not 0 <= i < EXTRAS:
            raise IndexError(f"a block has {EXTRAS} extra ports; asked for #{i}")
        return self.zenoh + 1 + i

    def ports(self) -> range:
        return range(self.first, self.first + SIZE)


def block(name: str) -> Block:
    """The ports of the test file called ``name`` (one of :data:`NAMES`)."""
    return Block(slot_base() + NAMES.index(name) * SIZE)
