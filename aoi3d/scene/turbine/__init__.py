"""The synthetic dynamic scene: a wind turbine on a textured field under a sky.

World is z-up, metres-ish, the turbine stands at the origin and its rotor faces −y (where the
camera rig stands). Everything that can be hit lies inside :attr:`TurbineScene.aabb`:

- a square slab of textured ground (top at z = 0, ``|x|, |y| ≤ GROUND_HALF``),
- a tapered tower (cone frustum), a nacelle (box), a spinner (ellipsoid), a brick hut (box)
  and a rock (ellipsoid) — all static,
- three identical tapered blades (thin trapezoidal prisms) turning at ``rotor_rpm`` about the
  horizontal rotor axis — the only moving part.

A ray that leaves the box without a hit gets :meth:`TurbineScene.background` of its direction
alone: a sky gradient with a sun glow above the horizon, hazy distant fields below it.

Rendering is exact analytic ray casting with ``spp × spp`` stratified samples per pixel (sample
centres of a regular sub-grid, no randomness), averaged in sRGB. Because only the blades move,
the static layer of a camera (colour and depth of every sample) is cast once and cached; a
frame then intersects only the sample rays that can reach the rotor disc with the blades and
keeps whichever hit is nearer (z-compositing). The result equals a full re-render.

Textures are procedural (checkers, stripes, bricks, value noise); the value-noise lattices come
from ``np.random.default_rng(cfg.seed)`` — no global RNG is touched.

The package's modules, each importing only those above it:

- :mod:`~aoi3d.scene.turbine.geometry` — the solids' dimensions and the ray–primitive
  intersections;
- :mod:`~aoi3d.scene.turbine.config` — :class:`SceneConfig`, :data:`SCENE_VERSION`,
  :func:`to_uint8`;
- :mod:`~aoi3d.scene.turbine.appearance` — light, sky, shading and the procedural textures;
- :mod:`~aoi3d.scene.turbine.scene` — :class:`TurbineScene`, the renderer (static layer cache,
  blade compositing).
"""

from aoi3d.scene.turbine.config import FRAMINGS, SCENE_VERSION, SceneConfig, to_uint8
from aoi3d.scene.turbine.geometry import (
    AABB,
    BLADE_HALF_CHORD_ROOT,
    BLADE_HALF_CHORD_TIP,
    BLADE_HALF_THICKNESS,
    BLADE_ROOT,
    BLADE_TIP,
    BLADES,
    GROUND_HALF,
    HUB_CENTRE,
    HUB_RADII,
    HUT_HI,
    HUT_LO,
    NACELLE_HI,
    NACELLE_LO,
    ROCK_CENTRE,
    ROCK_RADII,
    ROTOR_AABB,
    ROTOR_AXIS,
    ROTOR_E1,
    ROTOR_E2,
    TOWER_HEIGHT,
    TOWER_R_BASE,
    TOWER_R_TOP,
)
from aoi3d.scene.turbine.scene import TurbineScene

# The dimensions of the solids stay importable from here, as from the one-file module (the rig
# reads HUB_CENTRE, the tests BLADE_TIP and NACELLE_HI).
__all__ = [
    "AABB",
    "BLADES",
    "BLADE_HALF_CHORD_ROOT",
    "BLADE_HALF_CHORD_TIP",
    "BLADE_HALF_THICKNESS",
    "BLADE_ROOT",
    "BLADE_TIP",
    "FRAMINGS",
    "GROUND_HALF",
    "HUB_CENTRE",
    "HUB_RADII",
    "HUT_HI",
    "HUT_LO",
    "NACELLE_HI",
    "NACELLE_LO",
    "ROCK_CENTRE",
    "ROCK_RADII",
    "ROTOR_AABB",
    "ROTOR_AXIS",
    "ROTOR_E1",
    "ROTOR_E2",
    "SCENE_VERSION",
    "TOWER_HEIGHT",
    "TOWER_R_BASE",
    "TOWER_R_TOP",
    "SceneConfig",
    "TurbineScene",
    "to_uint8",
]
