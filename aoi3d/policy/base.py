"""The policy interface, its errors, the registry of policy kinds, and the questions a
caller asks a policy.

A policy looks at the AoI vector Δ(t) (ms, NaN = unknown) at a decision time and selects the
cameras whose newest frames the trainer uses. Every policy has a canonical text spec
(``mat:51``) and a JSON form (``{"kind": "mat", "mat_ms": 51}``); both round-trip through
``parse_policy`` / ``policy_from_json``.

A new kind plugs in in one step: implement ``Policy`` (most simply by subclassing
:class:`BasePolicy`, which answers the optional questions with the defaults of a policy that
has none of these needs) and call ``register_policy(PolicyKind(kind, form, from_args,
from_json, family=...))``; nothing here changes. Stateful policies clear their per-episode
state in ``reset()``.

**Families.** Every registered kind belongs to one family of :data:`FAMILIES`: ``rule`` (a
fixed selection rule: ``all``, ``mat``, ``freshest``, ``wait``), ``learned`` (it learns, or
was trained: ``ppo``), ``baseline`` (a trainer option of the follow-up paper over a policy:
``tembed``, ``wsum``; :mod:`aoi3d.experiment.baselines` registers them) and ``bound``
(searched with the truth, not a policy: ``oracle``; :mod:`aoi3d.experiment.oracle`).
:func:`parse_policy` builds only the policy families' kinds (:data:`POLICY_FAMILIES`); the
others are known so that every label of a result can be asked its kind and family
(:func:`kind_of`), which is how claims, figures and benches tell a rule from a learned policy
or a bound — never by a prefix of the label. A new family is one call,
:func:`register_family`.

Besides selecting, a policy answers the questions its callers have:

- ``wait_ms`` (int ≥ 0, default 0): how long after the decision epoch t the policy selects
  (the AoI is taken, and the render scored, at t + ``wait_ms``);
- ``check_fits(n_cameras)``: raise ``PolicySpecError`` when the policy cannot serve a rig of
  N cameras (default: it can);
- ``on_device(device)``: the policy with its model on a torch device (``auto``, ``cpu``,
  ``cuda``; default: the policy itself, it has no model);
- ``learns`` (bool, default False): whether the policy asks its caller to keep learning from
  the rewards of its decisions (such a policy — ``ppo`` with ``learn`` — names its agent by
  ``checkpoint`` and ``device``, which :class:`aoi3d.rl.online.OnlineLearner` loads);
- ``gamma_ms`` (float or None, default None): Γ, the maximum acceptable AoI of the rule the
  policy applies (``mat``'s; an adaptive policy's Γ in force), for a caller that reports it;
- ``observe(now_ms, deliveries)`` (default: ignore): called by the decision step at every
  decision with the time s the decision is for and the frames delivered since the previous
  decision, ``(camera index, generation ms, delivery ms)`` each — what an adaptive policy
  estimates the channel from (:mod:`aoi3d.policy.adaptive`);
- ``wants_quality`` (bool, default False) and ``observe_quality(time_ms, scores)`` (default:
  ignore): a policy rewarded by the quality of its renders (the bandit over Γ) is told the
  scores of the render made for ``time_ms`` once it is scored — on the virtual clock by the
  stepwise episode (:func:`aoi3d.experiment.adaptive.run_stepwise`), live by the scheduler
  from the ``quality`` topic;
- ``budget_steps`` (default None) and ``budget_for(aoi_ms)`` (default: that): the decision's
  training steps (None: the caller's default; :mod:`aoi3d.policy.budget`); ``<spec>@<steps>``
  gives any policy a fixed one (:class:`Budgeted`);
- ``observe_lag(lag)`` (default: ignore): the expected lag from the decision to its display,
  told before it selects — what a compute-aware policy (``dmat``) selects on.

So a caller asks the policy, never switches on its kind: only the registry knows the kinds.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from aoi3d.policy.budget import DisplayLag, check_budget, split_budget


class PolicySpecError(ValueError):
    """A policy spec or JSON form is invalid; the message lists the accepted forms."""

    def __init__(self, problem: str, spec: object = None) -> None:
        where = f"bad policy spec {spec!r}: " if spec is not None else "bad policy: "
        super().__init__(f"{where}{problem}. Accepted forms: {', '.join(ACCEPTED_FORMS)}; "
                         "any of them with '@<steps>', a training budget (mat:70@50).")
        self.problem = problem
        self.spec = spec


@runtime_checkable
class Policy(Protocol):
    """Selects cameras from the AoI vector (NaN, unknown, AoI is never selected), and answers
    its callers' questions (see the module docstring)."""

    @property
    def kind(self) -> str: ...

    @property
    def spec(self) -> str: ...

    @property
    def wait_ms(self) -> int:
        """How long after the decision epoch the policy selects (ms, ≥ 0)."""
        ...

    @property
    def learns(self) -> bool:
        """Whether the caller should keep learning from the rewards of its decisions."""
        ...

    @property
    def gamma_ms(self) -> float | None:
        """Γ of the MAT rule the policy applies (ms); None for a policy without one."""
        ...

    @property
    def wants_quality(self) -> bool:
        """Whether the policy is to be told the quality of its renders."""
        ...

    def observe(self, now_ms: float, deliveries: Sequence[tuple[int, float, float]]) -> None:
        """The frames delivered since the previous decision, before deciding for ``now_ms``."""
        ...

    def observe_quality(self, time_ms: float, scores: Mapping[str, float | None]) -> None:
        """The scores of the render made for ``time_ms`` (``psnr_db``, ``ssim``, ``reward``,
        ``psnr_dynamic_db``; None where not measured)."""
        ...

    @property
    def budget_steps(self) -> int | None:
        """The policy's fixed budget (training steps); None: the caller's default."""
        ...

    def observe_lag(self, lag: DisplayLag) -> None:
        """The expected lag from the coming decision to its display, before it selects."""
        ...

    def budget_for(self, aoi_ms: np.ndarray) -> int | None:
        """The budget of the decision on ``aoi_ms`` (None: the caller's default)."""
        ...

    def select(self, aoi_ms: np.ndarray) -> np.ndarray:
        """Boolean mask over the cameras of ``aoi_ms`` (same order)."""
        ...

    def to_json(self) -> dict[str, Any]:
        """The REST form, ``{"kind": ..., <params>}``."""
        ...

    def reset(self) -> None:
        """Start a new episode (no-op for stateless policies)."""
        ...

    def check_fits(self, n_cameras: int) -> None:
        """Raise ``PolicySpecError`` unless the policy can serve a rig of ``n_cameras``."""
        ...

    def on_device(self, device: str) -> Policy:
        """The policy with its model on ``device`` (``auto``, ``cpu``, ``cuda``);
        ``PolicySpecError`` when the device cannot be had."""
        ...


