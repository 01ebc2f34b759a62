"""The 3D viewer service: the scene, the cameras and the live reconstruction, orbited in a
browser (viser)."""
