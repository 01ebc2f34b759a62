"""Tests of the domain package, aoi3d/: the scene, channel, AoI, policies, the radiance field,
quality, the experiment engine and its claims, the pool, PPO, the live sweep's statistics."""
