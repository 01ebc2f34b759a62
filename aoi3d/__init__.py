"""aoi3d: the timeliness–fidelity tradeoff in real-time 3D scene representation.

The domain library: scene, channel, AoI, policies, radiance field, quality. It imports no
I/O framework (zenoh, fastapi, prometheus); the services under ``services/`` adapt it.
"""

import os

# OpenMP threads that spin while waiting collapse when another process holds a core: on this
# 2-core machine under load, 2 torch threads trained the grid at 1.1k rays/s with the default
# (active) wait policy and at 41k rays/s with a passive one (`aoi3d field train --threads 2
# --seconds 5`). libgomp reads this when torch loads it, so it is set here, before any aoi3d
# module imports torch; an explicit setting in the environment wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
