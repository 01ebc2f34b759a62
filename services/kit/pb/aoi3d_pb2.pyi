from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class ImageEncoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    IMAGE_ENCODING_UNSPECIFIED: _ClassVar[ImageEncoding]
    IMAGE_ENCODING_PNG: _ClassVar[ImageEncoding]
    IMAGE_ENCODING_RAW_RGB8: _ClassVar[ImageEncoding]

class EndReason(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    END_REASON_UNSPECIFIED: _ClassVar[EndReason]
    END_REASON_SUPERSEDED: _ClassVar[EndReason]
    END_REASON_WORKER_DIED: _ClassVar[EndReason]
    END_REASON_TIMEOUT: _ClassVar[EndReason]
    END_REASON_NOT_DELIVERED: _ClassVar[EndReason]
    END_REASON_RENDER_FAILED: _ClassVar[EndReason]
    END_REASON_REFUSED: _ClassVar[EndReason]
    END_REASON_NOT_RECEIVED: _ClassVar[EndReason]
    END_REASON_TRUTH_MISSING: _ClassVar[EndReason]
    END_REASON_RENDER_REJECTED: _ClassVar[EndReason]
    END_REASON_UNSEEN: _ClassVar[EndReason]
    END_REASON_EXPIRED: _ClassVar[EndReason]
IMAGE_ENCODING_UNSPECIFIED: ImageEncoding
IMAGE_ENCODING_PNG: ImageEncoding
IMAGE_ENCODING_RAW_RGB8: ImageEncoding
END_REASON_UNSPECIFIED: EndReason
END_REASON_SUPERSEDED: EndReason
END_REASON_WORKER_DIED: EndReason
END_REASON_TIMEOUT: EndReason
END_REASON_NOT_DELIVERED: EndReason
END_REASON_RENDER_FAILED: EndReason
END_REASON_REFUSED: EndReason
END_REASON_NOT_RECEIVED: EndReason
END_REASON_TRUTH_MISSING: EndReason
END_REASON_RENDER_REJECTED: EndReason
END_REASON_UNSEEN: EndReason
END_REASON_EXPIRED: EndReason

class Intrinsics(_message.Message):
    __slots__ = ("fx", "fy", "cx", "cy", "width", "height")
    FX_FIELD_NUMBER: _ClassVar[int]
    FY_FIELD_NUMBER: _ClassVar[int]
    CX_FIELD_NUMBER: _ClassVar[int]
    CY_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    def __init__(self, fx: _Optional[float] = ..., fy: _Optional[float] = ..., cx: _Optional[float] = ..., cy: _Optional[float] = ..., width: _Optional[int] = ..., height: _Optional[int] = ...) -> None: ...

class Pose(_message.Message):
    __slots__ = ("c2w",)
    C2W_FIELD_NUMBER: _ClassVar[int]
    c2w: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, c2w: _Optional[_Iterable[float]] = ...) -> None: ...

class Image(_message.Message):
    __slots__ = ("encoding", "width", "height", "data")
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    encoding: ImageEncoding
    width: int
    height: int
    data: bytes
    def __init__(self, encoding: _Optional[_Union[ImageEncoding, str]] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., data: _Optional[bytes] = ...) -> None: ...

class Frame(_message.Message):
    __slots__ = ("camera_id", "sequence", "generation_ms", "scene_time_ms", "send_ms", "delivery_ms", "pose", "intrinsics", "image")
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    GENERATION_MS_FIELD_NUMBER: _ClassVar[int]
    SCENE_TIME_MS_FIELD_NUMBER: _ClassVar[int]
    SEND_MS_FIELD_NUMBER: _ClassVar[int]
    DELIVERY_MS_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    IMAGE_FIELD_NUMBER: _ClassVar[int]
    camera_id: int
    sequence: int
    generation_ms: float
    scene_time_ms: float
    send_ms: float
    delivery_ms: float
    pose: Pose
    intrinsics: Intrinsics
    image: Image
    def __init__(self, camera_id: _Optional[int] = ..., sequence: _Optional[int] = ..., generation_ms: _Optional[float] = ..., scene_time_ms: _Optional[float] = ..., send_ms: _Optional[float] = ..., delivery_ms: _Optional[float] = ..., pose: _Optional[_Union[Pose, _Mapping]] = ..., intrinsics: _Optional[_Union[Intrinsics, _Mapping]] = ..., image: _Optional[_Union[Image, _Mapping]] = ...) -> None: ...

