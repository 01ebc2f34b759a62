"""The tiny scene and field the fast tests share: a 32×24 turbine of 4 training cameras and 30
frames (1 s), and a field small enough to train in milliseconds."""

from __future__ import annotations

from pathlib import Path

from aoi3d.scene import SceneConfig, SceneDataset, generate_dataset

__all__ = ["N_TRAIN", "TINY_FIELD", "tiny_dataset"]

N_TRAIN = 4
TINY_FIELD = {
    "batch_rays": 64, "samples_coarse": 12, "samples_fine": 12, "grid_sizes": [10],
    "upsample_steps": [], "background_size": [4, 8], "occupancy_from_step": 1000,
}


def tiny_dataset(path: Path, n_train: int = N_TRAIN) -> SceneDataset:
    """Generate the tiny scene at ``path``."""
    cfg = SceneConfig(width=32, height=24, fps=30, duration_s=1.0, n_train=n_train,
                      rotor_rpm=60.0, spp=1)
    return generate_dataset(path, cfg)
