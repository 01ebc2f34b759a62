"""The recorder service's FastAPI app: start, stop and watch the run's recording."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Request
from prometheus_client import CollectorRegistry
from pydantic import BaseModel, ConfigDict, Field

from services.kit.app import service_app
from services.kit.bus import Bus
from services.kit.guard import OutsideRoots, confined_path
from services.recorder.core import RecordingStatus
from services.recorder.runtime import RecorderRuntime, RecordingError
from services.recorder.settings import Settings

DESCRIPTION = """
Every run on record: the deliveries (each frame as a Foxglove image with its calibration and
pose), the truth frames, decisions with their AoI vectors, renders, Quality and the ledger's
outcomes of every site, written to an MCAP file with their protobuf schemas (docs/recording.md).
`aoi3d replay` re-runs a recording under any policy.
"""


class StartRecording(BaseModel):
    model_config = ConfigDict(extra="forbid")

    path: str = Field(description="The MCAP file to write (in AOI3D_FILES_ROOTS; replaced if "
                                  "it exists).", examples=["runs/recordings/run.mcap"],
                      min_length=1, max_length=1024)
    max_bytes: int = Field(0, ge=0, description="Size cap of one segment (0: none); the "
                                                "recording goes on in <stem>.part2.mcap …")


class RecordingView(BaseModel):
    recording: bool = Field(description="Whether a recording is open now.")
    path: str | None = Field(description="The latest recording's first file (None: none yet).")
    state: str | None = Field(description="recording, stopped or failed.")
    error: str | None = Field(description="Why it failed (a full disk…), else None.")
    whole: bool | None = Field(None, description="After a failure: whether its last file was "
                                                 "finished whole (summary and index) in the "
                                                 "disk space held for it, or is cut at its "
                                                 "last whole message (`mcap recover`); null "
                                                 "otherwise.")
    segments: list[str] = Field(description="Its files, in order.")
    messages: int = Field(description="Bus messages recorded.")
    mcap_messages: int = Field(description="MCAP messages written (a frame is four).")
    bytes_written: int = Field(description="Bytes written so far.")
    max_bytes: int = Field(description="Its segment cap (0: none).")


def _view(status: RecordingStatus | None) -> RecordingView:
    if status is None:
        return RecordingView(recording=False, path=None, state=None, error=None, segments=[],
                             messages=0, mcap_messages=0, bytes_written=0, max_bytes=0)
    return RecordingView(recording=status.state == "recording", path=status.path,
                         state=status.state, error=status.error, whole=status.whole,
                         segments=list(status.segments), messages=status.messages,
                         mcap_messages=status.mcap_messages,
                         bytes_written=status.bytes_written, max_bytes=status.max_bytes)


def _worker(request: Request) -> RecorderRuntime:
    return request.app.state.worker


WorkerDep = Annotated[RecorderRuntime, Depends(_worker)]
router = APIRouter(tags=["recording"])


@router.get("/recording", summary="The recording in force (or the latest one).")
def get_recording(worker: WorkerDep) -> RecordingView:
    return _view(worker.status())


@router.get("/status", summary="The recorder's status: its recording in force or the latest "
                                "one (as GET /recording), a failure and its error included.")
def get_status(worker: WorkerDep) -> RecordingView:
    return _view(worker.status())


@router.post("/recording/start", summary="Start recording into an MCAP file.",
             responses={409: {"description": "Already recording."},
                        422: {"description": "A path outside AOI3D_FILES_ROOTS."}})
def start_recording(body: StartRecording, worker: WorkerDep, request: Request) -> RecordingView:
    roots = request.app.state.settings.common.files_roots
    try:
        path = confined_path(body.path, roots, "the recording's path")
    except OutsideRoots as err:
        raise HTTPException(422, str(err)) from None
    try:
        status = worker.start_recording(path, max_bytes=body.max_bytes)
    except RecordingError as err:
        raise HTTPException(409, str(err)) from None
    if status.state == "failed":
        raise HTTPException(507, status.error)
    return _view(status)


@router.post("/recording/stop", summary="Finish the recording (summary and footer written).",
             responses={409: {"description": "No recording was started."}})
def stop_recording(worker: WorkerDep) -> RecordingView:
    try:
        return _view(worker.stop_recording())
    except RecordingError as err:
        raise HTTPException(409, str(err)) from None


def run_metadata(settings: Settings) -> dict[str, str]:
    """The ``aoi3d`` metadata of every segment: the run's clock and the settings of the
    processes a replay redoes (read from the same environment, through their settings)."""
    from services.metrics.settings import Settings as MetricsSettings
    from services.recon.settings import Settings as ReconSettings

    common = settings.common
    metrics = MetricsSettings()
    recon = ReconSettings()
    return {
        "run_id": common.run_id, "epoch_s": repr(common.epoch_s),
        "time_scale": repr(common.time_scale), "sites": ",".join(common.sites),
        "cameras": str(common.cameras), "dataset": str(common.dataset),
        "truth_period_ms": repr(metrics.truth_period_ms),
        "reward_psnr": repr(metrics.reward_psnr), "reward_ssim": repr(metrics.reward_ssim),
        "reward_lpips": repr(metrics.reward_lpips),
        "reward_psnr_dynamic": repr(metrics.reward_psnr_dynamic),
        "reward_ssim_dynamic": repr(metrics.reward_ssim_dynamic),
        "lpips": str(metrics.lpips).lower(), "lpips_net": metrics.lpips_net,
        "recon_torch_threads": str(recon.torch_threads), "recon_device": recon.device,
    }


def create_app(settings: Settings | None = None, *, bus: Bus | None = None,
               registry: CollectorRegistry | None = None) -> FastAPI:
    settings = settings or Settings()

    def build(the_bus: Bus, reg: CollectorRegistry) -> RecorderRuntime:
        worker = RecorderRuntime(the_bus, reg, run_id=settings.common.run_id,
                                inbox_size=settings.inbox_size, metadata=run_metadata(settings),
                                chunk_bytes=settings.chunk_bytes,
                                compression=settings.compression)
        if settings.path is not None:  # `aoi3d up --record`: from the start (not confined)
            worker.start_recording(Path(settings.path), max_bytes=settings.max_bytes)
        return worker

    app = service_app(title="aoi3d recorder", description=DESCRIPTION, settings=settings,
                      build_worker=build, bus=bus, registry=registry)
    app.include_router(router)
    return app