class FrameRef(_message.Message):
    __slots__ = ("camera_id", "sequence", "generation_ms", "aoi_ms")
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    GENERATION_MS_FIELD_NUMBER: _ClassVar[int]
    AOI_MS_FIELD_NUMBER: _ClassVar[int]
    camera_id: int
    sequence: int
    generation_ms: float
    aoi_ms: float
    def __init__(self, camera_id: _Optional[int] = ..., sequence: _Optional[int] = ..., generation_ms: _Optional[float] = ..., aoi_ms: _Optional[float] = ...) -> None: ...

class Decision(_message.Message):
    __slots__ = ("decision_id", "time_ms", "camera_ids", "aoi_ms", "selected", "policy", "incarnation", "gamma_ms", "budget_steps", "expected_lag_ms")
    DECISION_ID_FIELD_NUMBER: _ClassVar[int]
    TIME_MS_FIELD_NUMBER: _ClassVar[int]
    CAMERA_IDS_FIELD_NUMBER: _ClassVar[int]
    AOI_MS_FIELD_NUMBER: _ClassVar[int]
    SELECTED_FIELD_NUMBER: _ClassVar[int]
    POLICY_FIELD_NUMBER: _ClassVar[int]
    INCARNATION_FIELD_NUMBER: _ClassVar[int]
    GAMMA_MS_FIELD_NUMBER: _ClassVar[int]
    BUDGET_STEPS_FIELD_NUMBER: _ClassVar[int]
    EXPECTED_LAG_MS_FIELD_NUMBER: _ClassVar[int]
    decision_id: int
    time_ms: float
    camera_ids: _containers.RepeatedScalarFieldContainer[int]
    aoi_ms: _containers.RepeatedScalarFieldContainer[float]
    selected: _containers.RepeatedCompositeFieldContainer[FrameRef]
    policy: str
    incarnation: int
    gamma_ms: float
    budget_steps: int
    expected_lag_ms: float
    def __init__(self, decision_id: _Optional[int] = ..., time_ms: _Optional[float] = ..., camera_ids: _Optional[_Iterable[int]] = ..., aoi_ms: _Optional[_Iterable[float]] = ..., selected: _Optional[_Iterable[_Union[FrameRef, _Mapping]]] = ..., policy: _Optional[str] = ..., incarnation: _Optional[int] = ..., gamma_ms: _Optional[float] = ..., budget_steps: _Optional[int] = ..., expected_lag_ms: _Optional[float] = ...) -> None: ...

