"""The live sweep's domain: what ``aoi3d live sweep`` measured on a running pipeline,
summarised, judged and set beside the virtual clock.

Pure: no HTTP, no bus, no processes — the command (:mod:`aoi3d_cli.live`) talks to the
pipeline and hands the windows it measured here. :mod:`~aoi3d.live.summary` holds the windows
and their statistics, :mod:`~aoi3d.live.sim` the virtual-clock re-run of the same scene,
channel, carry and budget (the experiment engine), :mod:`~aoi3d.live.report` the typed result
and its files, :mod:`~aoi3d.live.figures` the figures (matplotlib). Only the summary is
imported here; the others load the engine or matplotlib.
"""

from aoi3d.live.summary import (
    DISPLAY_METRICS,
    METRICS,
    Measurement,
    measurement_doc,
    points_rows,
    render_latency_s,
    render_rows,
    steps_per_decision,
    summarise,
    with_sim,
)

__all__ = [
    "DISPLAY_METRICS",
    "METRICS",
    "Measurement",
    "measurement_doc",
    "points_rows",
    "render_latency_s",
    "render_rows",
    "steps_per_decision",
    "summarise",
    "with_sim",
]
