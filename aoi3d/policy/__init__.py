"""Frame-selection policies over the AoI vector: all, MAT (``mat:<ms>``), freshest-k."""

from aoi3d.policy.base import (
    ACCEPTED_FORMS,
    Policy,
    PolicyKind,
    PolicySpecError,
    as_aoi_vector,
    parse_policy,
    policy_from_json,
    register_policy,
)
from aoi3d.policy.rules import AllPolicy, FreshestPolicy, MatPolicy

__all__ = [
    "ACCEPTED_FORMS",
    "AllPolicy",
    "FreshestPolicy",
    "MatPolicy",
    "Policy",
    "PolicyKind",
    "PolicySpecError",
    "as_aoi_vector",
    "parse_policy",
    "policy_from_json",
    "register_policy",
]
