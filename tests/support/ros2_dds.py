"""Real ROS 2 in the tests (issue 43): rclpy and the message packages from the ROS 2 Kilted
wheels (``aoi3d[ros2]``, which ``make install`` installs), Fast DDS kept on 127.0.0.1 and a
domain of the test's own.

``need_rclpy()`` skips a test where the wheels are missing — but fails it under CI (``CI`` set),
where ``make install`` must have installed them: a CI that silently skipped the only check
against real ROS 2 would prove nothing."""

from __future__ import annotations

import os
import socket

import pytest

from services.ingest.fastdds import configure_fastdds

BASE_PORT, DOMAIN_GAIN = 7400, 250
"""Fast DDS's well-known ports: domain d's start at 7400 + 250·d."""


def need_rclpy() -> None:
    try:
        import rclpy  # noqa: F401
        import sensor_msgs.msg  # noqa: F401
    except ImportError as err:
        if os.environ.get("CI"):
            pytest.fail(f"the ROS 2 wheels are missing under CI ({err}): make install installs "
                        "aoi3d[ros2]")
        pytest.skip(f"no rclpy here ({err}): pip install 'aoi3d[ros2]'")


def _udp_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_domain(start: int | None = None) -> int:
    """A ROS domain id (1…100) whose first Fast DDS ports nobody on this host holds now, from
    ``pid % 100`` on: suites side by side get domains of their own."""
    start = os.getpid() if start is None else start
    for i in range(100):
        d = 1 + (start + i) % 100
        first = BASE_PORT + DOMAIN_GAIN * d
        if all(_udp_free(p) for p in (first + 10, first + 11, first + 12, first + 13)):
            return d
    raise RuntimeError("no free ROS domain in 1…100")


def loopback_env(environ: dict | None = None) -> dict[str, str]:
    """Fast DDS on 127.0.0.1 only (this process's environment, or ``environ``)."""
    return configure_fastdds("loopback", environ=environ)
