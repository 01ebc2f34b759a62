"""Where a live run is reached: every service's REST port and the Zenoh router's, the one
table the services' settings, ``aoi3d up`` (the supervisor), the console's upstreams,
``aoi3d live``, the benches (bench/ports.py) and the tests' port blocks (tests/support/ports.py)
read. Standard library only, so ``aoi3d --help`` and the supervisor stay light.

* :data:`SERVICE_PORTS`: each service's REST port before ``--port-offset`` (8101…8108; with a
  rig file the ingest takes the camera emulator's).
* :data:`ZENOH_PORT`: the local Zenoh router of ``aoi3d up`` (``--zenoh-port``; compose's
  routers listen on it too, in their own network namespaces).
* :class:`PortBlock`: the ports of one pipeline (``--port-offset``, ``--zenoh-port``): its
  URLs and its ``aoi3d up`` options; :data:`UP` is ``make up``'s.
"""

from __future__ import annotations

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
