"""Settings of the metrics service (environment prefix ``AOI3D_METRICS_``)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from aoi3d.quality import RewardWeights
from services.kit.ports import SERVICE_PORTS
from services.kit.settings import ServiceSettings

_DEFAULT_WEIGHTS = RewardWeights()


class Settings(ServiceSettings):
    """The metrics service: scores each render of the novel view against its ground truth."""

    model_config = SettingsConfigDict(env_prefix="AOI3D_METRICS_", extra="ignore")

    port: int = Field(SERVICE_PORTS["metrics"], ge=0, le=65535, description="REST API port.")
    truth_period_ms: float = Field(
        30.0, gt=0, le=60_000,
        description="Generation period C of the ground-truth frames in sim ms. A render at t "
                    "without a truth frame generated exactly at t is paired with the newest "
                    "truth frame generated in [t - C, t].")
    truth_frames: int = Field(
        512, ge=1, le=100_000,
        description="Ground-truth frames kept (still encoded), newest first out last.")
    history: int = Field(
        1000, ge=1, le=1_000_000, description="Quality results kept for GET /quality.")
    inbox_size: int = Field(
        256, ge=1, le=100_000,
        description="Messages queued between the bus and the scoring thread (oldest dropped).")
    reward_psnr: float = Field(
        _DEFAULT_WEIGHTS.psnr, allow_inf_nan=False,
        description="Reward weight of the PSNR term (per dB).")
    reward_ssim: float = Field(
        _DEFAULT_WEIGHTS.ssim, allow_inf_nan=False, description="Reward weight of the SSIM term.")
    reward_lpips: float = Field(
        _DEFAULT_WEIGHTS.lpips, allow_inf_nan=False,
        description="Reward weight of the LPIPS term (negative: lower LPIPS is better); "
                    "unused while LPIPS is unavailable.")
    reward_psnr_dynamic: float = Field(
        _DEFAULT_WEIGHTS.psnr_dynamic, allow_inf_nan=False,
        description="Reward weight of the dynamic region's PSNR (per dB; 0: the paper's "
                    "reward). The dynamic reward weighs what moves: PSNR 0, SSIM 0, "
                    "PSNR_DYNAMIC 0.02, SSIM_DYNAMIC 0.5, LPIPS -1.")
    reward_ssim_dynamic: float = Field(
        _DEFAULT_WEIGHTS.ssim_dynamic, allow_inf_nan=False,
        description="Reward weight of the dynamic region's SSIM (0: the paper's reward).")
    lpips: bool = Field(
        True, description="Compute LPIPS when its weights are cached (`python -m aoi3d.lpips "
                          "fetch`, run by `make install`); without them, or when false, LPIPS is "
                          "null and the reward uses PSNR and SSIM only.")
    lpips_per_s: float = Field(
        4.0, ge=0, le=10_000, allow_inf_nan=False,
        description="LPIPS on this many renders a wall second on average, bursts of one "
                    "second's worth let through (0: on every "
                    "render). LPIPS is most of the scoring's CPU; at time scale 1 the pool "
                    "renders 9-16 a second on 2 cores, and scoring them all took a quarter of a "
                    "core from the reconstruction. The renders left out are scored with PSNR "
                    "and SSIM alone and marked lpips_skipped (no reward: it needs LPIPS). Set 0 "
                    "for online PPO (learn=true) to be rewarded for every render.")
    lpips_net: Literal["alex", "vgg"] = Field(
        "alex", description="LPIPS backbone: alex (the paper's) or vgg (VGG16).")
    truth_wait_s: float = Field(
        5.0, ge=0, le=60,
        description="Wall seconds a render whose time is past every truth frame received is "
                    "held for its truth frame (still on its way when the camera lags) before "
                    "it is rejected as no_truth; 0 rejects it at once.")
    ledger_open_s: float = Field(
        150.0, gt=0, le=86_400,
        description="Wall seconds a decision may stay open in the decision ledger (no render, "
                    "no outcome) before it is counted lost (expired). Above the dispatcher's "
                    "job_timeout_s, so a job the pool still waits for is not counted twice.")
    state_dir: Path | None = Field(
        None, description="Folder where the decision ledger is saved (ledger-<run>-<site>.json, "
                          "at most once a second and on stop) and restored from on start, so "
                          "its totals survive a restart; unset: kept in memory only. `aoi3d "
                          "up` sets it to the run's log folder.")
    torch_threads: int = Field(
        1, ge=0, le=256,
        description="Torch CPU threads of this process (LPIPS); 0 keeps torch's default. One "
                    "thread keeps LPIPS at ~4 ms a pair without competing with the dispatcher.")

    def reward_weights(self) -> RewardWeights:
        """The reward weights as the domain's :class:`RewardWeights`."""
        return RewardWeights(psnr=self.reward_psnr, ssim=self.reward_ssim,
                             lpips=self.reward_lpips, psnr_dynamic=self.reward_psnr_dynamic,
                             ssim_dynamic=self.reward_ssim_dynamic)
