"""Frame-selection policies over the AoI vector: all, MAT (``mat:<ms>``), freshest-k, and a
trained PPO agent (``ppo:<checkpoint>``, :mod:`aoi3d.rl.policy`)."""

from collections.abc import Mapping
from typing import Any

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


# ``ppo`` is registered here, but built by aoi3d.rl.policy, imported on first use: importing
# the policies stays free of torch, and aoi3d.rl (which imports aoi3d.policy.base) never
# meets a half-initialised aoi3d.policy.
def _ppo_from_args(fields: list[str]) -> Policy:
    from aoi3d.rl.policy import ppo_from_args

    return ppo_from_args(fields)


def _ppo_from_json(params: Mapping[str, Any]) -> Policy:
    from aoi3d.rl.policy import ppo_from_json

    return ppo_from_json(params)


register_policy(PolicyKind("ppo", "ppo:<checkpoint>", _ppo_from_args, _ppo_from_json))

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
