"""The oracle bound: per scored decision, the best selection found by search with the truth.

Not a policy: it scores candidate selections against the ground truth of the decision's
time, which no scheduler has. It is the number every policy is judged against — how much a
better choice of frames could still gain on the same seeds, the same channel draws and the
same reconstruction budget.

For every scored decision of an episode (seed s, epoch t), each candidate selection is one
**reconstruction**: the one-decision plan that trains on exactly those cameras' newest frames
at t (the plan :class:`aoi3d.rl.env.FrameSelectionEnv` builds for an action), run by the
experiments' own :func:`aoi3d.experiment.episode.run_plan` — a fresh field of model seed s,
``steps_per_epoch`` steps, rendered and scored against the truth at t like every policy's
decisions. The best candidate by the objective (``metric``: the reward by default; LPIPS
minimised, the others maximised) is the oracle's selection at t; ties go to the earlier
candidate. The oracle's episode is those selections at the scored decisions, its numbers the
means of their scores (:func:`aoi3d.experiment.episode.episode_result`), exactly what
``run_plan`` gives for that plan: with the ``fresh`` carry (required) a scored decision's
render depends on its own frames and the seed alone, so the per-decision searches are
independent and the oracle pairs by seed with every policy.

Three searches (``oracle:<search>[:<metric>]``; ``oracle`` is ``oracle:rules:reward``):

- ``rules`` — the best over every rule that decides at t: ``mat:Γ`` for every Γ (one
  selection per distinct AoI level, ``all`` included) and ``freshest:k`` for every k from 1
  to the number of cameras with a frame, deduplicated. A MAT selection is always a freshest
  selection (the k youngest frames) and the freshest:k differ for every k, so this is
  k = 1 … N_known: **N_known reconstructions per decision** (18 on the experiments' rig
  once every camera has delivered). By construction the bound is never below any
  ``mat:Γ``, ``freshest:k`` or ``all`` episode on the same seed, in its metric.
- ``greedy`` — greedy forward selection over cameras: start from no camera, add the camera
  whose addition scores best, stop when no addition improves the objective (or every known
  camera is in). It can find selections no rule makes (an old frame from a useful angle, a
  young one left out), and is not guaranteed to beat ``rules``. Cost: N_known + (N_known − 1)
  + … per decision, one round per camera added plus the round that stops: for N = 18 and 6
  cameras chosen, 18 + 17 + … + 13 = 93 reconstructions, plus 12 for the round that stops:
  105.
- ``budgets`` — issue 40: the best (Γ, steps) per decision. The candidates are the cells of
  the display-time grid, ``mat:Γ@s`` for Γ in :data:`BUDGET_GAMMAS` and ``all@s``, for s in
  :data:`BUDGET_STEPS` (18 cells): each cell is run as its whole episode on the seed (the
  plan ``aoi3d experiment compare --policy mat:Γ@s`` runs, under the same cache key, so a
  grid already run costs nothing), and at every scored decision the oracle takes the cell
  whose render scores best there (``oracle:budgets:psnr_display_db``: the truth at display
  time, the render shown its budget's compute later). With the ``fresh`` carry a scored
  decision's render depends on its own frames, budget and the seed alone, so a cell
  episode's score at a decision is the one-decision reconstruction's, and the oracle's
  episode replays as one plan (selection and budget per decision). It is never below any
  cell, per decision: the bound over the fixed (Γ, steps) choices a compute-aware policy
  picks from, per decision, with the truth no policy has. Cost: 18 reconstructions per
  decision, counted as cell episodes (``computed`` + ``cached`` = cells × seeds).

Candidates are cached like every episode (:class:`aoi3d.experiment.ResultCache`, under
:func:`aoi3d.experiment.plan_key` of their one-decision plan), so a re-run costs nothing and
two searches share the candidates they both try. What a search cost is recorded
(:class:`OracleEpisode`): reconstructions per decision, and their compute time.
``wait:<ω>`` policies decide at t + ω, against another truth: they are not searched over.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from aoi3d.experiment.config import EpisodeConfig
from aoi3d.experiment.episode import (
    EpisodeLinks,
    EpisodePlan,
    EpisodeResult,
    EpochScore,
    PlannedDecision,
    episode_links,
    episode_result,
    plan_episode,
    plan_key,
    planned_decision,
)
from aoi3d.metric import AT_DECISION, AT_DISPLAY, REWARD, lower_is_better
from aoi3d.policy import (
    AllPolicy,
    Budgeted,
    FreshestPolicy,
    MatPolicy,
    PolicyKind,
    decide,
    kind_of,
    register_policy,
)
from aoi3d.scene import SceneDataset

__all__ = [
    "BUDGET_GAMMAS",
    "BUDGET_STEPS",
    "ORACLE_FORMS",
    "ORACLE_METRICS",
    "SEARCHES",
    "DecisionSearch",
    "Evaluate",
    "OracleEpisode",
    "OracleSpec",
    "OracleSpecError",
    "budget_cells",
    "is_oracle_spec",
    "parse_oracle",
    "rule_masks",
    "search_oracle",
]

SEARCHES = ("rules", "greedy", "budgets")
ORACLE_METRICS = (REWARD.name, *(m for m in AT_DECISION if m != REWARD.name), *AT_DISPLAY)
"""What an oracle may maximise (LPIPS: minimise), per scored decision: the scores at the
decision's time (:data:`aoi3d.metric.AT_DECISION`), the reward (the default) first, then the
scores at display time (:data:`aoi3d.metric.AT_DISPLAY`)."""
BUDGET_GAMMAS = (40, 70, 100, 130, 160)
"""Γ (ms) of the ``budgets`` search's MAT cells (with ``all``): the display-time grid's."""
BUDGET_STEPS = (25, 50, 100)
"""Budgets (training steps) of the ``budgets`` search's cells: the display-time grid's."""


def budget_cells() -> list[str]:
    """The ``budgets`` search's candidates, in the grid's order: ``mat:Γ@s`` per budget s
    and Γ, then ``all@s`` per s."""
    cells = [Budgeted(MatPolicy(float(g)), s).spec for s in BUDGET_STEPS for g in BUDGET_GAMMAS]
    return cells + [Budgeted(AllPolicy(), s).spec for s in BUDGET_STEPS]
ORACLE_FORMS = ("oracle", "oracle:<search>", "oracle:<search>:<metric>")

Evaluate = Callable[[Sequence[EpisodePlan]], Sequence[EpisodeResult]]
"""Runs one-decision plans and returns their results in order (the sweep's
:func:`aoi3d.experiment.sweep.run_plans`: cached, on local cores or Ray)."""


class OracleSpecError(ValueError):
    """An oracle spec is invalid; the message lists the accepted forms."""

    def __init__(self, problem: str, spec: object) -> None:
        super().__init__(f"bad oracle spec {spec!r}: {problem}. Accepted forms: "
                         f"{', '.join(ORACLE_FORMS)}; search: {', '.join(SEARCHES)}; "
                         f"metric: {', '.join(ORACLE_METRICS)}.")


@dataclass(frozen=True)
class OracleSpec:
    """A search and the objective it maximises per decision."""

    search: str = "rules"
    metric: str = "reward"

    def __post_init__(self) -> None:
        if self.search not in SEARCHES:
            raise OracleSpecError(f"unknown search {self.search!r}", self.spec)
        if self.metric not in ORACLE_METRICS:
            raise OracleSpecError(f"unknown metric {self.metric!r}", self.spec)

    @property
    def spec(self) -> str:
        """The canonical label, ``oracle:<search>:<metric>``."""
        return f"oracle:{self.search}:{self.metric}"

    @property
    def sign(self) -> float:
        """+1 where the metric is maximised, −1 for LPIPS."""
        return -1.0 if lower_is_better(self.metric) else 1.0

    kind = "oracle"

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "search": self.search, "metric": self.metric}


def is_oracle_spec(spec: str) -> bool:
    """Whether ``spec`` names a bound (its kind is of the ``bound`` family: the oracle)."""
    try:
        return kind_of(spec).family == "bound"
    except ValueError:
        return False


def parse_oracle(spec: str) -> OracleSpec:
    """``oracle[:<search>[:<metric>]]``; ``OracleSpecError`` otherwise."""
    head, *fields = (f.strip() for f in spec.strip().split(":"))
    if head.lower() != "oracle":
        raise OracleSpecError("it does not start with 'oracle'", spec)
    if len(fields) > 2:
        raise OracleSpecError(f"at most 2 parameters, got {len(fields)}", spec)
    search = fields[0].lower() if fields else "rules"
    metric = fields[1] if len(fields) == 2 else "reward"
    if search not in SEARCHES:
        raise OracleSpecError(f"unknown search {search!r}", spec)
    if metric not in ORACLE_METRICS:
        raise OracleSpecError(f"unknown metric {metric!r}", spec)
    return OracleSpec(search, metric)


def _oracle_from_args(fields: list[str]) -> OracleSpec:
    return parse_oracle(":".join(["oracle", *fields]))


def _oracle_from_json(params: Mapping[str, Any]) -> OracleSpec:
    return OracleSpec(params.get("search", "rules"), params.get("metric", "reward"))


KIND = PolicyKind("oracle", "oracle[:<search>[:<metric>]]", _oracle_from_args,
                  _oracle_from_json, family="bound")
"""The oracle, registered (family ``bound``: searched with the truth, not a policy) when this
module is imported."""
register_policy(KIND)


def rule_masks(aoi_ms: np.ndarray) -> list[np.ndarray]:
    """The distinct non-empty selections of ``mat:Γ`` for every Γ (just above each AoI level,
    up to ``all``) and of ``freshest:k`` for k = 1 … N_known, in that order, each made by the
    policy's own ``select``."""
    aoi = np.asarray(aoi_ms, dtype=np.float64)
    known = ~np.isnan(aoi)
    masks: list[np.ndarray] = []
    seen: set[bytes] = set()

    def add(mask: np.ndarray) -> None:
        mask = np.asarray(mask, dtype=bool) & known
        if mask.any() and mask.tobytes() not in seen:
            seen.add(mask.tobytes())
            masks.append(mask)

    for level in np.unique(aoi[known]):
        add(MatPolicy(float(np.nextafter(level, math.inf))).select(aoi))
    for k in range(1, int(known.sum()) + 1):
        add(FreshestPolicy(k).select(aoi))
    return masks


