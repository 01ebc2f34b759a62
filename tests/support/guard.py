"""The five service apps on a MemoryBus as the REST guard's tests build them (tests/services/
test_guard.py, tests/services/test_api_fuzz.py)."""

from __future__ import annotations

import time

from fastapi import FastAPI

from aoi3d.clock import SimClock
from aoi3d.scene import SceneDataset
from services.camera.app import create_app as camera_app
from services.camera.settings import Settings as CameraSettings
from services.dispatcher.app import create_app as trainer_app
from services.kit.membus import MemoryBus
from services.kit.settings import CommonSettings
from services.metrics.app import create_app as metrics_app
from services.metrics.settings import Settings as MetricsSettings
from services.network.app import create_app as network_app
from services.network.settings import Settings as NetworkSettings
from services.scheduler.app import create_app as scheduler_app
from services.scheduler.settings import Settings as SchedulerSettings
from tests.support.dispatcher import N_TRAIN, make_settings

HOSTS = ["127.0.0.1", "localhost", "testserver"]


def common(**kw) -> CommonSettings:
    return CommonSettings(run_id="guard", cameras=N_TRAIN, allowed_hosts=HOSTS, **kw)


def build(service: str, ds: SceneDataset, **kw) -> FastAPI:
    bus = MemoryBus()
    if service == "recorder":  # (files_roots: where a fuzzed start may write)
        from services.recorder.app import create_app as recorder_app
        from services.recorder.settings import Settings as RecorderSettings

        return recorder_app(RecorderSettings(common=common(**kw)), bus=bus)
    if service == "ingest":
        from aoi3d.rigfile import rig_from_dict
        from services.ingest.app import create_app as ingest_app
        from services.ingest.settings import Settings as IngestSettings
        from tests.support.ingest import rig_doc

        rig = rig_from_dict(rig_doc())
        return ingest_app(IngestSettings(common=common(epoch_s=time.time() - 60, **kw)),
                          bus=bus, rig=rig, source=MemoryBus())
    if service == "camera":
        return camera_app(CameraSettings(common=common(dataset=ds.root, **kw)), bus=bus,
                          clock=SimClock(time.time(), 1.0), dataset=ds)
    if service == "network":
        return network_app(NetworkSettings(common=common(**kw)), bus=bus)
    if service == "scheduler":
        return scheduler_app(SchedulerSettings(common=common(**kw)), bus=bus)
    if service == "metrics":
        return metrics_app(MetricsSettings(common=common(**kw)), bus=bus)
    settings = make_settings(common=common(time_scale=10.0, epoch_s=time.time(), **kw))
    return trainer_app(settings, bus=bus, dataset=ds)
SERVICES = ["camera", "network", "scheduler", "dispatcher", "metrics"]
FUZZED = [*SERVICES, "recorder", "ingest"]
"""Every service whose REST API the fuzz test drives (the five, and those added with real
cameras and recordings)."""
