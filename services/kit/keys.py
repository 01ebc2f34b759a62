"""Zenoh key expressions of one run (see docs/architecture.md, "Data flow")."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Keys:
    run_id: str

    @property
    def root(self) -> str:
        return f"aoi3d/{self.run_id}"

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
        """Delivered frames of one camera (network → scheduler, trainer)."""
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
    def work(self) -> str:
        """The pool's dispatcher answers queries for work here (reconstruction workers ask)."""
        return f"{self.root}/pool/work"

    def pool_worker(self, worker_id: str) -> str:
        """A reconstruction worker's liveliness token: the pool's membership."""
        return f"{self.root}/pool/worker/{worker_id}"

    @property
    def pool_workers(self) -> str:
        return f"{self.root}/pool/worker/*"
