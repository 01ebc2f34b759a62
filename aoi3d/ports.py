"""Where a live run is reached: every port of the project, and the names that address a site.

The one table the services' settings, ``aoi3d up`` (the supervisor), the console's upstreams,
``aoi3d live``, the benches and the tests' port blocks (tests/support/ports.py) all read. It lives
in the domain package, below both ``aoi3d_cli`` and ``services``, because both need it and
``aoi3d`` never imports ``services`` (pyproject.toml's import contracts); standard library
only, so ``aoi3d --help`` and the supervisor stay light.

* :data:`SERVICE_PORTS`: each service's REST port before ``--port-offset`` (8101…8108; with a
  rig file the ingest takes the camera emulator's).
* :data:`ZENOH_PORT`: the local Zenoh router of ``aoi3d up`` (``--zenoh-port``; compose's
  routers listen on it too, in their own network namespaces).
* :data:`BENCH_BLOCKS`: the fixed ``--port-offset``/``--zenoh-port`` of each bench that starts
  a pipeline, apart from ``make up`` and from each other (:class:`PortBlock`).
* :data:`TEST_FIRST`: the lowest port of the tests' blocks (tests/support/ports.py hands them out).
* :data:`DEFAULT_SITE`, :func:`check_site`, :func:`site_names`: a site's name, the segment
  of ``/sites/<site>/…`` and of the key space ``aoi3d/<run>/<site>/…``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

SERVICE_PORTS: dict[str, int] = {"camera": 8101, "network": 8102, "scheduler": 8103,
                                 "dispatcher": 8104, "metrics": 8105, "console": 8106,
                                 "recorder": 8107, "viewer": 8108}
"""Each service's REST port before ``--port-offset``, in ``aoi3d up``'s start order."""
ZENOH_PORT = 7447
"""TCP port of the Zenoh router (``aoi3d up --zenoh-port``, ``AOI3D_ZENOH_CONNECT``)."""
REST_FIRST = min(SERVICE_PORTS.values())
REST_LAST = max(SERVICE_PORTS.values())
LOCALHOST = "127.0.0.1"


def rest_port(service: str, offset: int = 0) -> int:
    """``service``'s REST port moved by ``offset`` (``KeyError`` for an unknown service)."""
    return SERVICE_PORTS[service] + offset


@dataclass(frozen=True)
class PortBlock:
    """The ports of one pipeline: the REST ports (8101…8108) moved by ``offset``, a Zenoh
    port."""

    offset: int = 0
    zenoh: int = ZENOH_PORT

    def rest(self, service: str) -> int:
        return rest_port(service, self.offset)

    def url(self, service: str, path: str = "", host: str = LOCALHOST) -> str:
        """``http://<host>:<service's port><path>``."""
        return f"http://{host}:{self.rest(service)}{path}"

    def up_args(self) -> list[str]:
        """The ``aoi3d up`` options that put a pipeline on these ports."""
        return ["--port-offset", str(self.offset), "--zenoh-port", str(self.zenoh)]

    def ports(self) -> list[int]:
        """Every port of the block: the REST ports, then the Zenoh port."""
        return [self.rest(s) for s in SERVICE_PORTS] + [self.zenoh]


UP = PortBlock()
"""``aoi3d up`` / ``make up`` with its defaults."""
BENCH_BLOCKS: dict[str, PortBlock] = {
    "pipeline": PortBlock(1000, 7547),     # REST 9101…9108
    "scale": PortBlock(3000, 7647),        # REST 11101…11108
    "online_live": PortBlock(3200, 7649),  # REST 11301…11308
    "soak": PortBlock(4000, 9467),         # REST 12101…12108
    "chaos": PortBlock(5000, 9567),        # REST 13101…13108
    "chaos_multihost": PortBlock(5100, 9667),  # the multi-host stack's published 13203…13205
    "live_channel": PortBlock(700, 7747),  # REST 8801…8808
    "ros2_sweep": PortBlock(3500, 11647),  # REST 11601…11608 (bench/ros2_sweep.sh)
    "live_default": PortBlock(3300, 9647),  # REST 11401…11408 (bench/live_default.py)
    "realtime": PortBlock(3400, 9747),     # REST 11501…11508 (bench/realtime.py)
    "science_twin": PortBlock(3600, 9847),  # REST 11701…11708 (bench/science_twin.py)
}
"""The ports of each bench that starts its own pipeline (bench/<name>.py), so that a running
``make up`` and the other benches are not disturbed. soak's and chaos's lie in the tests' range
(:data:`TEST_FIRST`…); the tests step around any port in use."""
TEST_FIRST = 12_000
"""Lowest port of the tests' blocks (tests/support/ports.py): above ``make up`` (7447, 8101…)
and the pipeline and scale benches, below Linux's ephemeral range."""

DEFAULT_SITE = "site1"
"""The site of a one-site run, and the one the REST paths without ``/sites/<site>`` address."""
SITE_PATTERN = r"^[a-z0-9][a-z0-9_-]{0,31}$"
RESERVED_SITES = frozenset({"pool", "sites"})


def check_site(name: str) -> str:
    """``name`` if it can name a site (a key chunk, a URL segment, a label value), else
    ``ValueError``."""
    if not re.fullmatch(SITE_PATTERN, name) or name in RESERVED_SITES:
        raise ValueError(f"site name {name!r}: 1-32 of a-z 0-9 _ -, starting with a letter or "
                         f"digit, not one of {', '.join(sorted(RESERVED_SITES))}")
    return name


def site_names(n: int) -> list[str]:
    """The sites of an ``n``-site run: ``site1`` … ``site<n>``."""
    return [f"site{i}" for i in range(1, n + 1)]
