"""aoi3d: the timeliness–fidelity tradeoff in real-time 3D scene representation.

The domain library: scene, channel, AoI, policies, radiance field, quality. It imports no
I/O framework (zenoh, fastapi, prometheus); the services under ``services/`` adapt it.
"""

__version__ = "0.1.0"