@dataclass(frozen=True)
class DecisionSearch:
    """What the search did at one scored decision: ``candidates`` reconstructions tried (in
    ``rounds`` batches) among ``n_known`` cameras with a frame, the chosen ``cameras`` and
    the objective's ``value`` there."""

    seed: int
    decision_ms: int
    n_known: int
    candidates: int
    rounds: int
    cameras: tuple[int, ...]
    value: float
    cell: str = ""
    """The ``budgets`` search's chosen cell (``mat:70@50``); empty for the others."""

    def to_dict(self) -> dict[str, Any]:
        doc = dict(vars(self), cameras=list(self.cameras))
        if not self.cell:
            doc.pop("cell")
        return doc


@dataclass(frozen=True)
class OracleEpisode:
    """The oracle's episode of one seed: its ``result`` (labelled with the oracle's spec;
    ``wall_s``: the compute time of every candidate it tried), its ``plan`` (the chosen
    selections at the scored decisions) and the per-decision searches."""

    result: EpisodeResult
    plan: EpisodePlan
    decisions: tuple[DecisionSearch, ...]

    @property
    def reconstructions(self) -> int:
        return sum(d.candidates for d in self.decisions)


@dataclass
class _State:
    """One scored decision under search."""

    seed: int
    base: EpisodePlan
    links: EpisodeLinks
    index: int  # in base.decisions
    aoi: np.ndarray
    chosen: np.ndarray | None = None  # mask
    value: float = -math.inf
    score: EpochScore | None = None
    decision: PlannedDecision | None = None
    candidates: int = 0
    rounds: int = 0
    active: bool = True
    wall_s: list[float] = field(default_factory=list)


