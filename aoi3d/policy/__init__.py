"""Frame-selection policies over the AoI vector, and the one decision step that applies them.

Importing this package registers every policy kind (see :mod:`aoi3d.policy.base` for the
families and how a new kind registers), in this order: ``all``, ``mat:<ms>``,
``freshest:<k>`` (:mod:`~aoi3d.policy.rules`), ``wait:<ms>`` (:mod:`~aoi3d.policy.wait`),
``ppo:<checkpoint>`` (:mod:`~aoi3d.policy.ppo`, the PPO agent's home: its acting side and its
learning side; torch loads only with a checkpoint) and ``adaptive:plugin`` /
``adaptive:bandit`` (:mod:`~aoi3d.policy.adaptive`, a Γ that follows the channel), and the
compute-aware ``dmat:<ms>`` and ``deadline:<ms>:<deadline_ms>`` (:mod:`~aoi3d.policy.display`,
which read the lag from a decision to its display). Any spec takes a training budget,
``<spec>@<steps>`` (:mod:`~aoi3d.policy.budget`).
:func:`~aoi3d.policy.decide.decide` is the decision step every setting uses. This package
imports nothing from :mod:`aoi3d.rl` or :mod:`aoi3d.experiment`: they build on it (an
import contract in pyproject.toml checks it).
"""

from aoi3d.policy import adaptive, display, ppo, rules, wait
from aoi3d.policy.adaptive import BanditPolicy, PluginPolicy
from aoi3d.policy.base import (
    ACCEPTED_FORMS,
    FAMILIES,
    POLICY_FAMILIES,
    BasePolicy,
    Budgeted,
    Policy,
    PolicyKind,
    PolicySpecError,
    as_aoi_vector,
    family_of,
    kind_of,
    parse_policy,
    policy_from_json,
    register_family,
    register_policy,
    short_label,
)
from aoi3d.policy.budget import (
    BUDGET_MAX_STEPS,
    DisplayLag,
    LagEstimator,
    check_budget,
)
from aoi3d.policy.decide import Selection, decide
from aoi3d.policy.display import DeadlinePolicy, DisplayMatPolicy
from aoi3d.policy.ppo import PPOPolicy
from aoi3d.policy.rules import AllPolicy, FreshestPolicy, MatPolicy
from aoi3d.policy.wait import WaitPolicy

# One place, one order, whatever was imported first (the error messages list the forms so).
register_family(adaptive.FAMILY, "a rule whose parameter follows what it observes (Γ that "
                "follows the channel)", policies=True)
for _kind in (*rules.KINDS, wait.KIND, ppo.KIND, adaptive.KIND, *display.KINDS):
    register_policy(_kind)
del _kind

__all__ = [
    "ACCEPTED_FORMS",
    "BUDGET_MAX_STEPS",
    "FAMILIES",
    "POLICY_FAMILIES",
    "AllPolicy",
    "BanditPolicy",
    "BasePolicy",
    "Budgeted",
    "DeadlinePolicy",
    "DisplayLag",
    "DisplayMatPolicy",
    "FreshestPolicy",
    "LagEstimator",
    "MatPolicy",
    "PPOPolicy",
    "PluginPolicy",
    "Policy",
    "PolicyKind",
    "PolicySpecError",
    "Selection",
    "WaitPolicy",
    "as_aoi_vector",
    "check_budget",
    "decide",
    "family_of",
    "kind_of",
    "parse_policy",
    "policy_from_json",
    "register_family",
    "register_policy",
    "short_label",
]
