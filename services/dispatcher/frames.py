"""The delivered frames the dispatcher holds, per camera and still encoded, to resolve the
FrameRefs of a decision (a selection names a camera's frame by its generation time)."""

from __future__ import annotations

from collections import deque
from typing import Generic, Protocol, TypeVar


class FrameData(Protocol):
    """What the buffer needs of a frame: its camera and generation time (read only)."""

    @property
    def camera_id(self) -> int: ...
    @property
    def generation_ms(self) -> float: ...


F = TypeVar("F", bound=FrameData)


class FrameBuffer(Generic[F]):
    """The newest ``per_camera`` delivered frames of each camera (older ones fall out)."""

    def __init__(self, per_camera: int) -> None:
        if per_camera < 1:
            raise ValueError(f"per_camera must be >= 1, got {per_camera}")
        self._per_camera = per_camera
        self._frames: dict[int, deque[F]] = {}

    def add(self, frame: F) -> None:
        buf = self._frames.get(frame.camera_id)
        if buf is None:
            buf = self._frames[frame.camera_id] = deque(maxlen=self._per_camera)
        buf.append(frame)

    def find(self, camera_id: int, generation_ms: float) -> F | None:
        """Camera ``camera_id``'s frame generated at ``generation_ms``, if still held."""
        for frame in reversed(self._frames.get(camera_id, ())):
            if frame.generation_ms == generation_ms:
                return frame
        return None

    def __len__(self) -> int:
        return sum(len(b) for b in self._frames.values())