def _candidate(state: _State, mask: np.ndarray) -> EpisodePlan:
    """The one-decision plan that trains on the cameras of ``mask`` at the state's epoch."""
    d = state.base.decisions[state.index]
    bits = np.asarray(mask, dtype=bool)
    sel = decide(AllPolicy(), d.decision_ms, state.links.newest_ms, act=lambda _a, _s: bits)
    decision = planned_decision(sel, state.links.camera_ids, train=True, scored=True)
    label = "".join("1" if b else "0" for b in sel.mask)
    return replace(state.base, policy=f"mask:{label}", decisions=(decision,))


def _value(result: EpisodeResult, oracle: OracleSpec) -> float:
    return oracle_value(result.epochs[0], oracle)


def _evaluate_round(states: list[tuple[_State, list[np.ndarray]]], oracle: OracleSpec,
                    evaluate: Evaluate) -> list[bool]:
    """Score every state's candidate masks; keep each state's best. Returns, per state,
    whether its best improved on what it had."""
    plans = [_candidate(s, m) for s, masks in states for m in masks]
    results = list(evaluate(plans))
    if len(results) != len(plans):
        raise RuntimeError(f"evaluate returned {len(results)} results for {len(plans)} plans")
    improved = []
    i = 0
    for state, masks in states:
        best = None
        for mask in masks:
            plan, result = plans[i], results[i]
            i += 1
            state.wall_s.append(result.wall_s)
            value = _value(result, oracle)
            if best is None or value > best[0]:
                best = (value, mask, result, plan)
        state.candidates += len(masks)
        state.rounds += 1
        assert best is not None
        if state.chosen is None or best[0] > state.value:
            state.value, state.chosen = best[0], best[1]
            state.score, state.decision = best[2].epochs[0], best[3].decisions[0]
            improved.append(True)
        else:
            improved.append(False)
    return improved


