"""Selection policies over the AoI vector: all, MAT, freshest-k; specs and JSON forms."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from aoi3d.policy import (
    ACCEPTED_FORMS,
    AllPolicy,
    BasePolicy,
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
from aoi3d.policy.wait import WaitPolicy

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
    class OldestPolicy(BasePolicy):  # the answers it has no need of: BasePolicy's defaults
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


# --- the registry and the decision step ------------------------------------------------------
def test_importing_the_package_registers_every_kind_without_torch_or_upward_imports() -> None:
    """A fresh interpreter: ``import aoi3d.policy`` alone knows every policy kind, in one order,
    and loads neither torch nor aoi3d.rl nor aoi3d.experiment."""
    import subprocess
    import sys

    code = ("import sys, aoi3d.policy as p; print(p.ACCEPTED_FORMS); "
            "print(sorted(m for m in sys.modules if m == 'torch' or m.startswith("
            "('aoi3d.rl', 'aoi3d.experiment'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=60).stdout.splitlines()
    assert out == ["['all', 'mat:<ms>', 'freshest:<k>', 'wait:<ms>', 'ppo:<checkpoint>', "
                   "'adaptive:<plugin|bandit>', 'dmat:<ms>', 'deadline:<ms>:<deadline_ms>']",
                   "[]"]


def test_decide_takes_the_aoi_at_t_plus_the_wait_and_never_an_unknown_camera() -> None:
    from aoi3d.policy import decide

    deliveries = {0: [(0.0, 5.0), (30.0, 70.0)], 1: [(10.0, 95.0)], 2: []}  # (gen, delivery)

    def newest_at(s: float) -> np.ndarray:
        out = np.full(3, NAN)
        for cam, frames in deliveries.items():
            gens = [g for g, d in frames if d <= s]
            if gens:
                out[cam] = max(gens)
        return out

    asked: list[float] = []
    sel = decide(parse_policy("all"), 60, newest_at)
    assert (sel.decision_ms, sel.eval_ms, sel.policy) == (60, 60, "all")
    np.testing.assert_array_equal(sel.aoi_ms, [60.0, NAN, NAN])
    assert sel.mask.tolist() == [True, False, False]
    # wait:40 decides epoch 60 at 100: camera 0's frame of 30 arrived at 70, camera 1's at 95
    sel = decide(parse_policy("wait:40"), 60, lambda s: asked.append(s) or newest_at(s))
    assert asked == [100] and sel.eval_ms == 100
    np.testing.assert_array_equal(sel.aoi_ms, [70.0, 90.0, NAN])
    assert sel.mask.tolist() == [False, False, False]  # neither was captured since t = 60
    assert sel.cameras([11, 12, 13]) == () and math.isnan(decide(
        parse_policy("all"), 1, newest_at).mean_aoi_all_ms)
    # an agent's action in the policy's place: its bits, less the unknown camera
    sel = decide(parse_policy("mat:0"), 100, newest_at, act=lambda aoi, s: np.ones(3, bool))
    assert sel.mask.tolist() == [True, True, False] and sel.cameras([11, 12, 13]) == (11, 12)
    assert sel.gen_ms.tolist() == [30.0, 10.0] and sel.selected_aoi_ms.tolist() == [70.0, 90.0]
    with pytest.raises(ValueError, match="selection of shape"):
        decide(parse_policy("all"), 100, newest_at, act=lambda aoi, s: np.ones(2, bool))


def test_policies_answer_their_own_questions() -> None:
    fresh = parse_policy("freshest:5")
    fresh.check_fits(5)
    with pytest.raises(PolicySpecError, match=r"0\.\.4"):
        fresh.check_fits(4)
    for spec in ("all", "mat:10", "wait:20", "freshest:1"):
        policy = parse_policy(spec)
        assert isinstance(policy, BasePolicy)
        policy.check_fits(1)  # any rig
        assert policy.on_device("cuda") is policy  # no model to place
        assert not policy.learns
    assert parse_policy("wait:20").wait_ms == 20 and parse_policy("all").wait_ms == 0
    assert parse_policy("mat:10").gamma_ms == 10.0 and parse_policy("all").gamma_ms is None
    with pytest.raises(TypeError):
        WaitPolicy()  # type: ignore[call-arg]  # ω is required, not BasePolicy's 0


def test_a_policy_missing_a_member_is_not_a_policy() -> None:
    """The protocol is complete: a kind that forgets an answer (here ``wait_ms``) is refused,
    not silently given a default."""

    class Bare:
        kind = "bare"
        spec = "bare"
        learns = False
        gamma_ms = None
        wants_quality = False

        def observe(self, now_ms, deliveries) -> None: ...

        def observe_quality(self, time_ms, scores) -> None: ...

        def select(self, aoi_ms):
            return np.zeros(len(aoi_ms), bool)

        def to_json(self):
            return {"kind": "bare"}

        def reset(self) -> None: ...

        def check_fits(self, n_cameras: int) -> None: ...

        def on_device(self, device: str):
            return self

        budget_steps = None

        def observe_lag(self, lag) -> None: ...

        def budget_for(self, aoi_ms):
            return None

    assert not isinstance(Bare(), Policy)
    Bare.wait_ms = 0
    assert isinstance(Bare(), Policy)