class BasePolicy:
    """The answers of a policy without a wait, a model, learning, a Γ or observations; a kind
    subclasses it and overrides what differs (``kind``, ``spec``, ``select`` and ``to_json``
    it must define)."""

    if TYPE_CHECKING:  # read-only, as in Policy: a kind may answer with a property instead
        @property
        def wait_ms(self) -> int: ...
        @property
        def learns(self) -> bool: ...
        @property
        def gamma_ms(self) -> float | None: ...
        @property
        def wants_quality(self) -> bool: ...
        @property
        def budget_steps(self) -> int | None: ...
    else:
        wait_ms: int = 0
        learns: bool = False
        gamma_ms: float | None = None
        wants_quality: bool = False
        budget_steps: int | None = None

    def reset(self) -> None:
        """Stateless between episodes."""

    def observe(self, now_ms: float, deliveries: Sequence[tuple[int, float, float]]) -> None:
        """Sees nothing but the AoI vector."""

    def observe_quality(self, time_ms: float, scores: Mapping[str, float | None]) -> None:
        """Not rewarded."""

    def observe_lag(self, lag: DisplayLag) -> None:
        """Blind to the lag to the display."""

    def budget_for(self, aoi_ms: np.ndarray) -> int | None:
        """Its fixed budget, if any: no per-decision choice."""
        return self.budget_steps

    def check_fits(self, n_cameras: int) -> None:
        """Any rig."""

    def on_device(self, device: str) -> Policy:
        """No model to place: the policy itself."""
        return self  # type: ignore[return-value]


