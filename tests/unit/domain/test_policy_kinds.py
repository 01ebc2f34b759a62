"""Policies as types: one registry of kinds in families (aoi3d/policy/base.py), baselines and
the oracle registered through it, results that carry their policy's JSON, and no caller that
tells kinds apart by a label's prefix."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import aoi3d.experiment  # noqa: F401  (registers the baseline and bound kinds)
from aoi3d.policy import (
    FAMILIES,
    PolicyKind,
    PolicySpecError,
    family_of,
    kind_of,
    parse_policy,
    register_family,
    register_policy,
    short_label,
)
from aoi3d.policy import base as registry

ROOT = Path(__file__).resolve().parents[3]


def test_every_label_has_a_kind_and_a_family() -> None:
    expected = {"all": ("all", "rule"), "mat:70": ("mat", "rule"),
                "freshest:6": ("freshest", "rule"), "wait:40": ("wait", "rule"),
                "ppo:models/ppo/quick/final.pt": ("ppo", "learned"),
                "wsum:60@mat:130": ("wsum", "baseline"), "tembed": ("tembed", "baseline"),
                "oracle:rules:reward": ("oracle", "bound")}
    for label, (kind, family) in expected.items():
        assert (kind_of(label).kind, family_of(label)) == (kind, family), label
    assert kind_of({"kind": "mat", "mat_ms": 70}).kind == "mat"
    assert kind_of(parse_policy("freshest:3")).kind == "freshest"
    assert set(FAMILIES) >= {"rule", "learned", "baseline", "bound"}
    with pytest.raises(PolicySpecError, match="unknown kind"):
        kind_of("bogus:1")


def test_only_policy_families_parse_as_policies() -> None:
    for label in ("wsum:60", "oracle:rules:reward"):
        with pytest.raises(PolicySpecError, match="not a policy"):
            parse_policy(label)
    assert short_label("ppo:models/ppo/quick/final.pt") == "ppo:quick/final.pt"
    assert short_label("wsum:60@ppo:a/b/c.pt") == "wsum:60@ppo:a/b/c.pt"
    assert short_label("not-a-kind") == "not-a-kind"


def test_a_new_family_and_kind_register_in_one_step(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    monkeypatch.setattr(registry, "FAMILIES", dict(registry.FAMILIES))
    monkeypatch.setattr(registry, "POLICY_FAMILIES", set(registry.POLICY_FAMILIES))
    monkeypatch.setattr(registry, "ACCEPTED_FORMS", list(registry.ACCEPTED_FORMS))
    register_family("example", "Γ chosen online", policies=True)
    mat = kind_of("mat:1")
    register_policy(PolicyKind("plugin", "plugin:<ms>", mat.from_args, mat.from_json,
                               family="example"))
    assert family_of("plugin:70") == "example" and parse_policy("plugin:70").gamma_ms == 70
    with pytest.raises(ValueError, match="unknown family"):
        register_policy(PolicyKind("x", "x", mat.from_args, mat.from_json, family="nope"))


def test_no_kind_is_told_by_a_label_prefix_outside_the_policy_package() -> None:
    """The issue's done-when: no ``startswith("mat:")``-style test of a policy kind (nor
    ``"mat:best"`` rebuilt as ``f"mat:{…}"``) outside aoi3d/policy."""
    kinds = "mat|ppo|freshest|wait|all|oracle|wsum|tembed"
    pattern = re.compile(rf"""startswith\(\(?["']({kinds})[:"']|f["']mat:\{{""")
    offenders = [str(p.relative_to(ROOT)) for p in [*ROOT.glob("aoi3d/**/*.py"),
                                                    *ROOT.glob("bench/*.py")]
                 if "policy" not in p.relative_to(ROOT).parts[:2]
                 and pattern.search(p.read_text())]
    assert offenders == []
