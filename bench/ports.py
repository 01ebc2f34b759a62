"""The ports of each bench that starts its own pipeline: a fixed ``--port-offset`` /
``--zenoh-port`` (a :class:`services.kit.ports.PortBlock`) apart from ``make up`` and from each
other (tests/unit/test_ports.py checks it). bench/ros2_sweep.sh and bench/ingest_rate.sh read
theirs from here too."""

from __future__ import annotations

from services.kit.ports import PortBlock

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
(tests/support/ports.py); the tests step around any port in use."""
