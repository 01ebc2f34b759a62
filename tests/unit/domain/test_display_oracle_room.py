"""The compute-aware question with its bound (issue 40): the oracle over (Γ, steps)'s room
over the best fixed cell, and compute-aware runs the caller names (a PPO agent), on small
synthetic compare documents."""

from __future__ import annotations

import json

import numpy as np

from aoi3d.experiment.display_claims import compute_aware_beats_best_fixed

SEEDS = tuple(range(20000, 20008))
ORACLE = "oracle:budgets:psnr_display_db"
PPO = "ppo:models/ppo/display/final.pt@100"


def doc(oracle_gain: float | None, ppo_gain: float = -0.3) -> dict:
    rng = np.random.default_rng(1)
    nominal = {"mat:100@50": 24.0, "mat:100@100": 23.8, "dmat:130@50": 23.9,
               PPO: 24.0 + ppo_gain}
    if oracle_gain is not None:
        nominal[ORACLE] = 24.0 + oracle_gain
    episodes = []
    for s in SEEDS:
        common = rng.normal(0.0, 1.0)
        for p, v in nominal.items():
            episodes.append({"policy": p, "seed": s,
                             "psnr_display_db": v + common + rng.normal(0.0, 0.05)})
    policies = [{"policy": p, "bound": p == ORACLE} for p in nominal]
    return json.loads(json.dumps({"meta": {"seed_list": list(SEEDS)}, "policies": policies,
                                  "episodes": episodes}))


def test_the_oracle_room_is_reported_beside_the_question() -> None:
    v = compute_aware_beats_best_fixed(doc(0.9))
    assert not v.holds and "no oracle searched" not in v.evidence
    room = v.numbers["oracle_minus_best_fixed"]
    assert 0.8 < room["mean"] < 1.0 and room["n"] == len(SEEDS)
    assert f"({ORACLE}, " in v.evidence and "− best fixed: +0.9" in v.evidence
    assert v.numbers["oracle_minus_best_compute_aware"]["mean"] > room["mean"]
    assert ORACLE not in v.numbers["means"]  # the bound is not a candidate
    without = compute_aware_beats_best_fixed(doc(None))
    assert "(no oracle searched)" in without.evidence
    assert "oracle_minus_best_fixed" not in without.numbers


def test_a_named_run_counts_as_compute_aware() -> None:
    plain = compute_aware_beats_best_fixed(doc(0.9, ppo_gain=0.8))
    assert plain.numbers["best_compute_aware"] == "dmat:130@50"  # ppo is not a kind of it
    named = compute_aware_beats_best_fixed(doc(0.9, ppo_gain=0.8), aware_labels=[PPO])
    assert named.numbers["best_compute_aware"] == PPO and named.holds
    assert "goal ≥ 0.5: met" in named.evidence
