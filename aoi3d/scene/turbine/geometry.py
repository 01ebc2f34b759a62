"""The turbine scene's geometry: where every solid stands, and how a ray meets each kind.

World is z-up, metres-ish, the turbine stands at the origin and its rotor faces −y (where the
camera rig stands). The intersection routines take (origins (N, 3), dirs (N, 3)) and return
(t (N,), unit normals (N, 3)); t is +inf on a miss, and rays start outside every primitive
(cameras stand outside the box).
"""

from __future__ import annotations

import numpy as np

BLADES = 3
"""Number of (identical) rotor blades: the image repeats every 1/3 revolution."""

# --- geometry (world units, z-up) ------------------------------------------------------------
GROUND_HALF = 2.0
"""Half side of the square textured ground slab (its top is the plane z = 0)."""
AABB = np.array([[-GROUND_HALF, -GROUND_HALF, -0.05], [GROUND_HALF, GROUND_HALF, 2.7]])
"""The box that holds every surface of the scene, (2, 3): rows min, max."""
ROTOR_AABB = np.array([[-1.0, -0.65, 0.55], [1.0, 0.45, 2.6]])
"""The box that holds every surface the ``rotor`` framing can see (the rotor, the spinner, the
nacelle and the top of the tower; the ground lies outside its cameras' view)."""

TOWER_HEIGHT = 1.62
TOWER_R_BASE = 0.10
TOWER_R_TOP = 0.06
NACELLE_LO = np.array([-0.12, -0.26, 1.55])
NACELLE_HI = np.array([0.12, 0.38, 1.79])
HUB_CENTRE = np.array([0.0, -0.34, 1.67])
"""Centre of the spinner and of the rotor; the blades turn in the plane y = HUB_CENTRE[1]."""
HUB_RADII = np.array([0.10, 0.16, 0.10])
ROTOR_AXIS = np.array([0.0, -1.0, 0.0])
"""Unit rotor axis (pointing from the nacelle towards the rig)."""
ROTOR_E1 = np.array([1.0, 0.0, 0.0])
ROTOR_E2 = np.array([0.0, 0.0, 1.0])
"""In-plane basis of the rotor disc: blade 0 points along ``ROTOR_E2`` (up) at t = 0."""
BLADE_ROOT = 0.06
BLADE_TIP = 0.88
BLADE_HALF_CHORD_ROOT = 0.075
BLADE_HALF_CHORD_TIP = 0.025
BLADE_HALF_THICKNESS = 0.015
HUT_LO = np.array([0.35, 0.10, 0.0])
HUT_HI = np.array([0.65, 0.35, 0.22])
ROCK_CENTRE = np.array([-0.75, -0.45, 0.0])
ROCK_RADII = np.array([0.18, 0.13, 0.11])

EPS_T = 1e-9
"""Smallest ray distance that counts as a hit (a ray does not hit its own origin)."""


def hit_ground(o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[:, 2] / d[:, 2]
    x = o[:, 0] + t * d[:, 0]
    y = o[:, 1] + t * d[:, 1]
    ok = (d[:, 2] < 0) & (o[:, 2] > 0) & (np.abs(x) <= GROUND_HALF) & (np.abs(y) <= GROUND_HALF)
    t = np.where(ok, t, np.inf)
    normal = np.broadcast_to(np.array([0.0, 0.0, 1.0]), o.shape)
    return t, normal


def hit_box(
    o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    d_safe = np.where(np.abs(d) < 1e-15, 1e-15, d)
    inv = 1.0 / d_safe
    t1 = (lo - o) * inv
    t2 = (hi - o) * inv
    t_near = np.minimum(t1, t2)
    t_far = np.maximum(t1, t2)
    axis = np.argmax(t_near, axis=1)
    t_in = np.take_along_axis(t_near, axis[:, None], axis=1)[:, 0]
    t_out = np.min(t_far, axis=1)
    ok = (t_in <= t_out) & (t_in > EPS_T)
    t = np.where(ok, t_in, np.inf)
    normal = np.zeros_like(o)
    rows = np.arange(len(o))
    normal[rows, axis] = -np.sign(d_safe[rows, axis])
    return t, normal


def hit_frustum(
    o: np.ndarray, d: np.ndarray, r_base: float, r_top: float, height: float
) -> tuple[np.ndarray, np.ndarray]:
    """Lateral surface of a vertical cone frustum standing on z = 0 at the origin."""
    a, b = r_base, (r_top - r_base) / height
    ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    r_o = a + b * oz
    qa = dx * dx + dy * dy - b * b * dz * dz
    qb = 2.0 * (ox * dx + oy * dy - r_o * b * dz)
    qc = ox * ox + oy * oy - r_o * r_o
    disc = qb * qb - 4.0 * qa * qc
    t = np.full(len(o), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        sq = np.sqrt(np.maximum(disc, 0.0))
        roots = ((-qb - sq) / (2.0 * qa), (-qb + sq) / (2.0 * qa))
    for root in reversed(roots):  # the nearer root last, so it wins where both are valid
        z = oz + root * dz
        ok = (disc >= 0) & np.isfinite(root) & (root > EPS_T) & (z >= 0.0) & (z <= height)
        t = np.where(ok & (root < t), root, t)
    p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    normal = np.stack([p[:, 0], p[:, 1], -(a + b * p[:, 2]) * b], axis=1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    return t, normal


def hit_ellipsoid(
    o: np.ndarray, d: np.ndarray, centre: np.ndarray, radii: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    os_ = (o - centre) / radii
    ds = d / radii
    qa = np.einsum("ij,ij->i", ds, ds)
    qb = 2.0 * np.einsum("ij,ij->i", os_, ds)
    qc = np.einsum("ij,ij->i", os_, os_) - 1.0
    disc = qb * qb - 4.0 * qa * qc
    root = (-qb - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * qa)
    t = np.where((disc >= 0) & (root > EPS_T), root, np.inf)
    p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    normal = (p - centre) / (radii * radii)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    return t, normal
