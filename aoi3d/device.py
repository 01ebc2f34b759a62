"""The torch device of a component, by name: ``auto``, ``cpu`` or ``cuda``.

One rule for every part that places a model (the trainer's radiance field, the scheduler's
PPO agent): ``auto`` takes CUDA when it is available, else the CPU; ``cuda`` where CUDA is
not available is an error that says so; any other name is an error listing the accepted ones.
:func:`check_device` validates the name alone (no torch import), for settings that are only
resolved once a model needs them.
"""

from __future__ import annotations

__all__ = ["DEVICES", "check_device", "resolve_device"]

DEVICES = ("auto", "cpu", "cuda")
"""The accepted device names."""


def check_device(name: str) -> str:
    """``name`` if it is one of :data:`DEVICES`, else ``ValueError`` listing them."""
    if name not in DEVICES:
        raise ValueError(f"unknown device {name!r}; accepted: {', '.join(DEVICES)}")
    return name


def resolve_device(name: str) -> str:
    """The torch device ``name`` stands for here: ``auto`` → ``cuda`` when available, else
    ``cpu``; ``cpu`` as it is; ``cuda`` only where CUDA is available (else ``ValueError``)."""
    check_device(name)
    if name == "cpu":
        return name
    import torch  # only where a model is placed: importing this module stays torch-free

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if not torch.cuda.is_available():
        raise ValueError("device 'cuda' was requested but CUDA is not available here; "
                         "use 'auto' or 'cpu'")
    return name
