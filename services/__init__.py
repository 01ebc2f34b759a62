"""The aoi3d services: adapters between Zenoh/REST and the domain package."""

import aoi3d  # noqa: F401  (sets OMP_WAIT_POLICY before any service imports torch)