@dataclass(frozen=True, eq=False)
class Budgeted:
    """A policy with a fixed budget: ``<spec>@<steps>``. It selects, waits, learns and
    observes as its inner policy does; its decisions train ``steps`` steps."""

    inner: Policy
    steps: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "steps", check_budget(self.steps))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Budgeted) and (other.steps, other.inner) == (self.steps,
                                                                             self.inner)

    def __hash__(self) -> int:
        return hash(self.spec)

    @property
    def kind(self) -> str:
        return self.inner.kind

    @property
    def spec(self) -> str:
        return f"{self.inner.spec}@{self.steps}"

    @property
    def wait_ms(self) -> int:
        return self.inner.wait_ms

    @property
    def learns(self) -> bool:
        return self.inner.learns

    @property
    def gamma_ms(self) -> float | None:
        return self.inner.gamma_ms

    @property
    def wants_quality(self) -> bool:
        return self.inner.wants_quality

    @property
    def budget_steps(self) -> int:
        return self.steps

    def observe(self, now_ms: float, deliveries: Sequence[tuple[int, float, float]]) -> None:
        self.inner.observe(now_ms, deliveries)

    def observe_quality(self, time_ms: float, scores: Mapping[str, float | None]) -> None:
        self.inner.observe_quality(time_ms, scores)

    def observe_lag(self, lag: DisplayLag) -> None:
        self.inner.observe_lag(lag.at(self.steps))

    def budget_for(self, aoi_ms: np.ndarray) -> int:
        return self.steps

    def select(self, aoi_ms: np.ndarray) -> np.ndarray:
        return self.inner.select(aoi_ms)

    def to_json(self) -> dict[str, Any]:
        return {**self.inner.to_json(), "budget_steps": self.steps}

    def reset(self) -> None:
        self.inner.reset()

    def check_fits(self, n_cameras: int) -> None:
        self.inner.check_fits(n_cameras)

    def on_device(self, device: str) -> Budgeted:
        placed = self.inner.on_device(device)
        return self if placed is self.inner else Budgeted(placed, self.steps)



def as_aoi_vector(aoi_ms: np.ndarray | Sequence[float]) -> np.ndarray:
    """The AoI vector as a 1-D float64 array; ``ValueError`` for any other shape."""
    arr = np.asarray(aoi_ms, dtype=np.float64)
    if arr.ndim != 1:
        raise ValueError(f"aoi_ms must be a 1-D vector (one AoI per camera), got {arr.shape}")
    return arr


FAMILIES: dict[str, str] = {
    "rule": "a fixed selection rule",
    "learned": "a policy that learns or was trained",
    "baseline": "a trainer option over a policy (how the field learns, not which frames)",
    "bound": "searched with the truth: a bound, not a policy",
}
"""The families of kinds and what each means (:func:`register_family` adds one)."""
POLICY_FAMILIES: set[str] = {"rule", "learned"}
"""The families whose kinds are policies (:func:`parse_policy` builds them)."""


def register_family(name: str, meaning: str, *, policies: bool) -> None:
    """Declare a new family of kinds (``policies``: its kinds select frames, so
    :func:`parse_policy` builds them)."""
    if name in FAMILIES:
        raise ValueError(f"family {name!r} is already declared")
    FAMILIES[name] = meaning
    if policies:
        POLICY_FAMILIES.add(name)


@dataclass(frozen=True)
class PolicyKind:
    """One kind: its name, the spec form shown to users, how to build it from its spec fields
    and from its JSON form, its family (:data:`FAMILIES`) and, optionally, how a table names
    one of its labels when the label is long (``short``; default: the label itself)."""

    kind: str
    form: str  # as shown to users, e.g. "mat:<ms>"
    from_args: Callable[[list[str]], Any]  # the spec's fields after "kind:"
    from_json: Callable[[Mapping[str, Any]], Any]  # the JSON object without "kind"
    family: str = "rule"
    short: Callable[[str], str] | None = None

    @property
    def is_policy(self) -> bool:
        """Whether the kind's family selects frames (:data:`POLICY_FAMILIES`)."""
        return self.family in POLICY_FAMILIES


