"""``aoi3d export``: the running pipeline's latest reconstruction of a site as a .ply that other
tools open (MeshLab, CloudCompare, Blender, trimesh, Open3D).

It asks the dispatcher's ``GET /sites/<site>/export.ply``; the worker that rendered the site's
latest decision answers from its snapshot of that model. What each format holds and loses:
docs/viewer.md ("Export").
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from aoi3d.sites import DEFAULT_SITE
from aoi3d_cli.common import control_headers, fail, make_console
from services.kit.ports import LOCALHOST, rest_port


def export(
    out: Annotated[Path, typer.Option(help="The .ply file to write.")],
    site: Annotated[str, typer.Option(help="The site whose latest model to export.")]
    = DEFAULT_SITE,
    mesh: Annotated[bool, typer.Option(
        help="A triangle mesh (marching cubes through scikit-image at the opacity --alpha) "
             "instead of a coloured point cloud.")] = False,
    resolution: Annotated[int, typer.Option(
        min=8, max=256, help="Lattice points a side over the scene box where the density is "
                             "sampled.")] = 96,
    alpha: Annotated[float, typer.Option(
        min=0.001, max=0.999,
        help="Opacity a kept point (the mesh's surface) has over one of the renderer's "
             "ray steps.")] = 0.1,
    dispatcher: Annotated[str | None, typer.Option(
        "--dispatcher", "--trainer",
        help="The dispatcher's URL (default: this machine's, moved by --port-offset; "
             "--trainer is its old name, read for one release).")] = None,
    port_offset: Annotated[int, typer.Option(help="As given to `aoi3d up`.")] = 0,
    timeout_s: Annotated[float, typer.Option(min=1, help="How long to wait.")] = 180.0,
) -> None:
    """Write the latest reconstruction of a site as a .ply: a coloured point cloud from the
    field's density and colour (or, with --mesh, a coloured mesh). The pipeline must run
    (`aoi3d up`) and have rendered a decision of the site."""
    import httpx

    base = (dispatcher or f"http://{LOCALHOST}:{rest_port('dispatcher', port_offset)}").rstrip("/")
    url = f"{base}/sites/{site}/export.ply"
    params = {"format": "mesh" if mesh else "points", "resolution": resolution,
              "alpha": alpha}
    try:
        r = httpx.get(url, params=params, headers=control_headers(), timeout=timeout_s)
    except httpx.HTTPError as err:
        fail(f"the dispatcher at {base} did not answer ({type(err).__name__}): is the pipeline "
             f"running (aoi3d up)?")
    if r.status_code != 200:
        try:
            detail = r.json().get("detail", r.text)
        except ValueError:
            detail = r.text
        fail(f"{url}: {r.status_code}: {detail}")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(r.content)
    what = "mesh" if mesh else "point cloud"
    make_console().print(
        f"wrote {out} ({len(r.content) / 1024:.0f} KiB, {what} of site {site}, decision "
        f"{r.headers.get('x-decision-id', '?')}, step {r.headers.get('x-training-step', '?')}, "
        f"worker {r.headers.get('x-worker', '?')})", soft_wrap=True)
