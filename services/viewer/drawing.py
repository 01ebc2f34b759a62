"""What the viewer puts on viser's scene, and the free view a browser's camera asks for.

The scene building of :class:`services.viewer.runtime.ViewerRuntime`, apart from its loops,
locks and bus: the box and the truth camera (drawn once), a frustum per camera in the state
:class:`services.viewer.core.ViewerCore` gives it, the status line, where a browser's camera
starts or is sent back to, and the dispatcher's query for a free view from a browser's camera.
``scene`` and ``client`` are viser's (``ViserServer.scene``, a ``ClientHandle``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from aoi3d.freeview import MAX_VIEW_SIDE, c2w_from_viser
from services.viewer.core import CameraState, ViewerCore, box_segments

__all__ = ["draw_cameras", "draw_static", "look_from_truth", "overview", "status_text",
           "view_params"]


def draw_static(scene: Any, core: ViewerCore) -> None:
    """The scene box and the truth camera (they never change during a run)."""
    box = box_segments(core.aabb)
    scene.add_line_segments("/box", box, (200, 200, 200), thickness=2.0,
                            thickness_units="screen")
    t = core.truth_frustum
    scene.add_camera_frustum("/truth", fov=t.fov, aspect=t.aspect,
                             scale=core.frustum_scale * 1.3, color=(60, 140, 255),
                             wxyz=t.wxyz, position=t.position, thickness=3.0,
                             thickness_units="screen")
    scene.add_label("/truth/label", "truth", position=(0.0, 0.0, 0.0))


def draw_cameras(scene: Any, core: ViewerCore, states: dict[int, CameraState],
                 thumbs: dict[int, np.ndarray | None]) -> None:
    """A frustum per camera (colour: its AoI; thicker and labelled ✓: used by the decision in
    force; image: its latest delivered frame), labelled with its AoI."""
    scale = core.frustum_scale
    for c, st in states.items():
        f = core.frustums[c]
        scene.add_camera_frustum(
            f"/cameras/cam{c}", fov=f.fov, aspect=f.aspect, scale=scale, color=st.colour,
            wxyz=f.wxyz, position=f.position, image=thumbs.get(c),
            thickness=5.0 if st.selected else 2.0, thickness_units="screen")
        aoi = "?" if np.isnan(st.aoi_ms) else f"{st.aoi_ms:.0f} ms"
        scene.add_label(f"/cameras/cam{c}/label",
                        f"{c}{' ✓' if st.selected else ''} {aoi}", position=(0, 0, 0))


def status_text(doc: dict[str, Any], last_view: dict[str, Any]) -> str:
    """The status line (markdown): the decision in force of the site shown (``doc``, its
    ``/scene.json``) and the model behind the last free view shown."""
    d = doc["decision"]
    if d is None:
        text = f"**{doc['site']}**: waiting for the first decision"
    else:
        gamma = "—" if d["gamma_ms"] is None else f"{d['gamma_ms']:.0f} ms"
        text = (f"**{doc['site']}** decision {d['decision_id']} ({d['policy']}, "
                f"Γ {gamma}): {len(d['selected'])} of {len(doc['cameras'])} cameras used")
    if last_view:
        text += (f"  \nview: decision {last_view.get('decision_id')}, step "
                 f"{last_view.get('training_step')}, worker {last_view.get('worker')}")
    return text


def look_from_truth(client: Any, core: ViewerCore) -> None:
    """Put the browser's camera at the truth camera, looking at the box's centre."""
    t = core.truth_frustum
    with client.atomic():
        client.camera.position = t.position
        client.camera.look_at = tuple(core.aabb.mean(axis=0))
        client.camera.up_direction = (0.0, 0.0, 1.0)


def overview(client: Any, core: ViewerCore) -> None:
    """Back from the truth camera and above it, far enough to see every camera."""
    centre = core.aabb.mean(axis=0)
    t = np.asarray(core.truth_frustum.position)
    reach = max(float(np.linalg.norm(np.asarray(f.position) - centre))
                for f in [*core.frustums.values(), core.truth_frustum])
    away = t - centre
    away[2] = 0.0
    away = away / max(float(np.linalg.norm(away)), 1e-9)
    eye = centre + away * 2.0 * reach + np.array([0.0, 0.0, 1.2 * reach])
    with client.atomic():
        client.camera.position = tuple(eye)
        client.camera.look_at = tuple(centre)
        client.camera.up_direction = (0.0, 0.0, 1.0)


def view_params(camera: Any, height: int) -> dict[str, str | int | float] | None:
    """The dispatcher's ``GET /render.png`` query for a free view from the browser's ``camera``,
    ``height`` pixels high (the width follows its aspect); None while its pose is unknown."""
    try:
        c2w = c2w_from_viser(camera.wxyz, camera.position)
        aspect = float(camera.aspect) if camera.aspect and np.isfinite(camera.aspect) else 4 / 3
        fov_deg = float(np.degrees(camera.fov))
    except Exception:  # the client's camera is not known yet
        return None
    w = int(min(MAX_VIEW_SIDE, max(8, round(height * aspect))))
    return {"c2w": ",".join(f"{v:.7g}" for v in c2w.ravel()), "width": w, "height": height,
            "fov": min(179.0, max(1.0, fov_deg))}