_REGISTRY: dict[str, PolicyKind] = {}
#: The accepted policy spec forms, in registration order (kept in step with
#: ``register_policy``); the other families' forms are not policies and are not listed.
ACCEPTED_FORMS: list[str] = []


def register_policy(kind: PolicyKind) -> None:
    """Make a kind known: ``parse_policy`` and ``policy_from_json`` build it when its family is
    a policy family, and :func:`kind_of` answers for its labels whatever its family."""
    if kind.kind in _REGISTRY:
        raise ValueError(f"policy kind {kind.kind!r} is already registered")
    if kind.family not in FAMILIES:
        raise ValueError(f"policy kind {kind.kind!r}: unknown family {kind.family!r} "
                         f"(declared: {', '.join(FAMILIES)}; register_family adds one)")
    _REGISTRY[kind.kind] = kind
    if kind.is_policy:
        ACCEPTED_FORMS.append(kind.form)


def kind_of(spec: str | Mapping[str, Any] | Policy) -> PolicyKind:
    """The registered kind of a label, a JSON form or a policy: ``mat:70`` → ``mat``,
    ``{"kind": "ppo", …}`` → ``ppo``, ``wsum:60@mat:130`` → ``wsum`` (a baseline),
    ``oracle:rules:reward`` → ``oracle`` (a bound). Reads the kind only (nothing is built, no
    checkpoint is loaded); ``PolicySpecError`` for a kind nobody registered."""
    if isinstance(spec, Mapping):
        name = spec.get("kind")
    elif isinstance(spec, str):
        name = spec.strip().split("@", 1)[0].split(":", 1)[0].strip()
    else:
        name = getattr(spec, "kind", None)
    entry = _REGISTRY.get(name.lower()) if isinstance(name, str) else None
    if entry is None:
        raise PolicySpecError(f"unknown kind {name!r}", spec if isinstance(spec, str) else None)
    return entry


def family_of(spec: str | Mapping[str, Any] | Policy) -> str:
    """The family (:data:`FAMILIES`) of a label, a JSON form or a policy."""
    return kind_of(spec).family


def short_label(spec: str) -> str:
    """A label's name for a table or a figure: its kind's ``short`` form (``ppo`` shortens a
    checkpoint path to its folder and file), else the label itself (also for an unknown
    kind)."""
    try:
        entry = kind_of(spec)
    except PolicySpecError:
        return spec
    return entry.short(spec) if entry.short is not None else spec


def _policy_entry(kind: str, spec: object) -> PolicyKind:
    entry = _REGISTRY.get(kind.lower())
    if entry is None:
        raise PolicySpecError(f"unknown kind {kind!r}", spec)
    if not entry.is_policy:
        raise PolicySpecError(f"{entry.kind} is a {entry.family} ({FAMILIES[entry.family]}), "
                              "not a policy", spec)
    return entry


def parse_policy(spec: str | Policy) -> Policy:
    """Build a policy from its spec (``all``, ``mat:51``, ``freshest:6``, …); a policy passes
    through. Raises ``PolicySpecError`` (a ``ValueError``) listing the accepted forms."""
    if isinstance(spec, Policy) and not isinstance(spec, str):
        return spec
    if not isinstance(spec, str):
        raise PolicySpecError(f"expected a string, got {type(spec).__name__}", spec)
    text = spec.strip()
    if not text:
        raise PolicySpecError("empty spec", spec)
    head, budget = split_budget(text)
    if budget is not None:
        inner = parse_policy(head) if head else None
        if inner is None:
            raise PolicySpecError("nothing before the budget '@'", spec)
        return _with_budget(inner, budget, spec)
    kind, *fields = (part.strip() for part in text.split(":"))
    entry = _policy_entry(kind, spec)
    try:
        policy: Policy = entry.from_args(fields)
        return policy
    except PolicySpecError as err:
        raise PolicySpecError(err.problem, spec) from None


