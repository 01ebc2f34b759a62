"""The agent's checkpoint file, read and written here only (imports torch).

A checkpoint is one ``torch.save`` document (format ``aoi3d-ppo``, version 1): the learner's
:class:`~aoi3d.policy.ppo.config.PPOConfig` as a flat dict, the counts of episodes and
updates learned, the network's weights, the optimizer's state, the state of the generator
everything random is drawn from, and ``extra`` — plain data a caller keeps alongside (a
training loop's position, the episode config). :class:`Checkpoint` is that document;
:meth:`Checkpoint.read` checks the format and version, :meth:`Checkpoint.write` writes
atomically (:func:`aoi3d.atomic.atomic_path`). The acting side takes the config and the
weights of it, the learner everything.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from aoi3d.atomic import atomic_path

__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "Checkpoint"]

CHECKPOINT_FORMAT = "aoi3d-ppo"
CHECKPOINT_VERSION = 1


@dataclass
class Checkpoint:
    """One checkpoint document (tensors on the CPU)."""

    config: dict[str, Any]
    episodes: int
    updates: int
    model: dict[str, torch.Tensor]
    optimizer: dict[str, Any]
    generator: torch.Tensor
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def read(cls, path: str | Path) -> Checkpoint:
        """The checkpoint at ``path``, its format and version checked. A missing file raises
        ``FileNotFoundError``; anything that is not a readable checkpoint of this format and
        version (or lacks one of its parts) raises ``ValueError`` saying why."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no PPO checkpoint at {path}")
        try:
            doc = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as err:  # torch raises many kinds for a file that is not its own
            raise ValueError(f"{path} is not a readable PPO checkpoint: "
                             f"{type(err).__name__}: {str(err).splitlines()[0][:200]}") from None
        if not isinstance(doc, dict) or doc.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(f"{path} is not an aoi3d PPO checkpoint (format "
                             f"{doc.get('format') if isinstance(doc, dict) else None!r})")
        if doc.get("version") != CHECKPOINT_VERSION:
            raise ValueError(f"{path}: checkpoint version {doc.get('version')!r}, this code "
                             f"reads version {CHECKPOINT_VERSION}")
        try:
            return cls(config=dict(doc["config"]), episodes=int(doc["episodes"]),
                       updates=int(doc["updates"]), model=doc["model"],
                       optimizer=doc["optimizer"], generator=doc["generator"],
                       extra=dict(doc.get("extra") or {}))
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"{path}: damaged PPO checkpoint: {type(err).__name__}: "
                             f"{str(err).splitlines()[0][:200]}") from None

    def write(self, path: str | Path) -> None:
        """Write this checkpoint to ``path`` atomically (its folder created if missing)."""
        doc = {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "config": self.config,
            "episodes": self.episodes,
            "updates": self.updates,
            "model": {k: v.detach().cpu() for k, v in self.model.items()},
            "optimizer": _to_cpu(self.optimizer),
            "generator": self.generator,
            "extra": dict(self.extra),
        }
        with atomic_path(path) as tmp:
            torch.save(doc, tmp)


def _to_cpu(obj: Any) -> Any:
    """A copy of a (nested) optimizer state with every tensor on the CPU."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(_to_cpu(v) for v in obj)
    return obj
