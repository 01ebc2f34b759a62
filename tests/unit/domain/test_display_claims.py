"""The display-time question of issue 40 §3 on small synthetic compare documents."""

from __future__ import annotations

import json

import numpy as np

from aoi3d.experiment.display_claims import compute_aware_beats_best_fixed

SEEDS = tuple(range(20000, 20008))


def grid_doc(aware_gain: float, shuffle: float = 0.0) -> dict:
    """A compare results.json over fixed cells and compute-aware policies, the best
    compute-aware ``aware_gain`` dB above the best fixed cell (``mat:100@50``); ``shuffle``
    lets a runner-up fixed cell win on every other seed."""
    rng = np.random.default_rng(0)
    nominal = {"mat:40@25": 22.0, "mat:100@50": 24.0, "mat:100@100": 23.6, "all@50": 22.5,
               "dmat:130@50": 24.0 + aware_gain, "deadline:100:40": 23.0}
    episodes = []
    for k, s in enumerate(SEEDS):
        common = rng.normal(0.0, 1.0)  # the seed's scene: shared by every policy (paired)
        for p, v in nominal.items():
            bump = shuffle if (p == "mat:100@100" and k % 2) else 0.0
            episodes.append({"policy": p, "seed": s,
                             "psnr_display_db": v + common + bump + rng.normal(0.0, 0.1)})
    doc = {"meta": {"seed_list": list(SEEDS), "episode_config": {"steps_per_epoch": 300}},
           "policies": [{"policy": p, "bound": False} for p in nominal], "episodes": episodes}
    return json.loads(json.dumps(doc))


def test_a_compute_aware_policy_ahead_of_the_best_cell_holds_and_meets_the_goal() -> None:
    v = compute_aware_beats_best_fixed(grid_doc(0.8))
    assert v.holds and "goal ≥ 0.5: met" in v.evidence
    assert v.numbers["best_fixed"] == "mat:100@50"
    assert v.numbers["best_compute_aware"] == "dmat:130@50"
    assert v.numbers["aware_minus_fixed"]["mean"] > 0.5


def test_a_tie_with_the_best_cell_does_not_hold_and_the_room_is_reported() -> None:
    tied = compute_aware_beats_best_fixed(grid_doc(0.0))
    assert not tied.holds and "not significantly different" in tied.evidence
    assert tied.numbers["per_seed_room_mean"] < 0.2
    worse = compute_aware_beats_best_fixed(grid_doc(-1.0))
    assert not worse.holds and "significantly worse" in worse.evidence
    # a runner-up cell wins every other seed by 0.8 − 0.4 = 0.4 dB: the room is about 0.2 dB
    roomy = compute_aware_beats_best_fixed(grid_doc(0.0, shuffle=0.8))
    assert 0.1 < roomy.numbers["per_seed_room_mean"] < 0.35
    assert roomy.numbers["per_seed_best_cell"][SEEDS[1]] == "mat:100@100"


def test_a_grid_without_a_compute_aware_policy_is_not_tested() -> None:
    doc = grid_doc(0.8)
    doc["policies"] = [r for r in doc["policies"] if r["policy"].startswith(("mat", "all"))]
    v = compute_aware_beats_best_fixed(doc)
    assert not v.holds and v.evidence.startswith("not tested")


def test_the_science_section_tables_the_question_with_its_header_first() -> None:
    from bench.science_display import render_lines

    v = compute_aware_beats_best_fixed(grid_doc(0.0)).to_dict()
    claim = {"statement": "a claim", "holds": True, "evidence": "e"}
    section = {"configs": {"fresh50": {"text": "fifty", "options": "--steps-per-epoch 50",
                                       "verdicts": [claim]}},
               "grid": v, "runs": [{"command": "aoi3d experiment compare --out "
                                    "/x/science/display/grid --policy all@25", "wall_s": 1.0,
                                    "load_at_start": 2.0, "load_at_end": 2.5}]}
    lines = render_lines(section, "results/science")
    at = next(i for i, line in enumerate(lines) if line.startswith(f"| {v['statement']}?"))
    assert lines[at - 2] == "| question | answer | evidence |" and "**no**" in lines[at]
    assert any("| fresh50: fifty (`--steps-per-epoch 50`) | a claim | **holds** |" in line
               for line in lines)
    assert any("`display/grid` 1.0 s (2.0/2.5)" in line for line in lines)
