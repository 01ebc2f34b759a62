"""Selection policies over the AoI vector: all, MAT, freshest-k; specs and JSON forms."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from aoi3d.policy import (
    ACCEPTED_FORMS,
    AllPolicy,
    FreshestPolicy,
    MatPolicy,
    Policy,
    PolicyKind,
    PolicySpecError,
    parse_policy,
    policy_from_json,
    register_policy,
)
from aoi3d.policy import base as policy_base

NAN = np.nan
AOI = np.array([10.0, NAN, 50.0, 51.0, 5.0, 10.0, 80.0])


def test_all_selects_every_known_aoi() -> None:
    np.testing.assert_array_equal(AllPolicy().select(AOI), ~np.isnan(AOI))
    assert not AllPolicy().select(np.full(3, NAN)).any()


def test_mat_uses_a_camera_iff_its_aoi_is_below_the_threshold() -> None:
    mask = MatPolicy(51).select(AOI)
    np.testing.assert_array_equal(mask, [True, False, True, False, True, True, False])
    assert MatPolicy(51.5).select(AOI)[3]  # 51 < 51.5
    assert not MatPolicy(0).select(np.array([0.0, 1.0, NAN])).any()  # Γ = 0 selects none
    assert not MatPolicy(1e9).select(np.array([NAN]))[0]  # unknown is never selected


def test_freshest_takes_the_k_smallest_known_aoi_ties_by_camera_order() -> None:
    np.testing.assert_array_equal(
        FreshestPolicy(2).select(AOI), [True, False, False, False, True, False, False]
    )
    # Ties at 10 ms: camera position 0 wins over position 5.
    np.testing.assert_array_equal(
        FreshestPolicy(2).select(np.array([10.0, 3.0, 10.0])), [True, True, False]
    )
    assert FreshestPolicy(100).select(AOI).sum() == 6  # only the known ones
    assert not FreshestPolicy(0).select(AOI).any()
    assert not FreshestPolicy(3).select(np.full(4, NAN)).any()


@pytest.mark.parametrize("policy", [AllPolicy(), MatPolicy(51), FreshestPolicy(6)])
def test_policies_reject_a_non_vector(policy: Policy) -> None:
    with pytest.raises(ValueError, match="1-D"):
        policy.select(np.zeros((2, 3)))
    assert policy.select([1.0, 2.0]).dtype == bool


@pytest.mark.parametrize(
    ("spec", "expected", "canonical", "as_json"),
    [
        ("all", AllPolicy(), "all", {"kind": "all"}),
        (" ALL ", AllPolicy(), "all", {"kind": "all"}),
        ("mat:51", MatPolicy(51), "mat:51", {"kind": "mat", "mat_ms": 51}),
        ("mat:51.0", MatPolicy(51), "mat:51", {"kind": "mat", "mat_ms": 51}),
        ("mat:37.5", MatPolicy(37.5), "mat:37.5", {"kind": "mat", "mat_ms": 37.5}),
        ("mat:0", MatPolicy(0), "mat:0", {"kind": "mat", "mat_ms": 0}),
        ("freshest:6", FreshestPolicy(6), "freshest:6", {"kind": "freshest", "k": 6}),
    ],
)
def test_specs_and_json_round_trip(
    spec: str, expected: Policy, canonical: str, as_json: dict[str, Any]
) -> None:
    policy = parse_policy(spec)
    assert policy == expected
    assert isinstance(policy, Policy)
    assert policy.spec == canonical
    assert policy.to_json() == as_json
    assert json.loads(json.dumps(policy.to_json())) == as_json
    assert policy_from_json(as_json) == policy
    assert parse_policy(policy.spec) == policy
    assert parse_policy(policy) is policy


@pytest.mark.parametrize(
    ("spec", "problem"),
    [
        ("", "empty"),
        ("best", "unknown kind"),
        ("mat", "takes 1 parameter"),
        ("mat:1:2", "takes 1 parameter"),
        ("all:3", "takes 0 parameter"),
        ("mat:abc", "must be a number"),
        ("mat:-1", ">= 0"),
        ("mat:inf", "finite"),
        ("mat:nan", "finite"),
        ("freshest:2.5", "whole number"),
        ("freshest:-1", ">= 0"),
        ("freshest:x", "must be a number"),
    ],
)
def test_bad_specs_say_what_and_list_the_forms(spec: str, problem: str) -> None:
    with pytest.raises(PolicySpecError) as info:
        parse_policy(spec)
    message = str(info.value)
    assert problem in message and repr(spec) in message
    for form in ("all", "mat:<ms>", "freshest:<k>"):
        assert form in message
    assert isinstance(info.value, ValueError)


@pytest.mark.parametrize(
    ("data", "problem"),
    [
        ({}, '"kind"'),
        ({"kind": 3}, '"kind"'),
        ({"kind": "best"}, "unknown kind"),
        ({"kind": "mat"}, "needs key"),
        ({"kind": "mat", "mat_ms": "51"}, "JSON number"),
        ({"kind": "mat", "mat_ms": -2}, ">= 0"),
        ({"kind": "mat", "mat_ms": 51, "k": 2}, "does not take"),
        ({"kind": "all", "k": 2}, "does not take"),
        ({"kind": "freshest", "k": 2.5}, "whole number"),
        ({"kind": "freshest", "k": True}, "must be a number"),
        ([1, 2], "JSON object"),
    ],
)
def test_bad_json_forms(data: Any, problem: str) -> None:
    with pytest.raises(PolicySpecError, match="Accepted forms") as info:
        policy_from_json(data)
    assert problem in str(info.value)


def test_constructors_validate() -> None:
    with pytest.raises(ValueError):
        MatPolicy(float("inf"))
    with pytest.raises(ValueError):
        FreshestPolicy(-3)
    assert FreshestPolicy(4.0).k == 4  # type: ignore[arg-type]


def test_a_new_kind_plugs_in_through_the_registry() -> None:
    """A later kind (e.g. ``wait:<ms>`` or ``ppo``) needs no change to parsing or JSON."""

    @dataclass(frozen=True)
    class OldestPolicy:
        kind = "oldest"
        spec = "oldest"

        def select(self, aoi_ms: np.ndarray) -> np.ndarray:
            aoi = np.asarray(aoi_ms, dtype=float)
            mask = np.zeros(len(aoi), dtype=bool)
            if (~np.isnan(aoi)).any():
                mask[np.nanargmax(aoi)] = True
            return mask

        def to_json(self) -> dict[str, Any]:
            return {"kind": "oldest"}

        def reset(self) -> None:
            pass

    def from_args(fields: list[str]) -> OldestPolicy:
        policy_base.expect_fields("oldest", fields, ())
        return OldestPolicy()

    def from_json(params: Mapping[str, Any]) -> OldestPolicy:
        policy_base.expect_keys("oldest", params, ())
        return OldestPolicy()

    forms_before = list(ACCEPTED_FORMS)  # other modules (e.g. the ω-wait policy) may register
    register_policy(PolicyKind("oldest", "oldest", from_args, from_json))
    try:
        assert "oldest" in ACCEPTED_FORMS
        policy = parse_policy("oldest")
        assert isinstance(policy, Policy)
        assert policy.select(AOI).tolist() == [False] * 6 + [True]
        assert policy_from_json({"kind": "oldest"}) == policy
        with pytest.raises(PolicySpecError, match="oldest"):
            parse_policy("nope")
        with pytest.raises(ValueError, match="already registered"):
            register_policy(PolicyKind("oldest", "oldest", from_args, from_json))
    finally:
        del policy_base._REGISTRY["oldest"]
        ACCEPTED_FORMS.remove("oldest")
    assert forms_before == ACCEPTED_FORMS
    assert forms_before[:3] == ["all", "mat:<ms>", "freshest:<k>"]