def policy_from_json(data: Mapping[str, Any]) -> Policy:
    """Build a policy from its REST form, e.g. ``{"kind": "mat", "mat_ms": 51}``."""
    if not isinstance(data, Mapping):
        raise PolicySpecError(f"expected a JSON object, got {type(data).__name__}", data)
    kind = data.get("kind")
    if not isinstance(kind, str):
        raise PolicySpecError('missing or non-string "kind"', dict(data))
    if (steps := data.get("budget_steps")) is not None:
        if isinstance(steps, str):  # as every number of a JSON form: not a string
            raise PolicySpecError(f"budget_steps must be a JSON integer, got {steps!r}", dict(data))
        inner = policy_from_json({k: v for k, v in data.items() if k != "budget_steps"})
        return _with_budget(inner, steps, dict(data))
    entry = _policy_entry(kind, dict(data))
    params = {k: v for k, v in data.items() if k not in ("kind", "budget_steps")}
    try:
        policy: Policy = entry.from_json(params)
        return policy
    except PolicySpecError as err:
        raise PolicySpecError(err.problem, dict(data)) from None


def _with_budget(inner: Policy, steps: object, spec: object) -> Policy:
    """``inner`` with a fixed budget; ``PolicySpecError`` for a bad one, or a second one."""
    if inner.budget_steps is not None:
        raise PolicySpecError("a policy has one budget ('@<steps>' once)", spec)
    if getattr(inner, "chooses_budget", False):
        raise PolicySpecError(f"{inner.kind} chooses each decision's budget itself: no "
                              "'@<steps>'", spec)
    if isinstance(steps, str):
        text = steps.strip()
        if not (text.isascii() and text.isdigit()):  # not '²', which int() refuses
            raise PolicySpecError(f"budget {text!r} after '@' is not a whole number of "
                                  "training steps", spec)
        steps = int(text)
    try:
        return Budgeted(inner, steps)  # type: ignore[arg-type]  # checked by check_budget
    except ValueError as err:
        raise PolicySpecError(str(err), spec) from None


# Helpers for kinds' parsers: each raises PolicySpecError with a precise problem.


def expect_fields(kind: str, fields: list[str], names: Sequence[str]) -> list[str]:
    if len(fields) != len(names):
        form = ":".join([kind, *(f"<{n}>" for n in names)])
        raise PolicySpecError(f"{kind} takes {len(names)} parameter(s) ({form}), got {len(fields)}")
    return fields


def expect_keys(kind: str, params: Mapping[str, Any], keys: Sequence[str]) -> None:
    missing = [k for k in keys if k not in params]
    extra = sorted(k for k in params if k not in keys)
    if missing:
        raise PolicySpecError(f"{kind} needs key(s) {missing}")
    if extra:
        raise PolicySpecError(f"{kind} does not take key(s) {extra}")


def number(name: str, value: Any, *, minimum: float = -math.inf) -> float:
    """A finite number >= ``minimum`` (a spec field or a JSON number; not a bool)."""
    x: float
    if isinstance(value, str):
        try:
            x = float(value)
        except ValueError:
            raise PolicySpecError(f"{name} must be a number, got {value!r}") from None
    elif isinstance(value, int | float | np.integer | np.floating) and not isinstance(
        value, bool
    ):
        x = float(value)
    else:
        raise PolicySpecError(f"{name} must be a number, got {value!r}")
    if not math.isfinite(x):
        raise PolicySpecError(f"{name} must be finite, got {value!r}")
    if x < minimum:
        raise PolicySpecError(f"{name} must be >= {minimum:g}, got {value!r}")
    return x


def integer(name: str, value: Any, *, minimum: int = 0) -> int:
    """A whole number >= ``minimum`` (``"6"``, ``6`` or ``6.0``; not ``6.5`` or a bool)."""
    x = number(name, value)
    if not x.is_integer():
        raise PolicySpecError(f"{name} must be a whole number, got {value!r}")
    if x < minimum:
        raise PolicySpecError(f"{name} must be >= {minimum}, got {value!r}")
    return int(x)
