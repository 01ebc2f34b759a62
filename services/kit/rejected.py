"""``Rejected``: a message that must be dropped, with its reason (:class:`RejectReason`) for
the metrics.

Its own module so that the cores, which raise it, import nothing that does I/O; the counting
(Prometheus) is :class:`services.kit.observe.Rejections`. Every reason is a member of
:class:`RejectReason`, the one list of the values of ``aoi3d_messages_rejected_total{reason}``
(and of the ingest's ``aoi3d_ingest_rejected_total{camera,reason}``); docs/operations.md's
table, "Why a message was dropped", lists them, and tests/unit/rules/test_reject_reasons.py keeps
the two equal and finds any ``Rejected`` raised with a bare string.
"""

from __future__ import annotations

from enum import StrEnum

__all__ = ["RejectReason", "Rejected"]


class RejectReason(StrEnum):
    """Why a message was dropped. A member is its label (a ``str``): the Prometheus label
    value, the key of a ``/status`` count, the text of a log line, as it is."""

    # the message itself
    MALFORMED = "malformed"
    TOO_LARGE = "too_large"
    NON_FINITE = "non_finite"
    BAD_POSE = "bad_pose"
    BAD_INTRINSICS = "bad_intrinsics"
    BAD_IMAGE = "bad_image"
    IMAGE_SIZE_MISMATCH = "image_size_mismatch"
    UNKNOWN_CAMERA = "unknown_camera"
    KEY_MISMATCH = "key_mismatch"
    UNKNOWN_SITE = "unknown_site"
    WRONG_SITE = "wrong_site"
    UNKNOWN_KEY = "unknown_key"
    # its time against the receiver's
    CLOCK_SKEW = "clock_skew"
    BAD_TIME = "bad_time"
    FUTURE_DELIVERY = "future_delivery"
    STALE_DECISION = "stale_decision"
    IMPLAUSIBLE_DECISION_ID = "implausible_decision_id"
    # what the receiver could not do with it
    NO_TRUTH = "no_truth"
    UNSCORABLE = "unscorable"
    NOT_RECORDING = "not_recording"
    INTERNAL_ERROR = "internal_error"
    # a ROS 2 sample at the ingest (docs/real-cameras.md, "Bad input")
    BAD_CDR = "bad_cdr"
    BAD_ATTACHMENT = "bad_attachment"
    TYPE_HASH_MISMATCH = "type_hash_mismatch"
    UNKNOWN_ENCODING = "unknown_encoding"
    IMAGE_MISMATCH = "image_mismatch"
    NO_INTRINSICS = "no_intrinsics"
    NO_POSE = "no_pose"
    STAMP_INVALID = "stamp_invalid"
    STAMP_FUTURE = "stamp_future"
    STAMP_STALE = "stamp_stale"
    STAMP_BEFORE_RUN = "stamp_before_run"
    SEQUENCE_REPLAYED = "sequence_replayed"


class Rejected(ValueError):
    """A message that must be dropped; ``reason`` says why (the label for metrics),
    ``detail`` what was wrong."""

    def __init__(self, reason: RejectReason, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail
