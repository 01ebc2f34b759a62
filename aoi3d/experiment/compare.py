"""``aoi3d experiment compare``'s policies side by side: the specs checked before any sweep
runs (:func:`plan_compare`: policies, the follow-up paper's trainer baselines, ``mat:best``
and the oracle bounds), resolved once the best Γ is known (:meth:`ComparePlan.resolve`), and
the results set side by side with each bound's paired distance to every policy
(:class:`CompareResult`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from aoi3d.experiment.baselines import (
    TrainerOption,
    TrainerSpecError,
    baseline_label,
    is_trainer_spec,
    split_baseline,
)
from aoi3d.experiment.config import EpisodeConfig
from aoi3d.experiment.episode import EpisodeResult
from aoi3d.experiment.episode.plan import check_budget_applies
from aoi3d.experiment.optimum import Optimum, paired_difference, sign_of
from aoi3d.experiment.oracle import OracleSpec, OracleSpecError, is_oracle_spec, parse_oracle
from aoi3d.experiment.sweep import OracleOutcome, aggregate
from aoi3d.experiment.tradeoff import OPTIMUM_METRICS, sweep_optima
from aoi3d.field import field_config
from aoi3d.policy import MatPolicy, Policy, PolicySpecError, parse_policy

__all__ = [
    "MAT_BEST",
    "ComparePlan",
    "CompareResult",
    "CompareSpecError",
    "bound_doc",
    "plan_compare",
]

MAT_BEST = "mat:best"
"""The ``compare --policy`` value for MAT at the best Γ of the tradeoff sweep (or
``--mat-ms``): the command's placeholder, resolved to a ``MatPolicy`` with that Γ."""


class CompareSpecError(ValueError):
    """A ``compare`` spec that cannot run; the message says which and why."""


@dataclass(frozen=True)
class ComparePlan:
    """The checked specs: per policy spec its trainer option (None: the plain policy) and its
    policy (None: ``mat:best``, whose Γ is known once the tradeoff sweep has run), and the
    oracle bounds."""

    entries: list[tuple[TrainerOption | None, Policy | None]]
    oracles: list[OracleSpec]

    @property
    def needs_best_gamma(self) -> bool:
        """Whether a spec is ``mat:best``."""
        return any(p is None for _, p in self.entries)

    def resolve(self, mat_ms: float | None
                ) -> tuple[list[tuple[str | None, str]], dict[str, dict[str, Any]]]:
        """The runs (trainer spec or None, policy spec; each once, in order) with ``mat:best``
        at ``mat_ms`` (required when a spec is ``mat:best``), and each label's JSON: the
        policy's ``to_json()``, inside its trainer option's for a baseline, and the oracles'
        (results carry it beside the label)."""
        resolved: dict[tuple[str | None, str], None] = {}
        as_json: dict[str, dict[str, Any]] = {}
        if mat_ms is None and self.needs_best_gamma:
            raise ValueError("mat:best needs the best Γ (mat_ms)")
        for trainer, p in self.entries:
            pol = p if p is not None else MatPolicy(mat_ms or 0.0)
            resolved[None if trainer is None else trainer.spec, pol.spec] = None
            if trainer is None:
                as_json[pol.spec] = pol.to_json()
            else:
                as_json[baseline_label(trainer, pol.spec)] = {**trainer.to_json(),
                                                              "policy": pol.to_json()}
        as_json.update({o.spec: o.to_json() for o in self.oracles})
        return list(resolved), as_json


def plan_compare(specs: Sequence[str], cfg: EpisodeConfig, n_cameras: int) -> ComparePlan:
    """Check every spec before any sweep runs: :class:`CompareSpecError` for an unknown spec,
    a policy that does not fit ``n_cameras``, a budget (``mat:70@50``, ``deadline``) under
    the warm carry, a baseline ``cfg``'s backend cannot take, or an oracle without
    ``--carry fresh``."""
    oracles = []
    entries: list[tuple[TrainerOption | None, Policy | None]] = []
    for spec in specs:
        if is_oracle_spec(spec):
            try:
                oracle = parse_oracle(spec)
            except OracleSpecError as err:
                raise CompareSpecError(str(err)) from None
            if cfg.carry != "fresh":
                raise CompareSpecError(
                    f"{spec}: the oracle searches each scored decision on its own, which needs "
                    f"--carry fresh (a fresh model per scored decision), not {cfg.carry!r}")
            oracles.append(oracle)
            continue
        trainer = None
        policy_spec = spec
        if is_trainer_spec(spec):
            try:
                option, policy_spec = split_baseline(spec)
            except TrainerSpecError as err:
                raise CompareSpecError(str(err)) from None
            try:
                field_config(cfg.backend, **{**cfg.field, **option.field_overrides()})
            except (TypeError, ValueError) as err:
                raise CompareSpecError(
                    f"{spec}: the {cfg.backend!r} backend cannot take it ({err}); the "
                    "timeliness embedding (tembed) needs the grid backend") from None
            trainer = option
        policy = None if policy_spec == MAT_BEST else _fitting_policy(policy_spec, n_cameras,
                                                                      spec)
        if policy is not None and (policy.budget_steps is not None
                                   or getattr(policy, "chooses_budget", False)):
            try:
                check_budget_applies(cfg)  # a budget needs a carry that spends one
            except ValueError as err:
                raise CompareSpecError(f"{spec}: {err} (--carry fresh, stream or fork)"
                                       ) from None
        entries.append((trainer, policy))
    return ComparePlan(entries, oracles)


def _fitting_policy(spec: str, n_cameras: int, given: str) -> Policy:
    try:
        policy = parse_policy(spec)
        policy.check_fits(n_cameras)  # e.g. a ppo checkpoint for another N
        return policy
    except PolicySpecError as err:
        where = "" if spec == given else f"in {given!r}: "
        raise CompareSpecError(f"{where}{err}") from None


def bound_doc(bound: OracleOutcome, results: Sequence[EpisodeResult]) -> dict[str, Any]:
    """What results.json says of one oracle bound: the search, its cost, and for every
    metric of :data:`OPTIMUM_METRICS` each policy's paired distance to it (bound − policy in
    the metric's better direction: positive where the bound is better), over the seeds both
    have."""
    search, metric = bound.spec.split(":")[1:]
    minus: dict[str, dict[str, Any]] = {}
    for name in OPTIMUM_METRICS:
        sign = sign_of(name)

        def per_seed(rs: Sequence[EpisodeResult], name: str = name, sign: float = sign
                     ) -> dict[int, float]:
            return {r.seed: sign * getattr(r, name) for r in rs
                    if getattr(r, name) is not None}

        mine = per_seed(bound.results)
        by_policy: dict[str, list[EpisodeResult]] = {}
        for r in results:
            by_policy.setdefault(r.policy, []).append(r)
        minus[name] = {p: paired_difference(mine, per_seed(rs)).to_dict()
                       for p, rs in by_policy.items()}
    return {"kind": "bound", "search": search, "metric": metric,
            "note": "searched with the ground truth at each scored decision: a bound on "
                    "frame selection, not a policy a scheduler could run",
            "cost": bound.cost(), "minus": minus}


@dataclass(frozen=True)
class CompareResult:
    """The policies' and the bounds' episodes side by side: one aggregate row per label
    (``bound`` true for an oracle's), the policies' optimum set per metric (the bounds left
    out), and each bound's :func:`bound_doc`."""

    results: list[EpisodeResult]
    bounds: list[OracleOutcome]
    rows: list[dict[str, Any]]
    optima: dict[str, Optimum]
    bound_docs: dict[str, dict[str, Any]]

    @classmethod
    def of(cls, results: Sequence[EpisodeResult], bounds: Sequence[OracleOutcome]
           ) -> CompareResult:
        results = list(results)
        rows = aggregate(results + [r for b in bounds for r in b.results])
        bound_labels = {b.spec for b in bounds}
        for row in rows:
            row["bound"] = row["policy"] in bound_labels
        optima = sweep_optima(results) if results else {}
        return cls(results, list(bounds), rows, optima,
                   {b.spec: bound_doc(b, results) for b in bounds})

    @property
    def labels(self) -> list[str]:
        """The policies' labels, in the order of their results."""
        return list(dict.fromkeys(r.policy for r in self.results))

    @property
    def episodes(self) -> list[EpisodeResult]:
        """Every episode: the policies', then the bounds'."""
        return self.results + [r for b in self.bounds for r in b.results]

    def document(self, as_json: dict[str, dict[str, Any]]) -> dict[str, Any]:
        """The command's part of results.json: the rows with each label's JSON, the optimum
        sets and the bounds."""
        return {"policies": [{**r, "policy_json": as_json.get(r["policy"])} for r in self.rows],
                "optimum": {m: o.to_dict() for m, o in self.optima.items()},
                "bound": self.bound_docs}