def search_oracle(cfg: EpisodeConfig, dataset: SceneDataset, oracle: OracleSpec | str,
                  seeds: Sequence[int], evaluate: Evaluate, *, lpips: bool,
                  progress: Callable[[str], None] | None = None) -> list[OracleEpisode]:
    """The oracle's episodes for ``seeds`` (see the module). ``evaluate`` runs candidate
    plans (batched: one call per search round, every seed and decision together);
    ``lpips``: whether the results compute LPIPS (for the oracle plan's cache key);
    ``progress(text)``: told what each round is about to run."""
    spec = parse_oracle(oracle) if isinstance(oracle, str) else oracle
    if cfg.carry != "fresh":
        raise ValueError(f"the oracle searches each scored decision on its own, which needs "
                         f"carry 'fresh' (a fresh model per scored decision), not "
                         f"{cfg.carry!r}")
    states: list[_State] = []
    bases: dict[int, EpisodePlan] = {}
    links_of: dict[int, EpisodeLinks] = {}
    for seed in seeds:
        links = episode_links(cfg, dataset, seed)
        base = plan_episode(cfg, dataset, AllPolicy(), seed, links=links)
        bases[seed], links_of[seed] = base, links
        for i, d in enumerate(base.decisions):
            if d.scored:
                aoi = decide(AllPolicy(), d.decision_ms, links.newest_ms).aoi_ms
                states.append(_State(seed=seed, base=base, links=links, index=i, aoi=aoi))

    def run(batch: list[tuple[_State, list[np.ndarray]]], what: str) -> list[bool]:
        if progress is not None:
            progress(f"{spec.spec} {what}: {sum(len(m) for _, m in batch)} reconstructions "
                     f"at {len(batch)} decisions")
        return _evaluate_round(batch, spec, evaluate)

    if spec.search == "budgets":
        return _search_cells(cfg, dataset, spec, seeds, evaluate, bases, links_of, lpips=lpips,
                             progress=progress)
    if spec.search == "rules":
        batch = [(s, rule_masks(s.aoi)) for s in states]
        for s, masks in batch:
            if not masks:  # no camera has a frame yet: the empty selection is all there is
                masks.append(np.zeros(len(s.aoi), dtype=bool))
        run(batch, "rules")
    else:
        round_no = 0
        while True:
            batch = []
            for s in states:
                if not s.active:
                    continue
                known = ~np.isnan(s.aoi)
                selected = s.chosen if s.chosen is not None else np.zeros(len(s.aoi), dtype=bool)
                adds = [selected | np.eye(len(s.aoi), dtype=bool)[c]
                        for c in np.flatnonzero(known & ~selected)]
                if not adds:
                    if s.chosen is None:  # no camera has a frame yet
                        adds = [selected]
                    else:
                        s.active = False
                        continue
                batch.append((s, adds))
            if not batch:
                break
            round_no += 1
            improved = run(batch, f"greedy round {round_no}")
            for (s, _), better in zip(batch, improved, strict=True):
                s.active = better  # the next round tries one more camera, if any is left

    return [_episode_of(seed, [s for s in states if s.seed == seed], bases[seed], spec,
                        dataset, lpips) for seed in seeds]


