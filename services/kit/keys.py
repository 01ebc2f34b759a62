"""Zenoh key expressions of one run (see docs/architecture.md, "Data flow").

A run holds one or more *sites* (a turbine each: its own cameras, channel, policy and
quality); every key of a site lives under ``aoi3d/<run>/<site>/``. The pool of
reconstruction workers is the run's, shared by its sites: ``aoi3d/<run>/pool/``.
``Keys(run, "*")`` gives the expressions that match every site (a subscriber of all sites).
"""

from __future__ import annotations

from dataclasses import dataclass

from aoi3d.sites import DEFAULT_SITE, SITE_PATTERN, check_site  # the sites' names: one home
from aoi3d.sites import RESERVED_SITES as RESERVED

__all__ = ["DEFAULT_SITE", "RESERVED", "SITE_PATTERN", "Keys", "check_site"]


@dataclass(frozen=True)
class Keys:
    run_id: str
    site: str = DEFAULT_SITE

    @property
    def root(self) -> str:
        """The site's keys live under here."""
        return f"aoi3d/{self.run_id}/{self.site}"

    @property
    def run_root(self) -> str:
        return f"aoi3d/{self.run_id}"

    @staticmethod
    def site_of(key: str) -> str:
        """The site chunk of a site's key (``aoi3d/<run>/<site>/…``)."""
        return key.split("/", 3)[2]

    def cam_frame(self, camera_id: int) -> str:
        """Offered frames of one camera (camera → network)."""
        return f"{self.root}/cam/{camera_id}/frame"

    @property
    def cam_frames(self) -> str:
        return f"{self.root}/cam/*/frame"

    @property
    def truth(self) -> str:
        """Held-out camera frames, the ground truth (camera → metrics)."""
        return f"{self.root}/truth/frame"

    def edge_frame(self, camera_id: int) -> str:
        """Delivered frames of one camera (network → scheduler, dispatcher)."""
        return f"{self.root}/edge/{camera_id}/frame"

    @property
    def edge_frames(self) -> str:
        return f"{self.root}/edge/*/frame"

    @property
    def decision(self) -> str:
        return f"{self.root}/decision"

    @property
    def render(self) -> str:
        return f"{self.root}/render"

    @property
    def quality(self) -> str:
        return f"{self.root}/quality"

    @property
    def outcome(self) -> str:
        """How a decision ended without a render (dispatcher → the ledger in metrics)."""
        return f"{self.root}/outcome"

    @property
    def work(self) -> str:
        """The pool's dispatcher answers queries for work here (reconstruction workers ask)."""
        return f"{self.run_root}/pool/work"

    def pool_worker(self, worker_id: str) -> str:
        """A reconstruction worker's liveliness token: the pool's membership."""
        return f"{self.run_root}/pool/worker/{worker_id}"

    def pool_view(self, worker_id: str) -> str:
        """A reconstruction worker answers free-view and export queries here (the dispatcher
        asks the worker that rendered a site's latest decision)."""
        return f"{self.run_root}/pool/view/{worker_id}"

    @property
    def pool_workers(self) -> str:
        return f"{self.run_root}/pool/worker/*"