class Render(_message.Message):
    __slots__ = ("decision_id", "time_ms", "pose", "intrinsics", "image", "training_step", "n_views", "backend", "frame_generation_ms", "carry", "render_steps", "decision_incarnation", "worker_id", "loss", "site", "seed", "aabb", "ready_ms", "warm_start", "compute_s", "frame_camera_ids", "job_index", "model_epoch", "job_steps", "cold_steps", "warm_max_gap_ms")
    DECISION_ID_FIELD_NUMBER: _ClassVar[int]
    TIME_MS_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    IMAGE_FIELD_NUMBER: _ClassVar[int]
    TRAINING_STEP_FIELD_NUMBER: _ClassVar[int]
    N_VIEWS_FIELD_NUMBER: _ClassVar[int]
    BACKEND_FIELD_NUMBER: _ClassVar[int]
    FRAME_GENERATION_MS_FIELD_NUMBER: _ClassVar[int]
    CARRY_FIELD_NUMBER: _ClassVar[int]
    RENDER_STEPS_FIELD_NUMBER: _ClassVar[int]
    DECISION_INCARNATION_FIELD_NUMBER: _ClassVar[int]
    WORKER_ID_FIELD_NUMBER: _ClassVar[int]
    LOSS_FIELD_NUMBER: _ClassVar[int]
    SITE_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    AABB_FIELD_NUMBER: _ClassVar[int]
    READY_MS_FIELD_NUMBER: _ClassVar[int]
    WARM_START_FIELD_NUMBER: _ClassVar[int]
    COMPUTE_S_FIELD_NUMBER: _ClassVar[int]
    FRAME_CAMERA_IDS_FIELD_NUMBER: _ClassVar[int]
    JOB_INDEX_FIELD_NUMBER: _ClassVar[int]
    MODEL_EPOCH_FIELD_NUMBER: _ClassVar[int]
    JOB_STEPS_FIELD_NUMBER: _ClassVar[int]
    COLD_STEPS_FIELD_NUMBER: _ClassVar[int]
    WARM_MAX_GAP_MS_FIELD_NUMBER: _ClassVar[int]
    decision_id: int
    time_ms: float
    pose: Pose
    intrinsics: Intrinsics
    image: Image
    training_step: int
    n_views: int
    backend: str
    frame_generation_ms: _containers.RepeatedScalarFieldContainer[float]
    carry: str
    render_steps: int
    decision_incarnation: int
    worker_id: str
    loss: float
    site: str
    seed: int
    aabb: _containers.RepeatedScalarFieldContainer[float]
    ready_ms: float
    warm_start: bool
    compute_s: float
    frame_camera_ids: _containers.RepeatedScalarFieldContainer[int]
    job_index: int
    model_epoch: int
    job_steps: int
    cold_steps: int
    warm_max_gap_ms: float
    def __init__(self, decision_id: _Optional[int] = ..., time_ms: _Optional[float] = ..., pose: _Optional[_Union[Pose, _Mapping]] = ..., intrinsics: _Optional[_Union[Intrinsics, _Mapping]] = ..., image: _Optional[_Union[Image, _Mapping]] = ..., training_step: _Optional[int] = ..., n_views: _Optional[int] = ..., backend: _Optional[str] = ..., frame_generation_ms: _Optional[_Iterable[float]] = ..., carry: _Optional[str] = ..., render_steps: _Optional[int] = ..., decision_incarnation: _Optional[int] = ..., worker_id: _Optional[str] = ..., loss: _Optional[float] = ..., site: _Optional[str] = ..., seed: _Optional[int] = ..., aabb: _Optional[_Iterable[float]] = ..., ready_ms: _Optional[float] = ..., warm_start: _Optional[bool] = ..., compute_s: _Optional[float] = ..., frame_camera_ids: _Optional[_Iterable[int]] = ..., job_index: _Optional[int] = ..., model_epoch: _Optional[int] = ..., job_steps: _Optional[int] = ..., cold_steps: _Optional[int] = ..., warm_max_gap_ms: _Optional[float] = ...) -> None: ...

class Job(_message.Message):
    __slots__ = ("decision", "frames", "n_missing", "backend", "carry", "render_steps", "seed", "model_epoch", "pose", "intrinsics", "aabb", "assigned_unix_s", "site", "cold_steps", "warm_max_gap_ms")
    DECISION_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    N_MISSING_FIELD_NUMBER: _ClassVar[int]
    BACKEND_FIELD_NUMBER: _ClassVar[int]
    CARRY_FIELD_NUMBER: _ClassVar[int]
    RENDER_STEPS_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    MODEL_EPOCH_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    AABB_FIELD_NUMBER: _ClassVar[int]
    ASSIGNED_UNIX_S_FIELD_NUMBER: _ClassVar[int]
    SITE_FIELD_NUMBER: _ClassVar[int]
    COLD_STEPS_FIELD_NUMBER: _ClassVar[int]
    WARM_MAX_GAP_MS_FIELD_NUMBER: _ClassVar[int]
    decision: Decision
    frames: _containers.RepeatedCompositeFieldContainer[Frame]
    n_missing: int
    backend: str
    carry: str
    render_steps: int
    seed: int
    model_epoch: int
    pose: Pose
    intrinsics: Intrinsics
    aabb: _containers.RepeatedScalarFieldContainer[float]
    assigned_unix_s: float
    site: str
    cold_steps: int
    warm_max_gap_ms: float
    def __init__(self, decision: _Optional[_Union[Decision, _Mapping]] = ..., frames: _Optional[_Iterable[_Union[Frame, _Mapping]]] = ..., n_missing: _Optional[int] = ..., backend: _Optional[str] = ..., carry: _Optional[str] = ..., render_steps: _Optional[int] = ..., seed: _Optional[int] = ..., model_epoch: _Optional[int] = ..., pose: _Optional[_Union[Pose, _Mapping]] = ..., intrinsics: _Optional[_Union[Intrinsics, _Mapping]] = ..., aabb: _Optional[_Iterable[float]] = ..., assigned_unix_s: _Optional[float] = ..., site: _Optional[str] = ..., cold_steps: _Optional[int] = ..., warm_max_gap_ms: _Optional[float] = ...) -> None: ...