def _episode_of(seed: int, mine: list[_State], base: EpisodePlan, spec: OracleSpec,
                dataset: SceneDataset, lpips: bool) -> OracleEpisode:
    """One seed's oracle episode from its searched decisions (``rules``, ``greedy``)."""
    chosen = {s.index: s.decision for s in mine}
    decisions = tuple(chosen.get(i, d) for i, d in enumerate(base.decisions))
    plan = replace(base, policy=spec.spec, decisions=decisions)  # type: ignore[arg-type]
    epochs = [s.score for s in mine]
    assert all(e is not None for e in epochs)
    result = episode_result(plan, epochs, key=plan_key(plan, dataset, lpips=lpips),  # type: ignore[arg-type]
                            wall_s=float(sum(w for s in mine for w in s.wall_s)))
    searches = tuple(
        DecisionSearch(seed=seed, decision_ms=base.decisions[s.index].decision_ms,
                       n_known=int(np.count_nonzero(~np.isnan(s.aoi))),
                       candidates=s.candidates, rounds=s.rounds,
                       cameras=s.decision.cameras if s.decision else (),
                       value=spec.sign * s.value)
        for s in mine)
    return OracleEpisode(result=result, plan=plan, decisions=searches)


def _search_cells(cfg: EpisodeConfig, dataset: SceneDataset, spec: OracleSpec,
                  seeds: Sequence[int], evaluate: Evaluate, bases: Mapping[int, EpisodePlan],
                  links: Mapping[int, EpisodeLinks], *, lpips: bool,
                  progress: Callable[[str], None] | None
                  ) -> list[OracleEpisode]:
    """The ``budgets`` search (see the module): every cell's episode per seed, evaluated in
    one batch, and per scored decision the best cell there."""
    cells = budget_cells()
    plans = [plan_episode(cfg, dataset, c, seed, links=links[seed])
             for seed in seeds for c in cells]
    if progress is not None:
        progress(f"{spec.spec}: {len(plans)} cell episodes ({len(cells)} cells × "
                 f"{len(seeds)} seeds)")
    results = list(evaluate(plans))
    if len(results) != len(plans):
        raise RuntimeError(f"evaluate returned {len(results)} results for {len(plans)} plans")
    episodes = []
    for k, seed in enumerate(seeds):
        mine = list(zip(plans[k * len(cells):(k + 1) * len(cells)],
                        results[k * len(cells):(k + 1) * len(cells)], strict=True))
        base = bases[seed]
        scored = [i for i, d in enumerate(base.decisions) if d.scored]
        for plan, _ in mine:
            if [plan.decisions[i].decision_ms for i in scored] != [
                    base.decisions[i].decision_ms for i in scored]:
                raise RuntimeError(f"{plan.policy}: its scored decisions are not the grid's")
        decisions = list(base.decisions)
        epochs: list[EpochScore] = []
        searches = []
        for j, i in enumerate(scored):
            values = [oracle_value(r.epochs[j], spec) for _, r in mine]
            best = int(np.argmax(values))  # the first of equals
            plan, result = mine[best]
            decisions[i] = plan.decisions[i]
            epochs.append(result.epochs[j])
            searches.append(DecisionSearch(
                seed=seed, decision_ms=base.decisions[i].decision_ms,
                n_known=base.decisions[i].n_known, candidates=len(cells), rounds=1,
                cameras=plan.decisions[i].cameras, value=spec.sign * values[best],
                cell=cells[best]))
        chosen = replace(base, policy=spec.spec, decisions=tuple(decisions))  # type: ignore[arg-type]
        result = episode_result(chosen, epochs, key=plan_key(chosen, dataset, lpips=lpips),
                                wall_s=float(sum(r.wall_s for _, r in mine)))
        episodes.append(OracleEpisode(result=result, plan=chosen, decisions=tuple(searches)))
    return episodes


def oracle_value(score: EpochScore, oracle: OracleSpec) -> float:
    """The objective at one scored decision, in its better direction (−inf where it is
    missing or not finite)."""
    v = getattr(score, oracle.metric)
    return -math.inf if v is None or not math.isfinite(v) else oracle.sign * float(v)