class WorkRequest(_message.Message):
    __slots__ = ("worker_id", "done_decision_id", "done_incarnation", "done_rendered", "done_reason", "busy_s", "jobs", "max_wait_s", "device", "pid", "host", "done_site")
    WORKER_ID_FIELD_NUMBER: _ClassVar[int]
    DONE_DECISION_ID_FIELD_NUMBER: _ClassVar[int]
    DONE_INCARNATION_FIELD_NUMBER: _ClassVar[int]
    DONE_RENDERED_FIELD_NUMBER: _ClassVar[int]
    DONE_REASON_FIELD_NUMBER: _ClassVar[int]
    BUSY_S_FIELD_NUMBER: _ClassVar[int]
    JOBS_FIELD_NUMBER: _ClassVar[int]
    MAX_WAIT_S_FIELD_NUMBER: _ClassVar[int]
    DEVICE_FIELD_NUMBER: _ClassVar[int]
    PID_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    DONE_SITE_FIELD_NUMBER: _ClassVar[int]
    worker_id: str
    done_decision_id: int
    done_incarnation: int
    done_rendered: bool
    done_reason: str
    busy_s: float
    jobs: int
    max_wait_s: float
    device: str
    pid: int
    host: str
    done_site: str
    def __init__(self, worker_id: _Optional[str] = ..., done_decision_id: _Optional[int] = ..., done_incarnation: _Optional[int] = ..., done_rendered: _Optional[bool] = ..., done_reason: _Optional[str] = ..., busy_s: _Optional[float] = ..., jobs: _Optional[int] = ..., max_wait_s: _Optional[float] = ..., device: _Optional[str] = ..., pid: _Optional[int] = ..., host: _Optional[str] = ..., done_site: _Optional[str] = ...) -> None: ...

class WorkReply(_message.Message):
    __slots__ = ("job", "reason")
    JOB_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    job: Job
    reason: str
    def __init__(self, job: _Optional[_Union[Job, _Mapping]] = ..., reason: _Optional[str] = ...) -> None: ...

class Outcome(_message.Message):
    __slots__ = ("decision_id", "incarnation", "site", "state", "reason", "detail")
    DECISION_ID_FIELD_NUMBER: _ClassVar[int]
    INCARNATION_FIELD_NUMBER: _ClassVar[int]
    SITE_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    DETAIL_FIELD_NUMBER: _ClassVar[int]
    decision_id: int
    incarnation: int
    site: str
    state: str
    reason: EndReason
    detail: str
    def __init__(self, decision_id: _Optional[int] = ..., incarnation: _Optional[int] = ..., site: _Optional[str] = ..., state: _Optional[str] = ..., reason: _Optional[_Union[EndReason, str]] = ..., detail: _Optional[str] = ...) -> None: ...

class Quality(_message.Message):
    __slots__ = ("decision_id", "time_ms", "scene_time_ms", "psnr_db", "ssim", "lpips", "reward", "reward_terms", "training_step", "truth_time_ms", "psnr_dynamic_db", "ssim_dynamic", "dynamic_fraction", "decision_incarnation", "site", "display_time_ms", "psnr_display_db", "ssim_display", "lpips_display", "reward_display", "psnr_dynamic_display_db", "display_truth_time_ms", "render_steps", "ready_ms", "lpips_skipped")
    DECISION_ID_FIELD_NUMBER: _ClassVar[int]
    TIME_MS_FIELD_NUMBER: _ClassVar[int]
    SCENE_TIME_MS_FIELD_NUMBER: _ClassVar[int]
    PSNR_DB_FIELD_NUMBER: _ClassVar[int]
    SSIM_FIELD_NUMBER: _ClassVar[int]
    LPIPS_FIELD_NUMBER: _ClassVar[int]
    REWARD_FIELD_NUMBER: _ClassVar[int]
    REWARD_TERMS_FIELD_NUMBER: _ClassVar[int]
    TRAINING_STEP_FIELD_NUMBER: _ClassVar[int]
    TRUTH_TIME_MS_FIELD_NUMBER: _ClassVar[int]
    PSNR_DYNAMIC_DB_FIELD_NUMBER: _ClassVar[int]
    SSIM_DYNAMIC_FIELD_NUMBER: _ClassVar[int]
    DYNAMIC_FRACTION_FIELD_NUMBER: _ClassVar[int]
    DECISION_INCARNATION_FIELD_NUMBER: _ClassVar[int]
    SITE_FIELD_NUMBER: _ClassVar[int]
    DISPLAY_TIME_MS_FIELD_NUMBER: _ClassVar[int]
    PSNR_DISPLAY_DB_FIELD_NUMBER: _ClassVar[int]
    SSIM_DISPLAY_FIELD_NUMBER: _ClassVar[int]
    LPIPS_DISPLAY_FIELD_NUMBER: _ClassVar[int]
    REWARD_DISPLAY_FIELD_NUMBER: _ClassVar[int]
    PSNR_DYNAMIC_DISPLAY_DB_FIELD_NUMBER: _ClassVar[int]
    DISPLAY_TRUTH_TIME_MS_FIELD_NUMBER: _ClassVar[int]
    RENDER_STEPS_FIELD_NUMBER: _ClassVar[int]
    READY_MS_FIELD_NUMBER: _ClassVar[int]
    LPIPS_SKIPPED_FIELD_NUMBER: _ClassVar[int]
    decision_id: int
    time_ms: float
    scene_time_ms: float
    psnr_db: float
    ssim: float
    lpips: float
    reward: float
    reward_terms: _containers.RepeatedScalarFieldContainer[str]
    training_step: int
    truth_time_ms: float
    psnr_dynamic_db: float
    ssim_dynamic: float
    dynamic_fraction: float
    decision_incarnation: int
    site: str
    display_time_ms: float
    psnr_display_db: float
    ssim_display: float
    lpips_display: float
    reward_display: float
    psnr_dynamic_display_db: float
    display_truth_time_ms: float
    render_steps: int
    ready_ms: float
    lpips_skipped: bool
    def __init__(self, decision_id: _Optional[int] = ..., time_ms: _Optional[float] = ..., scene_time_ms: _Optional[float] = ..., psnr_db: _Optional[float] = ..., ssim: _Optional[float] = ..., lpips: _Optional[float] = ..., reward: _Optional[float] = ..., reward_terms: _Optional[_Iterable[str]] = ..., training_step: _Optional[int] = ..., truth_time_ms: _Optional[float] = ..., psnr_dynamic_db: _Optional[float] = ..., ssim_dynamic: _Optional[float] = ..., dynamic_fraction: _Optional[float] = ..., decision_incarnation: _Optional[int] = ..., site: _Optional[str] = ..., display_time_ms: _Optional[float] = ..., psnr_display_db: _Optional[float] = ..., ssim_display: _Optional[float] = ..., lpips_display: _Optional[float] = ..., reward_display: _Optional[float] = ..., psnr_dynamic_display_db: _Optional[float] = ..., display_truth_time_ms: _Optional[float] = ..., render_steps: _Optional[int] = ..., ready_ms: _Optional[float] = ..., lpips_skipped: _Optional[bool] = ...) -> None: ...

class ViewRequest(_message.Message):
    __slots__ = ("site", "format", "pose", "intrinsics", "resolution", "alpha")
    SITE_FIELD_NUMBER: _ClassVar[int]
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    RESOLUTION_FIELD_NUMBER: _ClassVar[int]
    ALPHA_FIELD_NUMBER: _ClassVar[int]
    site: str
    format: str
    pose: Pose
    intrinsics: Intrinsics
    resolution: int
    alpha: float
    def __init__(self, site: _Optional[str] = ..., format: _Optional[str] = ..., pose: _Optional[_Union[Pose, _Mapping]] = ..., intrinsics: _Optional[_Union[Intrinsics, _Mapping]] = ..., resolution: _Optional[int] = ..., alpha: _Optional[float] = ...) -> None: ...

class ViewReply(_message.Message):
    __slots__ = ("data", "error", "reason", "decision_id", "time_ms", "training_step", "worker_id", "compute_s")
    DATA_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    DECISION_ID_FIELD_NUMBER: _ClassVar[int]
    TIME_MS_FIELD_NUMBER: _ClassVar[int]
    TRAINING_STEP_FIELD_NUMBER: _ClassVar[int]
    WORKER_ID_FIELD_NUMBER: _ClassVar[int]
    COMPUTE_S_FIELD_NUMBER: _ClassVar[int]
    data: bytes
    error: str
    reason: str
    decision_id: int
    time_ms: float
    training_step: int
    worker_id: str
    compute_s: float
    def __init__(self, data: _Optional[bytes] = ..., error: _Optional[str] = ..., reason: _Optional[str] = ..., decision_id: _Optional[int] = ..., time_ms: _Optional[float] = ..., training_step: _Optional[int] = ..., worker_id: _Optional[str] = ..., compute_s: _Optional[float] = ...) -> None: ...
